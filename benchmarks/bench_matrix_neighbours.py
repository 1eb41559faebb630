"""One-swap neighbourhoods on matrix-1024: scored from the selection's image against scored as masks.

A random selection of 256 of the 1024 elements has 256 x 768 = 196,608 one-swap neighbours. Side by
side in one process, on the same neighbours (float32, the scene's fast path):

(a) neighbourhood: ``MatrixObjective.evaluate_swaps`` of the swaps of ``--outs`` outgoing elements
    (each against all 768 inactive ones; ``--outs 256``: the whole neighbourhood), the selection's
    one-off work included;
(b) independent: ``MatrixObjective.evaluate`` of ``--masks`` of those neighbour masks (its batch
    path, 128 masks a batch);

then the neighbours both scored are compared (largest difference of ``Mean`` relative to its value,
float32 rounding). Rounds alternate (a) and (b) so that the load of a shared machine weighs on both
alike; each rate is the median of the rounds, the ratio the median of the rounds' ratios.

Usage::

    python benchmarks/bench_matrix_neighbours.py [--outs 16] [--masks 256] [--rounds 3] [--threads 1]

The last output line is a JSON record; everything before it is for people.
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

TARGET = 20.0


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default="matrix-1024", help="3-D scene (default matrix-1024)")
    p.add_argument("--outs", type=int, default=16, help="outgoing elements whose swaps (a) scores (default 16)")
    p.add_argument("--masks", type=int, default=256, help="neighbour masks (b) scores (default 256)")
    p.add_argument("--rounds", type=int, default=3, help="alternations of (a) and (b) (default 3)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--seed", type=int, default=0, help="the random selection's seed (default 0)")
    a = p.parse_args(argv)
    set_threads(a.threads)
    import numpy as np
    import torch

    from arraysel.objective.build import build_objective
    from arraysel.objective.neighbours import swap_masks, swap_pairs

    t0 = time.perf_counter()
    obj = build_objective(a.scene, dtype=torch.float32)
    load_s = time.perf_counter() - t0
    if not getattr(obj, "fast", False):
        raise SystemExit(f"scene {a.scene!r}: no fast 3-D path, nothing to compare")
    t0 = time.perf_counter()
    obj.prepare_neighbourhoods()
    prepare_s = time.perf_counter() - t0
    rng = np.random.default_rng(a.seed)
    ne, k = obj.n_elements, obj.k
    mask = np.zeros(ne, dtype=bool)
    mask[rng.choice(ne, k, replace=False)] = True
    out, into = swap_pairs(mask)
    outs = np.flatnonzero(mask)[:a.outs]
    pick = np.isin(out, outs)
    out, into = out[pick], into[pick]
    sample = rng.choice(out.size, min(a.masks, out.size), replace=False)
    masks = swap_masks(mask, out[sample], into[sample])
    obj.evaluate(masks[:8])  # warm-up
    fast_rate, slow_rate, ratios, errs = [], [], [], []
    for r in range(a.rounds):
        obj._neighbourhood().forget()   # each round pays the selection's one-off work
        t = time.perf_counter()
        got = obj.evaluate_swaps(mask, out, into)
        fast = out.size / (time.perf_counter() - t)
        t = time.perf_counter()
        ref = obj.evaluate(masks)
        slow = masks.shape[0] / (time.perf_counter() - t)
        fast_rate.append(fast)
        slow_rate.append(slow)
        ratios.append(fast / slow)
        errs.append(float(np.max(np.abs(got["Mean"][sample] - ref["Mean"]) / np.abs(ref["Mean"]))))
        print(f"round {r}: neighbourhood {fast:,.0f} masks/s ({out.size} swaps), independent {slow:,.1f} "
              f"masks/s ({masks.shape[0]} masks), ratio {fast / slow:.1f}x, load {os.getloadavg()[0]:.1f}",
              flush=True)
    rec = {"benchmark": "matrix_neighbours", "scene": a.scene, "k": int(k), "n_elements": int(ne),
           "swaps": int(out.size), "independent_masks": int(masks.shape[0]), "rounds": a.rounds,
           "objective_load_s": round(load_s, 2), "prepare_s": round(prepare_s, 2),
           "neighbourhood_masks_per_s": round(statistics.median(fast_rate), 1),
           "independent_masks_per_s": round(statistics.median(slow_rate), 2),
           "ratio": round(statistics.median(ratios), 1), "target_ratio": TARGET,
           "max_rel_diff_mean": max(errs), "machine": machine()}
    print(f"median: neighbourhood {rec['neighbourhood_masks_per_s']:,} masks/s, independent "
          f"{rec['independent_masks_per_s']} masks/s, ratio {rec['ratio']}x (target >= {TARGET}x); "
          f"largest relative difference of Mean {rec['max_rel_diff_mean']:.1e}")
    print(json.dumps(rec))
    return rec


if __name__ == "__main__":
    main()
