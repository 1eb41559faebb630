"""One-swap neighbourhoods on matrix-1024: scored through the objective's neighbourhood against scored as masks.

A random selection of 256 of the 1024 elements has 256 x 768 = 196,608 one-swap neighbours (768
under the 4-bank multiplexer of matrix-1024-mux, a swap staying inside a channel group). Side by
side in one process, on the scene's fast path, each neighbour scored exactly (the fast path's own
planes and metrics, to rounding), through ``objective.neighbourhood().evaluate`` as a search asks:

(a) ``whole``: every swap of ``--outs`` outgoing elements from a selection not seen before (its
    one-off work included; ``--outs 256``: the whole neighbourhood);
(b) ``blocks``: a descent's walk of ``--steps`` moves: at each step the block the neighbourhood
    prefers (``neighbourhood.block()``: one outgoing element against every incoming one; under
    channel groups as many outgoing elements as make 64 swaps), then a move to its best
    neighbour, so each step pays for the new selection (its image, and the carried columns);
(c) ``scattered``: the same walk, each step 64 random swaps (what the swap engine asked before it
    asked for blocks), each formed from its own rows;
(d) ``independent``: ``objective.evaluate`` of ``--masks`` of the neighbour masks of (a)-(c) (its
    batch path, 128 masks a batch).

The neighbours both scored are compared (largest difference of ``Mean`` relative to its value, float32
rounding). Rounds alternate the cases so that the load of a shared machine weighs on all alike;
each rate is the median of the rounds, each ratio the median of the rounds' ratios to (d).

Usage::

    python benchmarks/bench_matrix_neighbours.py [--scene matrix-1024] [--outs 16] [--steps 8]
        [--block-outs N] [--masks 256] [--rounds 3] [--threads 1]

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
SCATTERED = 64


def _swaps(mask, constraints):
    """Every feasible one-swap ``(out, into)`` of ``mask`` (out-major)."""
    from arraysel.objective.neighbours import swap_pairs

    return swap_pairs(mask) if constraints is None else constraints.swap_pairs(mask)


def _block(mask, constraints, rng, per_call):
    """The swaps of the block a descent asks for: outgoing elements in a random order, all their
    swaps, as many outgoing elements as make ``per_call`` swaps (at least one)."""
    import numpy as np

    out, into = _swaps(mask, constraints)
    outs = rng.permutation(np.unique(out))
    per = out.size / outs.size
    take = outs[:max(1, int(np.ceil(per_call / per)))]
    pick = np.isin(out, take)
    return out[pick], into[pick]


def _walk(nb, mask, steps, ask, keep):
    """Score ``ask(mask)`` at each of ``steps`` steps and move to the best; returns (seconds,
    neighbours scored, the last mask); ``keep(mask, out, into, means)`` sees each step's scores."""
    import numpy as np

    from arraysel.objective.neighbours import swap_masks

    t, n = 0.0, 0
    for _ in range(steps):
        out, into = ask(mask)
        t0 = time.perf_counter()
        means = nb.evaluate(mask, out, into)["Mean"]
        t += time.perf_counter() - t0
        n += out.size
        keep(mask, out, into, means)
        i = int(np.argmin(means))
        mask = swap_masks(mask, out[i:i + 1], into[i:i + 1])[0]
    return t, n, mask


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default="matrix-1024", help="3-D scene (default matrix-1024)")
    p.add_argument("--outs", type=int, default=16, help="outgoing elements whose swaps (a) scores (default 16)")
    p.add_argument("--steps", type=int, default=8, help="moves of the walks (b) and (c) a round (default 8)")
    p.add_argument("--block-outs", type=int, default=None,
                   help="outgoing elements of a block of (b) (default: what neighbourhood.block() prefers)")
    p.add_argument("--masks", type=int, default=256, help="neighbour masks (d) scores a round (default 256)")
    p.add_argument("--rounds", type=int, default=3, help="alternations of (a)-(d) (default 3)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--seed", type=int, default=0, help="the random selections' seed (default 0)")
    a = p.parse_args(argv)
    set_threads(a.threads)
    import numpy as np
    import torch

    from arraysel.constraints import constraints_of
    from arraysel.objective.build import build_objective
    from arraysel.objective.neighbours import prepare_neighbourhoods, swap_masks

    t0 = time.perf_counter()
    obj = build_objective(a.scene, dtype=torch.float32)
    load_s = time.perf_counter() - t0
    nb = obj.neighbourhood()
    if nb is None or nb.block() is None:
        raise SystemExit(f"scene {a.scene!r}: no neighbourhood that prefers blocks (no fast 3-D path)")
    prepare_s = prepare_neighbourhoods(obj)
    cons = constraints_of(obj)   # the channel groups of a scene with [constraints], else None
    rng = np.random.default_rng(a.seed)
    ne, k = obj.n_elements, obj.k
    block_outs = nb.block().outgoing if a.block_outs is None else a.block_outs
    per_block = block_outs * (ne - k) if cons is None else SCATTERED

    def fresh():
        if cons is not None:
            return cons.random_masks(rng, 1)[0]
        m = np.zeros(ne, dtype=bool)
        m[rng.choice(ne, k, replace=False)] = True
        return m

    def scattered(m):
        out, into = _swaps(m, cons)
        pick = rng.choice(out.size, min(SCATTERED, out.size), replace=False)
        return out[pick], into[pick]

    obj.evaluate(fresh()[None])  # warm-up
    rates = {c: [] for c in ("whole", "blocks", "scattered", "independent")}
    errs = {c: [] for c in ("whole", "blocks", "scattered")}
    for r in range(a.rounds):
        seen = {c: [] for c in errs}          # (neighbour masks, their Means) of each case

        def keeper(case):
            def keep(m, out, into, means):
                s = rng.choice(out.size, min(out.size, a.masks // 3), replace=False)
                seen[case].append((swap_masks(m, out[s], into[s]), means[s]))
            return keep

        mask = fresh()
        out, into = _swaps(mask, cons)
        outs = np.unique(out)[:a.outs]
        pick = np.isin(out, outs)
        t, n, _ = _walk(nb, mask, 1, lambda m: (out[pick], into[pick]), keeper("whole"))
        rates["whole"].append(n / t)
        t, n, _ = _walk(nb, fresh(), a.steps, lambda m: _block(m, cons, rng, per_block), keeper("blocks"))
        rates["blocks"].append(n / t)
        t, n, _ = _walk(nb, fresh(), a.steps, scattered, keeper("scattered"))
        rates["scattered"].append(n / t)
        masks = np.concatenate([np.concatenate([c[0] for c in seen[case]]) for case in errs])
        t0 = time.perf_counter()
        ref = obj.evaluate(masks)["Mean"]
        rates["independent"].append(masks.shape[0] / (time.perf_counter() - t0))
        i0 = 0
        for case in errs:
            got = np.concatenate([c[1] for c in seen[case]])
            errs[case].append(float(np.max(np.abs(got - ref[i0:i0 + got.size]) / np.abs(ref[i0:i0 + got.size]))))
            i0 += got.size
        print(f"round {r}: " + ", ".join(f"{c} {v[-1]:,.0f}/s" for c, v in rates.items())
              + f"; load {os.getloadavg()[0]:.1f}", flush=True)
    ind = rates["independent"]
    rec = {"benchmark": "matrix_neighbours", "scene": a.scene, "k": int(k), "n_elements": int(ne),
           "groups": cons is not None, "whole_outs": int(outs.size), "steps": a.steps, "block_outs": int(block_outs),
           "block_swaps": int(per_block),
           "scattered_swaps": SCATTERED, "rounds": a.rounds,
           "objective_load_s": round(load_s, 2), "prepare_s": round(prepare_s, 2),
           "independent_masks_per_s": round(statistics.median(ind), 1), "target_ratio": TARGET, "machine": machine()}
    for c in errs:
        rec[f"{c}_masks_per_s"] = round(statistics.median(rates[c]), 1)
        rec[f"{c}_ratio"] = round(statistics.median([x / y for x, y in zip(rates[c], ind)]), 1)
        rec[f"{c}_max_rel_diff_mean"] = max(errs[c])
    print("median: " + ", ".join(f"{c} {rec[c + '_masks_per_s']:,} masks/s ({rec[c + '_ratio']}x)" for c in errs)
          + f", independent {rec['independent_masks_per_s']} masks/s (target >= {TARGET}x); largest relative "
          f"difference of Mean {max(max(v) for v in errs.values()):.1e}")
    print(json.dumps(rec))
    return rec


if __name__ == "__main__":
    main()
