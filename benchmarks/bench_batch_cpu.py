"""CPU cost of scoring independent masks inside one process, first and later batches apart, to
compare two checkouts where the whole-process guard (``bench_regression.py``) cannot: on a shared
machine the start of a process moves by more than a change of a millisecond a mask.

    python benchmarks/bench_batch_cpu.py --scene l11-5v --masks 512 --rounds 3 \\
        --variant before:PYTHONPATH=PREVIOUS_CHECKOUT --variant after:PYTHONPATH=THIS_CHECKOUT

Each round starts one fresh process per variant (in the temporary folder, so that the checkout on
``PYTHONPATH`` is the one imported: :data:`bench_regression.RUN_DIR`) (the variants' order turned every round) that
builds the objective, scores one mask, then ``evaluate``s the same ``--masks`` random masks
``--repeats`` times and reports, per call, the user and system CPU ms a mask and the minor page
faults a mask (``resource.getrusage``). The first call holds what a process pays once to score a
batch (loading the compiled passes, the delay-and-sum plans, the first touch of the batch's
memory); the later ones are the cost of a mask in a warm process. ``--threads 1`` (default)
measures the work itself: two threads on cores that other jobs hold spend CPU waiting for each
other. Medians over the rounds; a table, then one JSON record as the last line.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import _common as C  # noqa: E402
from bench_regression import RUN_DIR, parse_variant, variant_env  # noqa: E402

#: the measurement, run in a fresh process: prints one JSON line
PROBE = r"""
import json, resource, sys
import numpy as np
from arraysel.objective.build import objective_for
scene, n, repeats, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
obj = objective_for(scene)
ne, k = int(obj.n_elements), int(obj.k)
rng = np.random.default_rng(seed)
masks = np.zeros((n, ne), dtype=np.float32)
for i in range(n):
    masks[i, rng.choice(ne, k, replace=False)] = 1
obj.evaluate(masks[:1])
calls = []
for _ in range(repeats):
    a = resource.getrusage(resource.RUSAGE_SELF)
    obj.evaluate(masks)
    b = resource.getrusage(resource.RUSAGE_SELF)
    calls.append({"user_ms": 1e3 * (b.ru_utime - a.ru_utime) / n, "sys_ms": 1e3 * (b.ru_stime - a.ru_stime) / n,
                  "faults": (b.ru_minflt - a.ru_minflt) / n})
print(json.dumps(calls))
"""


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default="l11-5v", help="scene name or .toml file (default l11-5v)")
    p.add_argument("--masks", type=int, default=512, help="masks of each evaluate call (default 512)")
    p.add_argument("--repeats", type=int, default=3, help="evaluate calls a process (default 3)")
    p.add_argument("--rounds", type=int, default=3, help="processes a variant (default 3)")
    p.add_argument("--threads", type=int, default=1, help="torch and numba threads (default 1; 0: as set)")
    p.add_argument("--variant", action="append", default=[], metavar="LABEL[:VAR=VALUE,...]",
                   help="a setting measured side by side with the others (default: one, 'default')")
    p.add_argument("--seed", type=int, default=0, help="seed of the random masks (default 0)")
    p.add_argument("--out", default=None, help="also write the JSON record to this file")
    a = p.parse_args(argv)
    for name in ("masks", "repeats", "rounds"):
        if getattr(a, name) < 1:
            p.error(f"--{name} must be >= 1")
    if a.threads < 0:
        p.error("--threads must be >= 0")
    a.variants = [parse_variant(v) for v in (a.variant or ["default"])]
    if len({label for label, _ in a.variants}) != len(a.variants):
        p.error("--variant labels must differ")
    return a


def main(argv=None) -> int:
    args = parse_args(argv)
    threads = {} if not args.threads else {v: str(args.threads) for v in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS")}
    record = {"command": " ".join(["python", "benchmarks/bench_batch_cpu.py", *(argv or sys.argv[1:])]),
              "variants": {label: dict(changes) for label, changes in args.variants},
              "machine": C.machine(), "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "runs": {}}
    scene = os.path.abspath(args.scene) if os.path.isfile(args.scene) else args.scene
    cmd = [sys.executable, "-c", PROBE, scene, str(args.masks), str(args.repeats), str(args.seed)]
    for r in range(args.rounds):
        order = args.variants[r % len(args.variants):] + args.variants[:r % len(args.variants)]
        for label, changes in order:
            env = variant_env({**threads, **changes})
            load = os.getloadavg()[0]
            proc = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=RUN_DIR)
            if proc.returncode != 0:
                raise SystemExit(f"variant {label} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
            calls = json.loads(proc.stdout.strip().splitlines()[-1])
            record["runs"].setdefault(label, []).append({"load": round(load, 2), "calls": calls})
            print(f"round {r + 1} {label}: " + ", ".join(f"{c['user_ms'] + c['sys_ms']:.2f}" for c in calls)
                  + f" CPU ms a mask (load {load:.1f})", file=sys.stderr, flush=True)
    rows = []
    for label, runs in record["runs"].items():
        for i, name in ((0, "first"), (slice(1, None), "later")):
            picked = [c for run in runs for c in ([run["calls"][i]] if i == 0 else run["calls"][i])]
            if not picked:
                continue
            med = {key: statistics.median(c[key] for c in picked) for key in ("user_ms", "sys_ms", "faults")}
            record.setdefault("summary", {}).setdefault(label, {})[name] = {k: round(v, 3) for k, v in med.items()}
            rows.append([label, name, len(picked), f"{med['user_ms']:.2f}", f"{med['sys_ms']:.2f}",
                         f"{med['user_ms'] + med['sys_ms']:.2f}", f"{med['faults']:.0f}",
                         f"{statistics.mean(run['load'] for run in runs):.1f}"])
    print(C.table(rows, ["variant", "call", "calls", "user ms", "sys ms", "CPU ms/mask", "faults/mask", "load"]))
    return C.finish(record, args.out)


if __name__ == "__main__":
    sys.exit(main())
