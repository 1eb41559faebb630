"""The fast path against the exact path on any scene: kernels, Table-1 Means and fallbacks.

For each scene (built-in name or TOML file), 12 masks: uniform, one random, 'edges' (the k/2
outermost elements on each side), 'centre' (the k middle ones) and ``--random`` more random
masks. Prints per mask the SI-MSE of the fast kernel against the exact path's, whether the fast
path fell back to the exact path, and both Means; then the largest SI-MSE per scene. The first
run on a scene builds its basis (a minute or two for 128 elements). ``benchmarks/scenes/`` holds
three scenes no built-in resembles (an off-axis point with an f-number on an L7-4, attenuation
and a 2-cycle pulse on a P6-3, a deep lateral point on a C5-2v with 9 plane waves).

Usage::

    python benchmarks/fast_vs_exact.py benchmarks/scenes/*.toml [--random 8] [--seed 7]

The last output line is a JSON record.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as C  # noqa: E402


def masks_for(ne: int, k: int, extra: int, seed: int) -> dict:
    """The four fidelity masks (random one of ``seed``) and ``extra`` more random ones."""
    out = C.named_masks(ne, k, random_seed=seed)
    out.update({f"rnd{i}": m for i, m in enumerate(C.random_masks(extra, ne, k, seed=seed + 1))})
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("scenes", nargs="+", help="built-in scene names or TOML files")
    p.add_argument("--random", type=int, default=8, help="random masks besides the four named ones (default 8)")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--threads", type=int, default=None)
    a = p.parse_args(argv)
    C.set_threads(a.threads)
    import numpy as np
    import torch

    from arraysel.objective.metrics import psf_metrics, si_mse
    from arraysel.objective.psf_objective import Objective
    from arraysel.scenes.schema import load_scene

    rows = []
    for name in a.scenes:
        t0 = time.perf_counter()
        obj = Objective(load_scene(name))
        setup_s = time.perf_counter() - t0
        masks = masks_for(obj.n_elements, obj.k, a.random, a.seed)
        w = torch.tensor(np.stack(list(masks.values())), dtype=obj.dtype)
        print(f"{name}: Ne {obj.n_elements}, k {obj.k}, {len(obj.psfs)} point(s), objective {setup_s:.1f} s")
        for point, model in enumerate(obj.psfs):
            if model.basis is None:
                print(f"  point {point}: no fast path (exact only)")
                continue
            with torch.no_grad():
                kf, fell_back = model.kernels(w, return_info=True)
                ke = model.kernels_exact(w)
            err = si_mse(kf.to(torch.complex128), ke.to(torch.complex128))
            ref = model.reference_kernel()
            mf = psf_metrics(kf, kappa_ref=ref.to(kf.dtype), **obj.metric_kw)["Mean"]
            me = psf_metrics(ke, kappa_ref=ref.to(ke.dtype), **obj.metric_kw)["Mean"]
            for i, m in enumerate(masks):
                print(f"  point {point} {m:8s} SI-MSE {float(err[i]):.2e} fallback {bool(fell_back[i])!s:5s} "
                      f"Mean fast {float(mf[i]):.6f} exact {float(me[i]):.6f}")
            rows.append({"scene": name, "point": point, "max_si_mse": float(err.max()),
                         "fallbacks": int(fell_back.sum()), "masks": len(masks),
                         "max_mean_diff": float((mf.double() - me.double()).abs().max())})
            print(f"  point {point}: max SI-MSE {float(err.max()):.2e}, {int(fell_back.sum())} fallback(s) "
                  f"of {len(masks)}")
    print(json.dumps({"machine": C.machine(), "rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
