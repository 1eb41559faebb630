"""The 3-D PSF metrics (``arraysel.objective.metrics3d``) on a batch of synthetic plane sets.

Times ``psf3d_metrics`` (every name: the Table-1 terms, ``PSL_dB`` and the -6 dB widths) on
``--masks`` plane sets of three ``--size`` x ``--size`` planes (C-plane, xz, yz; a sinc-shaped
main lobe with random side lobes, so the peaks sit at the scatterer), next to the 1-D
``psf_metrics`` (torch's operations and the compiled pass) on as many kernels of the same pixel
count, alternated ``--rounds`` times in one process, no gradient.

Usage::

    python benchmarks/bench_metrics3d.py [--masks 256] [--size 64] [--rounds 3] [--threads 2]

The last output line is a JSON record.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as C  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--masks", type=int, default=256, help="plane sets per call (default 256)")
    p.add_argument("--size", type=int, default=64, help="pixels per side of each plane (default 64)")
    p.add_argument("--rounds", type=int, default=3, help="alternations (default 3)")
    p.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    a = p.parse_args(argv)
    C.set_threads(a.threads)
    import numpy as np
    import torch

    from arraysel.objective.metrics import psf_metrics
    from arraysel.objective.metrics3d import psf3d_metrics

    lam, pitch, z0, n = 0.513e-3, 0.1e-3, 30e-3, a.size
    ax = (np.arange(n) - n // 2) * pitch
    coords = {}
    yy, xx = np.meshgrid(ax, ax, indexing="ij")
    coords["xy"] = np.stack([xx, yy, np.full_like(xx, z0)], -1)
    zz, xx = np.meshgrid(z0 + ax, ax, indexing="ij")
    coords["xz"] = np.stack([xx, np.zeros_like(xx), zz], -1)
    zz, yy = np.meshgrid(z0 + ax, ax, indexing="ij")
    coords["yz"] = np.stack([np.zeros_like(yy), yy, zz], -1)
    g = torch.Generator().manual_seed(0)

    def psf(c):
        x, y, z = (torch.as_tensor(c[..., i]) for i in range(3))
        lobe = torch.sinc(x / 1.6e-3) * torch.sinc(y / 1.6e-3) * torch.exp(-((z - z0) / 0.4e-3) ** 2)
        return (lobe * torch.exp(2j * math.pi * 2 * (z - z0) / lam)).to(torch.complex64)

    planes = {k: psf(c)[None] + 0.01 * torch.randn(a.masks, n, n, dtype=torch.complex64, generator=g)
              for k, c in coords.items()}
    ref = {k: psf(c)[None] for k, c in coords.items()}
    side = int(round(math.sqrt(3 * n * n)))
    flat = torch.randn(a.masks, side, side, dtype=torch.complex64, generator=g) * 0.01
    flat[:, side // 2, side // 2] += 1
    settings = {
        "3-D (three planes)": lambda: psf3d_metrics(planes, coords, wavelength=lam, planes_ref=ref, r_main=1.5,
                                                    r_guard=3.5),
        "1-D torch (same pixels)": lambda: psf_metrics(flat, pitch=pitch, wavelength=lam, kappa_ref=flat[0],
                                                       compiled=False),
        "1-D compiled (same pixels)": lambda: psf_metrics(flat, pitch=pitch, wavelength=lam, kappa_ref=flat[0],
                                                          compiled=True),
    }
    with torch.no_grad():
        for fn in settings.values():  # warm-up
            fn()
        times = {name: [] for name in settings}
        for r in range(a.rounds):
            order = list(settings) if r % 2 == 0 else list(reversed(settings))
            for name in order:
                t = time.perf_counter()
                settings[name]()
                times[name].append((time.perf_counter() - t) / a.masks * 1e3)
    rows = [[name, statistics.median(v), min(v)] for name, v in times.items()]
    print(f"{a.masks} sets of 3 x {n} x {n} pixels ({3 * n * n} a set); 1-D kernels {side} x {side}")
    print(C.table(rows, ["setting", "median ms/mask", "best ms/mask"]))
    C.emit_json({"benchmark": "metrics3d", "masks": a.masks, "size": n,
                 "ms_per_mask": {name: statistics.median(v) for name, v in times.items()}, **C.machine()})


if __name__ == "__main__":
    main()
