"""Per-run cost of isolating ``arraysel compare``'s runs: each run in a fresh child process.

Measures, alternated in one process on the paper scene (the basis must already be in the on-disk
cache), the wall time of one ``uniform`` run (one final evaluation):

* ``in_process``: :class:`arraysel.run.experiment.Experiment` in this process (``--in-process``);
* ``child``: what ``compare`` does without ``--in-process``: a fresh child from the forkserver
  builds the objective from its factory (basis memory-mapped, cache entries checked by size, as
  compare asks), runs the task, sends the row back, and this process scores the row's selection
  again (:func:`arraysel.run.compare._checked`);
* ``child_full_verify``: the same with every cache block's checksum verified in the child.

``overhead`` is the child's median minus the in-process median: the cost added to every run.
``build`` is the median time from the child's start to its objective being built.

Usage::

    python benchmarks/bench_isolation.py [--scene paper] [--rounds 5] [--threads 2]

The last output line is a JSON record.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from _common import emit_json, set_threads  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="paper")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    set_threads(args.threads)

    from arraysel.objective.build import objective_for
    from arraysel.run import isolation
    from arraysel.run.compare import _checked
    from arraysel.run.compare_task import compare_item, compare_task
    from arraysel.run.experiment import Experiment
    from arraysel.run.workers import objective_factory_for
    from arraysel.selectors.contract import Budget
    from arraysel.selectors.registry import get_registry

    objective = objective_for(args.scene, "cpu", "float32", None)
    factory = objective_factory_for(objective)
    cls = get_registry()["uniform"]
    budget = Budget(seconds=60.0)
    item = compare_item("uniform", cls, {}, budget, 0)
    times: dict[str, list[float]] = {"in_process": [], "child": [], "child_full_verify": []}
    builds: list[float] = []

    def child(verify):
        shot = isolation.OneShot(factory, compare_task, item, 90.0, isolation.default_threads(), verify).start()
        res = shot.wait()
        builds.append(shot.ready_at - shot.started_at)
        row, _ = _checked(objective, res["row"], res["trace"])
        assert not row["error"], row["error"]

    for _ in range(args.rounds + 1):  # the first round warms the forkserver up and is dropped
        t = time.perf_counter()
        Experiment(objective, cls, budget=budget, seed=0).run()
        times["in_process"].append(time.perf_counter() - t)
        for name, verify in (("child", "size"), ("child_full_verify", None)):
            t = time.perf_counter()
            child(verify)
            times[name].append(time.perf_counter() - t)
    med = {k: statistics.median(v[1:]) for k, v in times.items()}
    rec = {"benchmark": "isolation", "scene": args.scene, "rounds": args.rounds,
           **{f"{k}_s": round(v, 4) for k, v in med.items()},
           "overhead_s": round(med["child"] - med["in_process"], 4),
           "overhead_full_verify_s": round(med["child_full_verify"] - med["in_process"], 4),
           "build_s": round(statistics.median(builds[2:]), 4)}
    print(f"{'setting':<20}{'median s':>10}")
    for k, v in med.items():
        print(f"{k:<20}{v:>10.3f}")
    print(f"per-run overhead of a child: {rec['overhead_s']:.3f} s ({rec['overhead_full_verify_s']:.3f} s with "
          f"every checksum); the child's objective build: {rec['build_s']:.3f} s")
    emit_json(rec)


if __name__ == "__main__":
    main()
