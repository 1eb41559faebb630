"""The exact 3-D PSF of the 1024-element matrix probe against the PyMUST 3-D pipeline.

Measured side by side in one run: MATRIX-32x32 (3 MHz, 300 um pitch, 250 um elements), 9
diverging waves (tilts 3 x 3 over +-10 deg in x and y, virtual sources 10 mm behind the array),
one scatterer at (0, 0, 30 mm), three 64 x 64 planes (C-plane, xz, yz) of pixel lambda / 4:

(a) arraysel (``arraysel.physics.volume.MatrixPSF``): the one-off precompute (transmits, I/Q
    maps, DAS geometry), then the time per mask of ``planes`` without gradient for batches of
    ``--batch`` random 256-element masks (the first batch, which loads the compiled kernel, is
    reported apart), and one gradient (forward + backward of a scalar of the planes) of one mask;
(b) PyMUST (``tests/pymust_pipeline3.py``: simus3 -> rf2iq -> dasmtx3 per transmit): the 27 DAS
    matrices built by a warm-up mask (timed apart), then ``--pymust-masks`` masks timed;
(c) fidelity: the SI-MSE of each plane against PyMUST for the full array, the uniform mask (every
    second element in x and y: 256) and a random 256-element mask, in float32 and float64;
(d) memory: the resident peak (ru_maxrss) after (a), then after (b) (PyMUST's DAS matrices).

Usage::

    python benchmarks/bench_matrix_exact.py [--batch 8] [--masks 16] [--pymust-masks 3] [--threads N]

The last output line is a JSON record; everything before it is for people.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import load_tests_module, machine, peak_rss_gib, random_masks, set_threads  # noqa: E402


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--batch", type=int, default=8, help="masks per planes() call (default 8)")
    p.add_argument("--masks", type=int, default=16, help="random masks timed on the exact path (default 16)")
    p.add_argument("--pymust-masks", type=int, default=3, help="masks timed on PyMUST after its warm-up (default 3)")
    p.add_argument("--threads", type=int, default=None, help="torch / BLAS / numba threads (default: torch's)")
    a = p.parse_args(argv)
    set_threads(a.threads)
    if a.threads:
        import numba

        numba.set_num_threads(a.threads)
    import numpy as np
    import torch

    from arraysel.physics.probes import Acquisition, get_probe
    from arraysel.physics.volume import PLANES, MatrixPSF, MatrixPSFSetup, diverging_delays3, tilt_grid

    probe = get_probe("MATRIX-32x32")
    acq = Acquisition.for_probe(probe)
    lam = acq.c / probe.fc
    ax, ay = tilt_grid(3, 3, 10.0, 10.0)
    delays = diverging_delays3(probe, ax, ay, 10e-3, acq)
    setup = MatrixPSFSetup(probe, acq, delays, (0.0, 0.0, 30e-3), half_x=8 * lam, half_y=8 * lam,
                           half_z=8 * lam, pixel=lam / 4)
    rec = {"machine": machine(), "probe": probe.name, "n_tx": len(delays), "planes": "3 x 64 x 64",
           "pixel_m": setup.pixel}

    t = time.perf_counter()
    model = MatrixPSF(setup, dtype=torch.float32)
    rec["arraysel_precompute_s"] = round(time.perf_counter() - t, 2)
    assert all(tuple(c.shape[:2]) == (64, 64) for c in model.coords.values())
    masks = random_masks(a.masks + a.batch, 1024, 256, seed=1)
    with torch.no_grad():
        t = time.perf_counter()
        model.planes(torch.tensor(masks[:a.batch]))
        rec["arraysel_first_batch_s"] = round(time.perf_counter() - t, 2)
        t = time.perf_counter()
        for i in range(a.batch, a.batch + a.masks, a.batch):
            model.planes(torch.tensor(masks[i:i + a.batch]))
        rec["arraysel_s_per_mask"] = round((time.perf_counter() - t) / a.masks, 4)
    w = torch.tensor(masks[:1], dtype=torch.float32, requires_grad=True)
    t = time.perf_counter()
    out = model.planes(w)
    sum(v.abs().pow(2).sum() for v in out.values()).backward()
    rec["arraysel_grad_s"] = round(time.perf_counter() - t, 2)
    rec["arraysel_peak_rss_gib"] = round(peak_rss_gib(), 2)
    print(f"arraysel exact path: precompute {rec['arraysel_precompute_s']} s, first batch of {a.batch} "
          f"{rec['arraysel_first_batch_s']} s, then {rec['arraysel_s_per_mask']} s a mask (batches of {a.batch}), "
          f"one gradient {rec['arraysel_grad_s']} s; peak RSS {rec['arraysel_peak_rss_gib']} GiB")

    mod = load_tests_module("pymust_pipeline3")
    oracle = mod.PyMUSTScene3(probe, acq, delays, setup.scatterer, {k: v.numpy() for k, v in model.coords.items()})
    uni = np.zeros((32, 32))
    uni[::2, ::2] = 1
    named = {"full": np.ones(1024), "uniform": uni.ravel(), "random": masks[-1]}
    t = time.perf_counter()
    refs = {"full": oracle.planes(named["full"])}
    rec["pymust_first_mask_s"] = round(time.perf_counter() - t, 2)
    rec["pymust_das_build_s"] = round(oracle.das_seconds, 2)
    t = time.perf_counter()
    for i in range(a.pymust_masks):
        oracle.planes(masks[i])
    rec["pymust_s_per_mask"] = round((time.perf_counter() - t) / max(1, a.pymust_masks), 3)
    rec["pymust_peak_rss_gib"] = round(peak_rss_gib(), 2)
    print(f"PyMUST: first mask {rec['pymust_first_mask_s']} s (DAS matrices {rec['pymust_das_build_s']} s), "
          f"then {rec['pymust_s_per_mask']} s a mask; peak RSS after it {rec['pymust_peak_rss_gib']} GiB")
    rec["speedup_per_mask"] = round(rec["pymust_s_per_mask"] / rec["arraysel_s_per_mask"], 1)
    print(f"exact path vs PyMUST, a mask: {rec['speedup_per_mask']}x")

    for name in ("uniform", "random"):
        refs[name] = oracle.planes(named[name])
    fid = {}
    m64 = MatrixPSF(setup, dtype=torch.float64)
    for label, m in (("float32", model), ("float64", m64)):
        with torch.no_grad():
            got = m.planes(torch.tensor(np.stack(list(named.values()))))
        for i, name in enumerate(named):
            for plane in PLANES:
                ours = got[plane][i].to(torch.complex128).numpy()
                fid[f"{label}/{name}/{plane}"] = mod.si_mse(ours, refs[name][plane])
    rec["si_mse"] = {k: float(f"{v:.3g}") for k, v in fid.items()}
    print("SI-MSE per plane against PyMUST:")
    for k, v in rec["si_mse"].items():
        print(f"  {k:24s} {v:.3g}")
    print(json.dumps(rec))
    return rec


if __name__ == "__main__":
    main()
