"""Masks per second: arraysel's batched objective against a cached-DAS PyMUST pipeline.

Measured side by side in one run, on the paper scene (P4-2v, 7 plane waves,
400 x 400 grid, 128 x 128 kernel, random 32-of-64 masks):

(a) PyMUST (``tests/pymust_pipeline.py``): simus -> rf2iq -> DAS matrix
    product per transmit; the 7 DAS matrices are built by one warm-up mask
    (timed separately), then ``--pymust-masks`` masks are timed;
(b) arraysel: ``Objective.evaluate`` (PSF kernels + every Table-1 metric) on
    ``--masks`` masks, after the one-off precompute (pair basis, reference
    kernel, exact-path DAS plans), which is timed and reported separately, and
    a warm-up on ``--warmup-masks`` other random masks (also timed and
    reported), which fills the fast path's cache of 8 x 8-block DAS plans as a
    long search does: the figure is the rate of a long search, the way the
    PyMUST figure is that of cached DAS matrices;
(c) accuracy: the SI-MSE between arraysel's and PyMUST's kernels of the masks
    PyMUST computed, and the fraction of masks the fast path handed to the
    exact fallback (``Objective.fallbacks``).

Usage::

    python benchmarks/bench_psf.py [--masks 2048] [--pymust-masks 5] [--warmup-masks 1024]
        [--threads N] [--no-cache] [--no-malloc-tune]

The last output line is a JSON record; everything before it is for people.
"""
from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as C  # noqa: E402


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--masks", type=int, default=2048, help="masks evaluated by arraysel (default 2048)")
    p.add_argument("--pymust-masks", type=int, default=5, help="masks timed through PyMUST after the warm-up (default 5)")
    p.add_argument("--threads", type=int, default=None, help="torch / BLAS threads (default: library default)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random masks")
    p.add_argument("--warmup-masks", type=int, default=1024,
                   help="other random masks evaluated before the timing (default 1024; 0: none)")
    p.add_argument("--device", default="cpu", help="arraysel device (default cpu)")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--no-cache", action="store_true",
                   help="build the pair basis even if the on-disk cache ($ARRAYSEL_CACHE) holds it "
                        "(by default a cached basis is loaded and the precompute figure is the load time)")
    p.add_argument("--skip-pymust", action="store_true", help="arraysel figures only (no PyMUST, no accuracy)")
    p.add_argument("--no-malloc-tune", action="store_true",
                   help="leave glibc malloc at its defaults (arraysel.io.allocator; both pipelines run in "
                        "this process, so the setting applies to both)")
    a = p.parse_args(argv)
    if a.warmup_masks < 0:
        p.error("--warmup-masks must be >= 0")
    if a.masks < 1 or a.pymust_masks < 1:
        p.error("--masks and --pymust-masks must be >= 1")
    if a.pymust_masks + 1 > a.masks:
        p.error("--masks must be larger than --pymust-masks (PyMUST's masks are the first ones of the batch)")
    return a


def run_pymust(masks, n_timed):
    """(warm-up seconds, timed seconds, kernels of masks[:n_timed + 1])."""
    pp = C.load_pymust_pipeline()
    scene = pp.PyMUSTScene()
    with C.Timer() as tw:
        kernels = [scene.kernel(masks[0])]
    with C.Timer() as tt:
        for i in range(1, n_timed + 1):
            kernels.append(scene.kernel(masks[i]))
    return tw.s, tt.s, kernels


def main(argv=None):
    args = parse_args(argv)
    if args.no_malloc_tune:
        os.environ["ARRAYSEL_MALLOC_TUNE"] = "0"
    C.set_threads(args.threads)
    if args.no_cache:
        os.environ["ARRAYSEL_CACHE"] = "off"
    import numpy as np
    import torch

    from arraysel.io.allocator import tune_malloc
    from arraysel.objective.psf_objective import build_objective

    dtype = torch.float32 if args.dtype == "float32" else torch.float64
    masks = C.random_masks(args.masks, seed=args.seed)

    # (b0) one-off precompute: pair basis + certificate, reference kernel, exact-path DAS plans
    before = C.cache_files()
    with C.Timer() as t_basis:
        obj = build_objective("paper", device=args.device, dtype=dtype)
    source = C.basis_source(before)
    with C.Timer() as t_warm:
        obj.reference_kernel()
        obj.psf.kernels_exact(torch.as_tensor(masks[:1]))  # builds and caches the whole-grid DAS plans
        obj.evaluate(masks[:2])
    with C.Timer() as t_cache:
        if args.warmup_masks:
            obj.evaluate(C.random_masks(args.warmup_masks, seed=args.seed + 10_000))
    precompute_s = t_basis.s + t_warm.s
    fast = obj.psf.basis

    # (b) batched evaluation: kernels + every Table-1 metric
    obj.reset_counters()
    with C.Timer() as t_eval:
        res = obj.evaluate(masks)
    n_fb = obj.fallbacks
    arraysel_rate = args.masks / t_eval.s
    assert all(np.isfinite(v).all() for v in res.values())

    # (b') the fast path alone (certified or not), to show what the fallbacks cost
    fast_only_s = None
    if fast is not None and hasattr(fast, "kernels"):
        w = torch.as_tensor(masks, dtype=dtype, device=obj.device)
        with torch.no_grad(), C.Timer() as t_fast:
            for i in range(0, w.shape[0], obj.chunk):
                fast.kernels(w[i:i + obj.chunk])
        fast_only_s = t_fast.s

    rows = [
        ["arraysel precompute: fast-path basis + certificates", f"{t_basis.s:.1f} s",
         source],
        ["arraysel precompute: reference kernel, DAS plans", f"{t_warm.s:.1f} s", "one-off"],
        [f"arraysel warm-up: {args.warmup_masks} other masks", f"{t_cache.s:.1f} s",
         f"{args.warmup_masks / t_cache.s:.1f} masks/s" if args.warmup_masks else "none"],
        [f"arraysel evaluate ({args.masks} masks, {args.dtype}, {args.device})", f"{t_eval.s:.2f} s",
         f"{arraysel_rate:.1f} masks/s"],
        ["  masks sent to the exact fallback", f"{n_fb} / {args.masks}", f"{n_fb / args.masks:.2%}"],
    ]
    if fast_only_s is not None:
        rows.append([f"  fast path alone, no metrics ({args.masks} masks)", f"{fast_only_s:.2f} s",
                     f"{args.masks / fast_only_s:.1f} masks/s"])

    record = {}
    if not args.skip_pymust:
        # (a) PyMUST with cached DAS matrices
        warm_s, timed_s, kp = run_pymust(masks, args.pymust_masks)
        pymust_rate = args.pymust_masks / timed_s
        # (c) accuracy on the masks PyMUST computed (kernels through the public objective API)
        ka = obj.kernels(masks[: args.pymust_masks + 1]).to(torch.complex128).cpu().numpy()
        errs = [C.si_mse(ka[i], kp[i]) for i in range(len(kp))]
        rows = [
            ["PyMUST warm-up mask (builds 7 DAS matrices)", f"{warm_s:.1f} s", "one-off"],
            [f"PyMUST cached DAS ({args.pymust_masks} masks)", f"{timed_s:.1f} s", f"{pymust_rate:.3f} masks/s"],
        ] + rows + [
            ["speed-up arraysel / PyMUST", "", f"{arraysel_rate / pymust_rate:.0f} x"],
            [f"SI-MSE arraysel vs PyMUST ({len(kp)} masks)", f"max {max(errs):.2e}",
             f"median {float(np.median(errs)):.2e}"],
        ]
        record.update(pymust_masks_per_s=pymust_rate, arraysel_masks_per_s=arraysel_rate,
                      ratio=arraysel_rate / pymust_rate, max_si_mse_vs_pymust=max(errs))
    else:
        record.update(pymust_masks_per_s=None, arraysel_masks_per_s=arraysel_rate, ratio=None,
                      max_si_mse_vs_pymust=None)
    record.update(fallback_fraction=n_fb / args.masks, precompute_s=precompute_s)

    print("bench_psf: paper scene, random 32-of-64 masks (seed %d)" % args.seed)
    print("machine:", C.machine())
    print(C.table(rows, ["step", "time", "rate / note"]))
    record.update(masks=args.masks, pymust_masks=args.pymust_masks, dtype=args.dtype, device=args.device,
                  precompute_basis_s=t_basis.s, precompute_warmup_s=t_warm.s, evaluate_s=t_eval.s,
                  fast_path_only_s=fast_only_s, precompute_source=source, threads=torch.get_num_threads(),
                  warmup_masks=args.warmup_masks, warmup_s=t_cache.s,
                  malloc_tuned=tune_malloc())
    C.emit_json(record)


if __name__ == "__main__":
    main()
