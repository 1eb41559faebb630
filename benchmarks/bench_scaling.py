"""Masks per second of random search with 1, 2 and 4 local workers.

Usage::

    python benchmarks/bench_scaling.py                      # toy objective, process pool
    python benchmarks/bench_scaling.py --executor dask      # Dask LocalCluster on 127.0.0.1
    python benchmarks/bench_scaling.py --scene paper --masks 2048 --chunk 64

For each worker count the executor is started and warmed up (every worker
builds its objective) before the timed searches, so the numbers are the steady
rate, not start-up; the fastest of ``--repeat`` searches counts. The in-process rate (no executor) is the reference. The
best mask must be the same for every worker count; the script checks it.
Prints one JSON line, then a table.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="toy", help="toy (default) or a scene name/file, e.g. paper")
    p.add_argument("--executor", choices=("process", "dask"), default="process")
    p.add_argument("--workers", default="1,2,4", help="comma-separated worker counts (default 1,2,4)")
    p.add_argument("--masks", type=int, default=None, help="masks per search (default toy 200000, else 1024)")
    p.add_argument("--chunk", type=int, default=None, help="masks per task (default toy 4096, else 64)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--repeat", type=int, default=3, help="timed searches per setting; the fastest counts "
                   "(the machine may be shared)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--dtype", default="float32")
    args = p.parse_args(argv)

    from arraysel.objective.psf_objective import SceneObjectiveFactory
    from arraysel.objective.toy import ToyObjectiveFactory
    from arraysel.run.executors import DaskExecutor, ProcessExecutor
    from arraysel.run.random_search import distributed_random_search

    toy = args.scene == "toy"
    masks = args.masks or (200_000 if toy else 1024)
    chunk = args.chunk or (4096 if toy else 64)
    if toy:
        factory = ToyObjectiveFactory(64, 32, device=args.device, dtype=args.dtype)
    else:
        from arraysel.scenes.schema import load_scene
        factory = SceneObjectiveFactory(load_scene(args.scene).to_dict(), device=args.device, dtype=args.dtype)
    counts = [int(w) for w in args.workers.split(",") if w.strip()]

    import torch

    rows = []
    default_threads = torch.get_num_threads()
    distributed_random_search(factory, min(masks, chunk), None, args.seed, None, chunk)  # build + warm
    ref = None
    # in-process twice: with torch's default intra-op threads, and with one thread (what each
    # worker process gets when there are as many workers as cores: torch, numba and BLAS alike)
    from arraysel.run.template import thread_counts

    for threads in dict.fromkeys([default_threads, 1]):
        with thread_counts(threads):
            res = min((distributed_random_search(factory, masks, None, args.seed, None, chunk)
                       for _ in range(args.repeat)), key=lambda r: r.seconds)
        ref = ref or res
        rows.append({"executor": f"in-process/{threads}t", "workers": 1, "seconds": res.seconds,
                     "masks_per_second": res.masks_per_second, "startup_s": 0.0,
                     "best_mean": res.mean, "same_best": res.elements == ref.elements})
    for w in counts:
        t0 = time.perf_counter()
        ex = ProcessExecutor(workers=w) if args.executor == "process" else DaskExecutor(workers=w)
        try:
            # warm-up: every worker builds its objective and runs torch once
            distributed_random_search(factory, chunk * w * 2, None, args.seed + 1, ex, chunk)
            startup = time.perf_counter() - t0
            res = min((distributed_random_search(factory, masks, None, args.seed, ex, chunk)
                       for _ in range(args.repeat)), key=lambda r: r.seconds)
        finally:
            ex.close()
        per = max(1, (os.cpu_count() or 1) // w)
        rows.append({"executor": f"{args.executor}/{per}t" if args.executor == "process" else "dask/1t",
                     "workers": w, "seconds": res.seconds,
                     "masks_per_second": res.masks_per_second, "startup_s": startup,
                     "best_mean": res.mean, "same_best": res.elements == ref.elements})

    base = rows[0]["masks_per_second"]
    for r in rows:
        r["speedup"] = r["masks_per_second"] / base
    info = {"benchmark": "random_search_scaling", "scene": args.scene, "masks": masks, "chunk": chunk,
            "seed": args.seed, "cpu_count": os.cpu_count(), "load_avg_1min": os.getloadavg()[0],
            "python": platform.python_version(), "rows": rows}
    print(json.dumps(info))
    print(f"\n{'executor':>14} {'workers':>7} {'seconds':>9} {'masks/s':>11} {'speedup':>8} "
          f"{'startup s':>9} {'same best':>9}")
    for r in rows:
        print(f"{r['executor']:>14} {r['workers']:>7} {r['seconds']:>9.2f} {r['masks_per_second']:>11.0f} "
              f"{r['speedup']:>8.2f} {r['startup_s']:>9.1f} {str(r['same_best']):>9}")
    return 0 if all(r["same_best"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
