"""Loose blocks settled by delay-and-sums against hot blocks' pair matrices: the same swap runs
both ways, side by side in one run.

    python benchmarks/bench_hot_blocks.py --scenes paper,l11-5v,c5-2v --seeds 0,1,2,3 --evaluations 6000 --concurrent 2 --threads 1

A selection whose peak the block bounds alone do not certify is settled by the exact image on
each block whose bound reaches the peak (``Refinement.refine``). Every such block used to be
delay-and-summed from the selection's channels; a block left loose ``HotBlocks.after`` times (64)
is now *hot*: its symmetric pair matrix ``G`` (Ne x Ne x 2 block^2, from the stored pair channels)
is formed once, and a selection ``s + d`` near the reference ``s`` (the selection whose
neighbourhood is being scored) gets its image on the block as ``s^T G s + 2 d^T G s + d^T G d``
(``pairkernels.moved_block_values``: ``|d|^2`` rows of ``G``; ``arraysel.physics.psf.hotblocks``).
On a convex probe many selections of a search leave the same few blocks beside E loose (its
lateral lobes); on the linear scenes few selections need a block at all.

Per scene, the ``swap`` selector runs with the configuration of the 20 s and 120 s comparisons
(chirped start, ``fresh = mixed``, ``guide = 0.875``, ``model = quadratic``, ``scan = 0.125``,
``shift = 6``, ``shift_scan = 512``) for each seed on a budget of ``--evaluations``, twice: loose
blocks delay-and-summed only (``das``: ``HotBlocks.after`` too large to reach), then with hot
blocks (``hot``). Each run starts without hot state or block DAS plans (as a run in a fresh process
does), after a first run that warms the compiled kernels. A budget of evaluations makes both
ways take the same moves (their Means and evaluations must agree: checked, and printed).
``--concurrent 2`` runs the seeds in two processes at once, half each (a comparison's
``--executor process --workers 2`` on a 2-core machine, where the runs share the memory
bandwidth that forming each selection's channels needs); 1 (the default) runs them here.
Printed per way: evaluations and the runs' seconds summed over the seeds, evaluations per
second, the selections that reached a loose-block step, and the speed ratio ``hot / das``. The
objective's pair rows are formed before the runs (as ``compare`` does for these selectors). The
last line is one JSON record.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import machine, set_threads  # noqa: E402


CONFIG = {"start": "chirp", "fresh": "mixed", "guide": 0.875, "model": "quadratic", "scan": 0.125, "shift": 6,
          "shift_scan": 512}


def _runs(scene: str, way: str, seeds: list, evaluations: int, threads: int | None) -> list:
    """``[(seed, Mean, evaluations, seconds, loose selections)]`` of the ``swap`` runs of ``seeds``
    on ``scene`` with loose blocks settled ``way`` (``das`` or ``hot``), after a warm-up run."""
    set_threads(threads)
    import tempfile

    from arraysel.objective.neighbours import prepare_neighbourhoods
    from arraysel.objective.psf_objective import build_objective
    from arraysel.physics.psf.hotblocks import HotBlocks
    from arraysel.physics.psf.refinement import Refinement
    from arraysel.run.compare import compare
    from arraysel.selectors.contract import Budget

    obj = _objective(scene, build_objective, prepare_neighbourhoods)
    ref = obj.psf.basis.refinement
    after, refine = HotBlocks.after, Refinement.refine
    out_rows = []
    try:
        for seed, name in [(seeds[0], "warm-up")] + [(seed, way) for seed in seeds]:
            # each run starts as in a fresh process: no hot state, no block plans kept
            ref.hot.clear()
            ref._block_plans.clear()
            ref._block_dtx.clear()
            # class attributes: a truncated view of the basis has a refinement of its own (sharing
            # the state cleared above)
            HotBlocks.after = after if name == "hot" else 1 << 62
            loose = []

            def counted(self, w, *a, **kw):
                loose.append(int(w.shape[0]))
                return refine(self, w, *a, **kw)

            Refinement.refine = counted
            with tempfile.TemporaryDirectory() as out:
                res = compare(obj, [("swap", dict(CONFIG))], seeds=[seed], out_dir=out, force=True,
                              budget=Budget(evaluations=evaluations), progress=False, figures=False)
            Refinement.refine = refine
            if name != "warm-up":
                run = res.runs[res.runs["selector"] == "swap"].iloc[0]
                out_rows.append((seed, float(run["Mean"]), int(run["evaluations"]), float(run["seconds"]), sum(loose)))
    finally:
        HotBlocks.after, Refinement.refine = after, refine
    return out_rows


_OBJECTIVES: dict = {}


def _objective(scene, build_objective, prepare_neighbourhoods):
    """The scene's objective with its pair rows formed, built once a process."""
    if scene not in _OBJECTIVES:
        obj = build_objective(scene)
        prepare_neighbourhoods(obj)
        _OBJECTIVES[scene] = obj
    return _OBJECTIVES[scene]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="paper,l11-5v,c5-2v")
    ap.add_argument("--seeds", default="0,1,2,3", help="seeds of the swap runs (default 0,1,2,3)")
    ap.add_argument("--evaluations", type=int, default=6000, help="budget of each run (default 6000)")
    ap.add_argument("--concurrent", type=int, default=1, choices=(1, 2),
                    help="processes running the seeds at once (default 1: this one)")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    seeds = [int(x) for x in args.seeds.split(",") if x]
    if len(seeds) < args.concurrent or args.evaluations < 1:
        raise SystemExit(f"--seeds needs at least --concurrent seeds and --evaluations must be >= 1, got "
                         f"{args.seeds!r}, {args.evaluations}")
    set_threads(args.threads)
    from concurrent.futures import ProcessPoolExecutor

    record = {"seeds": seeds, "evaluations": args.evaluations, "concurrent": args.concurrent,
              "threads": args.threads, "machine": machine(), "config": CONFIG, "scenes": {}}
    groups = [seeds[i::args.concurrent] for i in range(args.concurrent)]
    for scene in [s for s in args.scenes.split(",") if s]:
        rows = {}
        for way in ("das", "hot"):
            if args.concurrent == 1:
                got = _runs(scene, way, seeds, args.evaluations, args.threads)
            else:
                with ProcessPoolExecutor(args.concurrent) as pool:
                    got = [r for part in pool.map(_runs, [scene] * len(groups), [way] * len(groups), groups,
                                                  [args.evaluations] * len(groups), [args.threads] * len(groups))
                           for r in part]
            got.sort()
            rows[way] = {"evaluations": sum(r[2] for r in got), "seconds": sum(r[3] for r in got),
                         "loose_selections": sum(r[4] for r in got), "Means": [r[1] for r in got],
                         "run_evaluations": [r[2] for r in got]}
        same = rows["das"]["Means"] == rows["hot"]["Means"] and \
            rows["das"]["run_evaluations"] == rows["hot"]["run_evaluations"]
        print(f"{scene}: swap, seeds {args.seeds}, {args.evaluations} evaluations a run, {args.concurrent} at once; "
              f"same moves both ways: {'yes' if same else 'NO'}")
        print(f"  {'way':5s} {'evals':>7s} {'seconds':>8s} {'evals/s':>8s} {'loose sel.':>10s} {'speed ratio':>12s}")
        for way, r in rows.items():
            r["evaluations_per_s"] = r["evaluations"] / r["seconds"]
            r["speed_ratio"] = r["evaluations_per_s"] / (rows["das"]["evaluations"] / rows["das"]["seconds"])
            print(f"  {way:5s} {r['evaluations']:7d} {r['seconds']:8.2f} {r['evaluations_per_s']:8.1f} "
                  f"{r['loose_selections']:10d} {r['speed_ratio']:12.2f}")
        record["scenes"][scene] = dict(rows, same_moves=same)
        if not same:
            print(json.dumps(record))
            return 1
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
