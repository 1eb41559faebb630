"""Two-swap steps at the end of a descent: how often the two-swaps the quadratic model predicts
best improve a local optimum of swaps and shifts, and what they cost.

    python benchmarks/bench_pair_steps.py --scenes paper,l11-5v,c5-2v --starts 5 --pairs 256 --threads 1

Per scene, ``--starts`` chirped starts (each the best of 32 random chirped layouts) and as many
random selections (seed 0) are descended by ``arraysel.selectors.localsearch.SwapSearch`` with
``swap``'s default configuration (``guide = 0.875``, ``model = quadratic``, ``scan = 0.125``,
``shift = 6``, ``shift_scan = 512``) to a local optimum of swaps and shifts. From there the
same descent goes on with two-swap steps (``pairs = --pairs``: at each local optimum the
``pairs`` two-swaps the model predicts best are scored, 64 a call, and the descent moves on from
the first improving one). Printed per start: the Mean of the local optimum, the Mean after the
two-swap steps, the improving two-swaps taken and the evaluations they cost (selections scored,
and the masks of each gradient and Hessian). The objective's pair rows are formed first (as
``compare`` does for these selectors). The last line is one JSON record.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import machine, set_threads  # noqa: E402

CONFIG = dict(guide=0.875, model="quadratic", scan=0.125, shift=6, shift_scan=512, gradient="exact")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="paper,l11-5v,c5-2v")
    ap.add_argument("--starts", type=int, default=5, help="chirped and random starts a scene, each (default 5)")
    ap.add_argument("--pairs", type=int, default=256, help="two-swaps scored at a local optimum (default 256)")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    if args.starts < 1:
        raise SystemExit(f"--starts must be >= 1, got {args.starts}")
    if args.pairs < 1:
        raise SystemExit(f"--pairs must be >= 1, got {args.pairs}")
    set_threads(args.threads)
    import numpy as np

    from arraysel.objective.neighbours import prepare_neighbourhoods
    from arraysel.objective.psf_objective import build_objective
    from arraysel.selectors.contract import Budget, BudgetedObjective, Recorder
    from arraysel.selectors.localsearch import FRESH_CHIRPS, SwapSearch
    from arraysel.selectors.starts import chirp_masks, random_mask

    record = {"starts": args.starts, "pairs": args.pairs, "threads": args.threads, "machine": machine(),
              "scenes": {}}
    for scene in [s for s in args.scenes.split(",") if s]:
        obj = build_objective(scene)
        prepare_neighbourhoods(obj)
        k, n = int(obj.k), int(obj.n_elements)
        rng = np.random.default_rng(0)
        starts = []
        for _ in range(args.starts):
            masks = chirp_masks(obj, k, rng, FRESH_CHIRPS)
            starts.append(("chirp", masks[int(np.argmin(obj.evaluate(masks)["Mean"]))].copy()))
        starts += [("random", random_mask(rng, n, k)) for _ in range(args.starts)]
        rows = []
        print(f"{scene} (Ne {n}, k {k}): local optimum -> after two-swap steps")
        for i, (kind, start) in enumerate(starts):
            budget = Budget(seconds=1e9).start(obj)
            view = BudgetedObjective(obj, budget, Recorder(obj, budget), k)
            search = SwapSearch(view, k, np.random.default_rng(i), **CONFIG)
            at, value = search.descend(start, float(search.score(start[None])[0]))
            search.pairs, before = args.pairs, budget.used_evaluations()
            _, after = search.descend(at, value)
            row = {"start": kind, "local_optimum": value, "after": after, "two_swaps": search.pair_moves,
                   "evaluations": budget.used_evaluations() - before}
            rows.append(row)
            print(f"  {kind:6s} {value:.7f} -> {after:.7f}  ({row['two_swaps']} two-swaps, "
                  f"{row['evaluations']} evaluations)")
        improved = sum(r["after"] < r["local_optimum"] for r in rows)
        spent = statistics.median(r["evaluations"] for r in rows)
        print(f"  improved {improved} of {len(rows)}; median evaluations after the local optimum {spent:.0f}")
        record["scenes"][scene] = {"rows": rows, "improved": improved, "median_evaluations": spent}
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
