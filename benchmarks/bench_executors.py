"""Evaluations per run per core of ``arraysel compare`` on the local, process and dask executors.

Runs, one after another in one invocation, the same comparison (``--selectors random,swap
--seeds 0,1`` on the paper scene, ``--budget-s 10``) as a user would, through the command line:

* ``local``: ``arraysel compare`` (each run isolated in a child of a warm template, one run at a
  time with all the cores' threads);
* ``process``: ``--executor process --workers W`` (W runs at a time, cores / W threads each);
* ``dask``: ``--executor dask --workers W`` (a Dask LocalCluster of W worker processes; the
  same runs, cores / W threads each).

* ``local1``: ``arraysel compare --threads 1``: the local runs on one thread each, the per-core
  reference that does not depend on how well a run uses several threads;
* ``local1x2``: two ``local1`` compares at the same time, one per seed: what two independent
  single-threaded runs get when they share the machine (its memory bandwidth and caches, and
  whatever else runs on it): the ceiling for any executor with two workers.

For each executor and selector it prints the evaluations of each run, their mean, the mean
divided by the run's threads (``per core``) and that figure over the local one (``ratio``; the
target is >= 0.8), over the one-thread local one (``ratio1``) and over two of those at once
(``ratio2``). A time budget counts only the run's own work: every worker's one-off work
(objective build, basis check, compiled code, plans) is done in its template before any run
starts, and is printed per worker (``warm-ups``, from ``run.json``). The machine's 1-minute load
average before and after each executor is printed too: on a shared machine, other work takes
cores from the runs.

Usage::

    python benchmarks/bench_executors.py [--budget-s 10] [--long] [--workers 2] [--out DIR]

``--long`` adds a pass with 60 s budgets. The last output line is a JSON record.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from _common import emit_json  # noqa: E402

SELECTORS = ("random", "swap")
SEEDS = "0,1"


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def _command(executor: str, workers: int, budget_s: float, scene: str, out: Path, seeds: str,
             threads: int | None) -> list[str]:
    cmd = [sys.executable, "-m", "arraysel", "compare", "--scene", scene, "--selectors", ",".join(SELECTORS),
           "--seeds", seeds, "--budget-s", f"{budget_s:g}", "--out", str(out), "--force", "--no-figures",
           "--no-progress"]
    if executor != "local":
        cmd += ["--executor", executor, "--workers", str(workers)]
    if threads is not None:
        cmd += ["--threads", str(threads)]
    return cmd


def one(spec: str, default_workers: int, budget_s: float, scene: str, out: Path) -> dict:
    """One ``arraysel compare`` of ``spec`` (an executor; ``local1``: local with ``--threads 1``;
    ``local1x2``: two of those at the same time, one per seed); its rows, threads, warm-ups, wall
    time and load."""
    import pandas as pd

    workers = default_workers
    if ":" in spec:  # process:1, dask:3: that many workers
        spec, workers = spec.split(":")[0], int(spec.split(":")[1])
    executor = "local" if spec.startswith("local") else spec
    threads = 1 if spec.startswith("local1") else None
    if spec == "local1x2":
        outs = [out.with_name(f"{out.name}-seed{s}") for s in SEEDS.split(",")]
        cmds = [_command(executor, workers, budget_s, scene, o, s, threads) for o, s in zip(outs, SEEDS.split(","))]
    else:
        outs, cmds = [out], [_command(executor, workers, budget_s, scene, out, SEEDS, threads)]
    load0 = _load()
    t0 = time.perf_counter()
    procs = [subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for c in cmds]
    results = [p.communicate() for p in procs]
    wall = time.perf_counter() - t0
    for c, p, (_, err) in zip(cmds, procs, results):
        if p.returncode != 0:
            raise SystemExit(f"{' '.join(c)} failed:\n{err[-3000:]}")
    stderr = "".join(err for _, err in results)
    runs = pd.concat([pd.read_csv(o / "runs.csv", keep_default_na=False) for o in outs])
    runs = runs.sort_values(["selector", "seed"], kind="stable")
    metas = [json.loads((o / "run.json").read_text()) for o in outs]
    meta = metas[0]
    warm = [w for m in metas for w in m.get("worker_warm_ups", [])]
    threads = (meta["executor"].get("threads") if executor == "process" else
               warm[0]["threads"] if warm else None)
    if not isinstance(threads, int):
        threads = max(1, os.cpu_count() // (1 if executor == "local" else workers))
    rows = {sel: [int(e) for e in runs[runs["selector"] == sel]["evaluations"]] for sel in SELECTORS}
    flags = [f for f in runs["budget_flag"] if f]
    label = spec if executor == "local" or workers == default_workers else f"{spec}:{workers}"
    return {"executor": label, "workers": 1 if executor == "local" else workers, "threads": threads,
            "evaluations": rows, "wall_s": round(wall, 1), "load_before": load0, "load_after": _load(),
            "warm_ups": [(round(w["ready_s"], 2), round(w["warm_s"], 2)) for w in warm], "flags": flags,
            "stderr_leak": "leaked semaphore" in stderr}


def _per_core(r: dict, sel: str) -> float:
    ev = r["evaluations"][sel]
    return sum(ev) / len(ev) / r["threads"]


def table(results: list[dict], budget_s: float) -> list[dict]:
    local = next((r for r in results if r["executor"] == "local"), results[0])
    one_thread = next((r for r in results if r["executor"] == "local1"), None)
    two_local = next((r for r in results if r["executor"] == "local1x2"), None)
    out = []
    print(f"\n{budget_s:g} s budgets, selectors {','.join(SELECTORS)}, seeds {SEEDS}, {os.cpu_count()} cores")
    print(f"{'executor':<9}{'workers':>8}{'threads':>8}  {'selector':<8}{'evaluations per run':>24}"
          f"{'mean':>9}{'per core':>10}{'ratio':>7}{'ratio1':>7}{'ratio2':>7}  {'wall s':>7}  load before/after  warm-ups (ready s, warm s)")
    for r in results:
        for sel in SELECTORS:
            ev = r["evaluations"][sel]
            mean = sum(ev) / len(ev)
            per_core = mean / r["threads"]
            ratio = per_core / _per_core(local, sel)
            ratio1 = per_core / _per_core(one_thread, sel) if one_thread else float("nan")
            ratio2 = per_core / _per_core(two_local, sel) if two_local else float("nan")
            out.append({"executor": r["executor"], "selector": sel, "evaluations": ev, "per_core": round(per_core, 1),
                        "ratio": round(ratio, 3), "ratio_1_thread": round(ratio1, 3),
                        "ratio_two_local": round(ratio2, 3)})
            print(f"{r['executor']:<9}{r['workers']:>8}{r['threads']:>8}  {sel:<8}{' / '.join(map(str, ev)):>24}"
                  f"{mean:>9.0f}{per_core:>10.0f}{ratio:>7.2f}{ratio1:>7.2f}{ratio2:>7.2f}  {r['wall_s']:>7}  "
                  f"{r['load_before']:>6} / {r['load_after']:<6}     {r['warm_ups']}")
        if r["flags"]:
            print(f"  flagged rows: {r['flags']}")
        if r["stderr_leak"]:
            print("  the resource tracker warned about leaked semaphores")
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="paper")
    ap.add_argument("--budget-s", type=float, default=10.0)
    ap.add_argument("--long", action="store_true", help="add a pass with 60 s budgets")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--executors", default="local,local1,local1x2,process,dask",
                    help="what to run (default local,local1,local1x2,process,dask; local1: local with "
                         "--threads 1; local1x2: two local1 compares at once, one per seed; process:1, "
                         "dask:1: with that many workers instead of --workers)")
    ap.add_argument("--out", default=None, help="folder for the compare outputs (default: a temporary one)")
    args = ap.parse_args(argv)
    base = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench-executors-"))
    record = {"cpu_count": os.cpu_count(), "passes": []}
    for budget_s in [args.budget_s] + ([60.0] if args.long else []):
        results = [one(ex, args.workers, budget_s, args.scene, base / f"{ex.replace(':', '-')}-{budget_s:g}")
                   for ex in args.executors.split(",")]
        record["passes"].append({"budget_s": budget_s, "rows": table(results, budget_s), "runs": results})
    emit_json(record)


if __name__ == "__main__":
    main()
