"""Long searches for the best-known masks of the built-in scenes, many runs in parallel.

    python benchmarks/best_known_search.py --out DIR [--seconds 400] [--jobs 16] [--scenes paper,l11-5v,c5-2v]

Each scene's PSF basis is built (or loaded from the cache) first, one process per scene; then
``--jobs`` worker processes (one thread each for torch, numba and BLAS) run the planned selector runs, each a time
budget of ``--seconds`` (``arraysel.run.experiment.Experiment``, the same runner ``compare``
uses, so every run's best is scored again at its end; a selector that scores neighbourhoods gets
its objective prepared for them before its clock, as in ``compare``). ``DIR/results.json`` holds every finished
run (scene, selector, options, seed, Mean, elements, evaluations, seconds), rewritten after each
one, and ``DIR/best.json`` the best run per scene. Re-score a found mask with ``arraysel evaluate``
before storing it in ``arraysel/scenes/best_known.json``.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import set_threads  # noqa: E402  (thread variables before numpy, torch and numba load)

#: (selector, options) runs per scene, in order; seeds 0, 1, ... per entry (see _plan)
RECIPES = {
    "paper": [("ils", {"start": "uniform", "fresh": "chirp", "starts": 3}), ("ils", {}), ("memetic", {}),
              ("ils", {"mode": "best", "starts": 7}), ("swap", {"start": "random", "mode": "best"}),
              ("ils", {"relink": 0.6}), ("ils", {"mode": "best", "relink": 0.6})],
    "l11-5v": [("swap", {"start": "chirp", "fresh": "chirp", "race": 16, "race_quota": 250, "shift": 6}),
               ("swap", {"start": "chirp", "fresh": "chirp", "max_perturb": 8}), ("swap", {"start": "chirp"}),
               ("memetic", {"init": "chirp"}), ("ils", {"start": "chirp", "fresh": "chirp"}), ("memetic", {}),
               ("ils", {}), ("anneal", {}), ("ils", {"relink": 0.6}), ("swap", {})],
    "c5-2v": [("swap", {"max_perturb": 8}), ("anneal", {}),
              ("ils", {"start": "uniform", "fresh": "chirp", "starts": 3}), ("memetic", {}), ("ils", {}),
              ("ils", {"relink": 0.6}), ("swap", {})],
}


def _plan(scenes: list[str], jobs: int) -> list[tuple[str, str, dict, int]]:
    """Round-robin over the scenes' recipes until ``jobs`` runs are planned; the seed counts the
    runs of the same scene."""
    runs, counters, pos = [], {s: 0 for s in scenes}, {s: 0 for s in scenes}
    while len(runs) < jobs:
        for s in scenes:
            if len(runs) >= jobs:
                break
            name, opts = RECIPES[s][pos[s] % len(RECIPES[s])]
            runs.append((s, name, dict(opts), counters[s]))
            pos[s] += 1
            counters[s] += 1
    return runs


def _build(scene: str, threads: int) -> tuple[str, float]:
    set_threads(threads)
    from arraysel.objective.psf_objective import build_objective

    t0 = time.perf_counter()
    build_objective(scene)
    return scene, time.perf_counter() - t0


def _run(item) -> dict:
    scene, name, options, seed, seconds = item
    set_threads(1)  # one thread for each run, as compare's workers have
    from arraysel.objective.neighbours import prepare_neighbourhoods
    from arraysel.objective.psf_objective import build_objective
    from arraysel.run.experiment import Experiment
    from arraysel.run.runners import RunSpec, scores_neighbourhoods
    from arraysel.selectors.contract import Budget
    from arraysel.selectors.registry import build_plugin_manager, get_registry

    reg = get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))
    obj = build_objective(scene)
    if scores_neighbourhoods(RunSpec(name, reg[name], options, seed)):
        prepare_neighbourhoods(obj)  # as compare does, before the clock
    t0 = time.perf_counter()
    row = Experiment(obj, name, options=options, budget=Budget(seconds=seconds), seed=seed, registry=reg,
                     k=obj.k).run()
    return {"scene": scene, "selector": name, "options": options, "seed": seed, "Mean": float(row["Mean"]),
            "elements": row["elements"], "evaluations": int(row["evaluations"]), "error": row["error"],
            "seconds": time.perf_counter() - t0, "budget_s": seconds}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--seconds", type=float, default=400.0)
    ap.add_argument("--jobs", type=int, default=max(1, os.cpu_count() or 1))
    ap.add_argument("--scenes", default="paper,l11-5v,c5-2v")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scenes = [s for s in args.scenes.split(",") if s]
    ctx = mp.get_context("spawn")
    t0 = time.perf_counter()
    with ctx.Pool(len(scenes)) as pool:
        for scene, sec in pool.starmap(_build, [(s, max(1, args.jobs // len(scenes))) for s in scenes]):
            print(f"basis of {scene}: {sec:.1f} s", flush=True)
    plan = [(s, n, o, seed, args.seconds) for s, n, o, seed in _plan(scenes, args.jobs)]
    results: list[dict] = []
    with ctx.Pool(args.jobs) as pool:
        for res in pool.imap_unordered(_run, plan):
            results.append(res)
            print(f"{res['scene']:8s} {res['selector']:6s} {json.dumps(res['options'])} seed {res['seed']}: "
                  f"Mean {res['Mean']:.6f}, {res['evaluations']} evaluations {res['error']}", flush=True)
            best = {}
            for r in results:
                if not r["error"] and (r["scene"] not in best or r["Mean"] < best[r["scene"]]["Mean"]):
                    best[r["scene"]] = r
            for name, payload in (("results.json", results), ("best.json", best)):
                tmp = out / (name + ".tmp")
                tmp.write_text(json.dumps(payload, indent=1))
                tmp.replace(out / name)
    print(f"done in {time.perf_counter() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
