"""Segment shifts scored as moves against the same masks scored independently, by the number of
elements a shift switches.

    python benchmarks/bench_moves.py --scenes paper,l11-5v,c5-2v --chunk 64 --shifts 2048 --threads 1

Per scene, from its best-known selection (a local optimum of swaps, as a descent meets shifts),
``--shifts`` segment shifts (runs of up to 24 elements rotated by 1 to 6 places, a random order,
seed 0; those that leave the selection unchanged or repeat one are dropped) are scored in chunks of
``--chunk``, as a descent scores them, each chunk both ways alternated in one process:
``arraysel.objective.neighbours.evaluate_moves`` (the objective's own ``evaluate_moves``: the
certificates' envelopes and the images corrected from the selection's channel sums and image, the
rows of each chunk padded to its widest move) and ``objective.evaluate`` of the moved masks. Both
must give the same Means to rounding (checked: relative 1e-4). Printed: shifts a second each way
over all chunks, then, for chunks of moves of one size m (1 to 8 elements, the shifts grouped by
size), the rate each way. The last line is one JSON record.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import best_known_start, set_threads  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="paper,l11-5v,c5-2v")
    ap.add_argument("--chunk", type=int, default=64)
    ap.add_argument("--shifts", type=int, default=2048)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    set_threads(args.threads)
    import numpy as np

    from arraysel.objective.neighbours import evaluate_moves, move_masks, moves_between
    from arraysel.selectors.moves import shift_moves, shifted_masks

    record = {"chunk": args.chunk, "shifts": args.shifts, "threads": args.threads, "scenes": {}}
    for scene in [s for s in args.scenes.split(",") if s]:
        obj, base = best_known_start(scene)
        n = int(obj.n_elements)
        cands = shifted_masks(base, shift_moves(n, 24, 6, np.random.default_rng(0))[:args.shifts])
        _, first = np.unique(cands, axis=0, return_index=True)
        cands = cands[np.sort(first)]
        cands = cands[(cands != base).any(1)]
        size = (base[None] & ~cands).sum(1)

        def both(group):
            """Seconds each way and the largest relative difference, chunk by chunk."""
            t_moves = t_masks = diff = 0.0
            for i in range(0, len(group), args.chunk):
                c = group[i:i + args.chunk]
                t0 = time.perf_counter()
                a = evaluate_moves(obj, base, *moves_between(base, c))["Mean"]
                t1 = time.perf_counter()
                b = obj.evaluate(c)["Mean"]
                t2 = time.perf_counter()
                t_moves, t_masks = t_moves + t1 - t0, t_masks + t2 - t1
                diff = max(diff, float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-30))))
            if diff > 1e-4:
                raise SystemExit(f"{scene}: moves and masks differ (largest relative difference {diff:.3g})")
            return t_moves, t_masks, diff

        warm = cands[:8]
        evaluate_moves(obj, base, *moves_between(base, warm))   # compiled passes, the selection's sums
        obj.evaluate(warm)
        assert (move_masks(base, *moves_between(base, cands)) == cands).all()
        tm, tk, diff = both(cands)
        row = {"n_elements": n, "k": int(obj.k), "shifts": int(len(cands)), "moves_per_s": len(cands) / tm,
               "masks_per_s": len(cands) / tk, "largest_relative_difference": diff, "by_size": {}}
        print(f"{scene}: {len(cands)} shifts from the best-known selection (Ne {n}, k {obj.k}), chunks of "
              f"{args.chunk}: moves {row['moves_per_s']:.0f}/s, masks {row['masks_per_s']:.0f}/s, "
              f"ratio {tk / tm:.2f}")
        print(f"  {'m':>3s} {'shifts':>7s} {'moves/s':>8s} {'masks/s':>8s} {'ratio':>6s}")
        for m in range(1, 9):
            group = cands[size == m]
            if len(group) < args.chunk // 2:
                continue
            gm, gk, _ = both(group)
            row["by_size"][m] = {"shifts": int(len(group)), "moves_per_s": len(group) / gm,
                                 "masks_per_s": len(group) / gk}
            print(f"  {m:3d} {len(group):7d} {len(group) / gm:8.0f} {len(group) / gk:8.0f} {gk / gm:6.2f}")
        record["scenes"][scene] = row
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    sys.exit(main())
