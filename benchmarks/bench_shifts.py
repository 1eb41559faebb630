"""Descents with segment shifts: shifts in a random order against shifts in the order the quadratic
model predicts, from the same starts, side by side in one run.

    python benchmarks/bench_shifts.py --scenes paper,l11-5v,c5-2v --starts 4 --threads 1

Per scene, ``--starts`` chirped starts (each the best of 32 random chirped layouts, seed 0) are
descended three ways by ``arraysel.selectors.localsearch.SwapSearch`` with the configuration of
the 20 s and 120 s comparisons (``guide = 0.875``, ``model = quadratic``, ``scan = 0.125``,
``shift = 6``): the shifts at a local optimum of swaps scored in a random order with
``shift_scan = 4096`` (``random-4096``: as an unguided descent scores them), in the
predicted order with the same scan (``guided-4096``), and in the predicted order with a scan of
512 (``guided-512``). Each descent has a generator of its own seed (the start's index), the same
for the three ways. Printed per way: evaluations per descent as a run's budget counts them
(selections scored, and the masks of each gradient and Hessian; median), seconds per descent
(median), the local optima's median and lowest Mean, and the ratio of evaluations against
``random-4096``. The objective's pair rows are formed before the descents (as ``compare`` does for
these selectors). The last line is one JSON record.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import machine, set_threads  # noqa: E402

WAYS = {"random-4096": (False, 4096), "guided-4096": (True, 4096), "guided-512": (True, 512)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="paper,l11-5v,c5-2v")
    ap.add_argument("--starts", type=int, default=4, help="chirped starts a scene (default 4)")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    if args.starts < 1:
        raise SystemExit(f"--starts must be >= 1, got {args.starts}")
    set_threads(args.threads)
    import numpy as np

    from arraysel.objective.neighbours import prepare_neighbourhoods
    from arraysel.objective.psf_objective import build_objective
    from arraysel.selectors.contract import Budget, BudgetedObjective, Recorder
    from arraysel.selectors.localsearch import FRESH_CHIRPS, SwapSearch
    from arraysel.selectors.starts import chirp_masks

    record = {"starts": args.starts, "threads": args.threads, "machine": machine(), "scenes": {}}
    for scene in [s for s in args.scenes.split(",") if s]:
        obj = build_objective(scene)
        prepare_neighbourhoods(obj)
        k = int(obj.k)
        rng = np.random.default_rng(0)
        starts = []
        for _ in range(args.starts):
            masks = chirp_masks(obj, k, rng, FRESH_CHIRPS)
            starts.append(masks[int(np.argmin(obj.evaluate(masks)["Mean"]))].copy())
        rows = {}
        for way, (guided, scan) in WAYS.items():
            scored, seconds, values = [], [], []
            for i, start in enumerate(starts):
                budget = Budget(seconds=1e9).start(obj)
                view = BudgetedObjective(obj, budget, Recorder(obj, budget), k)
                search = SwapSearch(view, k, np.random.default_rng(i), guide=0.875, model="quadratic", scan=0.125,
                                    shift=6, shift_scan=scan, guide_shifts=guided, gradient="exact")
                t0 = time.perf_counter()
                _, value = search.descend(start, float(search.score(start[None])[0]))
                seconds.append(time.perf_counter() - t0)
                scored.append(budget.used_evaluations())
                values.append(value)
            rows[way] = {"evaluations": statistics.median(scored), "seconds": statistics.median(seconds),
                         "median_Mean": statistics.median(values), "lowest_Mean": min(values), "Means": values}
        base = rows["random-4096"]["evaluations"]
        print(f"{scene} (Ne {int(obj.n_elements)}, k {k}): {args.starts} descents a way from the same chirped starts")
        print(f"  {'way':12s} {'evals':>8s} {'seconds':>8s} {'median Mean':>12s} {'lowest Mean':>12s} {'evals ratio':>12s}")
        for way, r in rows.items():
            r["evaluations_ratio"] = r["evaluations"] / base
            print(f"  {way:12s} {r['evaluations']:8.0f} {r['seconds']:8.2f} {r['median_Mean']:12.7f} "
                  f"{r['lowest_Mean']:12.7f} {r['evaluations_ratio']:12.2f}")
        record["scenes"][scene] = rows
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
