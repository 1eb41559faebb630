"""Peak memory and time of the exact PSF path against its own estimates.

Builds a scene's objective with the fast path off, evaluates ``--masks``
random k-subsets with ``ARRAYSEL_MEMORY_GIB`` set to ``--memory-gib`` and
prints, per field point, the batch and DAS sub-chunk the exact path chose,
the estimated peak (``PSFModel.exact_bytes``), the measured peak resident
memory of the process (``ru_maxrss``, which ``/usr/bin/time -v`` reports as
"Maximum resident set size") and the estimated and measured wall time.

Usage::

    python benchmarks/exact_memory.py --scene l11-5v --masks 64 --memory-gib 2

The last output line is a JSON record.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import time


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default="l11-5v")
    p.add_argument("--masks", type=int, default=64)
    p.add_argument("--memory-gib", type=float, default=None, help="ARRAYSEL_MEMORY_GIB (default: as set)")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.memory_gib is not None:
        os.environ["ARRAYSEL_MEMORY_GIB"] = str(args.memory_gib)
    import numpy as np
    import torch

    from arraysel.io.allocator import tune_malloc
    from arraysel.objective.psf_objective import Objective

    tune_malloc()
    if args.threads:
        torch.set_num_threads(args.threads)
    obj = Objective(args.scene, fast=False)
    rng = np.random.default_rng(args.seed)
    masks = np.zeros((args.masks, obj.n_elements))
    for row in masks:
        row[rng.choice(obj.n_elements, obj.k, replace=False)] = 1
    est_s = obj.estimate_seconds(args.masks)
    batch = [p.masks_per_batch() for p in obj.psfs]
    chunk = [p.exact_chunking()[1] for p in obj.psfs]
    est_b = max(p.exact_bytes(min(args.masks, b)) for p, b in zip(obj.psfs, batch))
    t0 = time.perf_counter()
    res = obj.evaluate(masks)
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    rec = {"scene": args.scene, "masks": args.masks, "memory_cap_gib": obj.psf.memory_limit / 2 ** 30,
           "batch": batch, "das_pixels": chunk, "estimate_gib": est_b / 2 ** 30, "peak_rss_gib": peak / 2 ** 30,
           "estimate_over_peak": est_b / peak, "estimate_s": est_s, "wall_s": wall,
           "finite": bool(np.isfinite(res["Mean"]).all())}
    print(f"scene {args.scene}: {args.masks} masks, cap {rec['memory_cap_gib']:.2f} GiB, batch {batch}, "
          f"DAS sub-chunk {chunk} px")
    print(f"memory: estimate {rec['estimate_gib']:.2f} GiB, measured peak {rec['peak_rss_gib']:.2f} GiB "
          f"(estimate / peak = {rec['estimate_over_peak']:.2f})")
    print(f"time: estimate {est_s:.1f} s, measured {wall:.1f} s")
    print(json.dumps(rec))


if __name__ == "__main__":
    main()
