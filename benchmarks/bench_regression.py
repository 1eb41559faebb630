"""Regression guard of scoring speed: ms a mask of independent batches on every kind of scene, and
the neighbourhood (one-swap) rate, in one command.

    python benchmarks/bench_regression.py --out benchmarks/results/bench-regression/after.json

Per scene (``--scenes``, default paper, l11-5v, c5-2v, matrix-1024), whole-process ``arraysel
evaluate`` runs, each a fresh process as a user starts it: one mask, and ``--masks`` random masks
(``--paper-masks`` on the paper scene, as the PyMUST comparison of the README counts it). The
marginal cost of a mask is ``(t_N - t_1) / (N - 1)``: what a mask adds once the process has started,
its imports and its basis loaded; the same difference of the processes' CPU seconds (every thread,
spinning ones too) is its CPU cost, which the machine's load moves less. Then the neighbourhood rate: a fresh process scores
``--swap-rounds`` one-swap neighbourhoods of ``--pairs`` neighbours each
(``arraysel.objective.neighbours.evaluate_swaps``, the objective prepared for neighbourhoods first)
on ``--swap-scene``, from its uniform layout, moving to the best neighbour after each, and reports
neighbours a second. ``--pymust-masks N`` (paper scene) times N masks of the cached-DAS PyMUST
pipeline (``tests/pymust_pipeline.py``) after its warm-up mask and gives the whole-process speed-up
``paper_masks * PyMUST seconds a mask / t_paper_masks``.

The machine's load moves timings by a third or more, so settings are compared inside one run:
``--variant LABEL[:VAR=VALUE,...]`` (repeatable) runs every measurement once per variant, the
variants' order turned every round, with those environment variables set (``VAR=`` unsets one).
For example ``--variant default --variant spinning:OMP_WAIT_POLICY=ACTIVE`` compares the default
with OpenMP threads that spin, and ``--variant old:PYTHONPATH=CHECKOUT`` an older checkout (its
commands are run as ``python -m arraysel`` in the temporary folder, so the checkout on PYTHONPATH is
the one imported: run in a checkout, ``python -m`` imports the current folder's ``arraysel`` first).
Medians over ``--rounds`` rounds; the 1-minute load average is recorded with every timing.

A table, then one JSON record as the last line (also written to ``--out`` when given).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

#: the environment as the command was started: importing arraysel here sets OMP_WAIT_POLICY, which
#: the measured processes must not inherit from this one
START_ENV = dict(os.environ)
HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import _common as C  # noqa: E402

#: Ne and k of the scenes the masks are drawn for without loading a scene (toy: the CLI's toy objective)
SIZES = {"toy": (64, 32)}

#: the neighbourhood measurement, run in a fresh process: prints one JSON line
SWAPS = r"""
import json, sys, time
import numpy as np
from arraysel.objective.build import objective_for
scene, pairs, rounds = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
try:
    from arraysel.objective import neighbours as nb
except ImportError:  # an older checkout without neighbourhoods
    print(json.dumps({"swaps_per_s": None})); sys.exit(0)
obj = objective_for(scene)
t0 = time.perf_counter()
nb.prepare_neighbourhoods(obj)
prepare_s = time.perf_counter() - t0
n, k = int(obj.n_elements), int(obj.k)
base = np.zeros(n, dtype=bool)
base[[(i * n) // k for i in range(k)]] = True
rng = np.random.default_rng(0)
nb.evaluate_swaps(obj, base, *(v[:8] for v in nb.swap_pairs(base, rng)))  # compiled passes loaded
seconds, scored = 0.0, 0
for _ in range(rounds):
    out, into = (v[:pairs] for v in nb.swap_pairs(base, rng))
    t0 = time.perf_counter()
    mean = nb.evaluate_swaps(obj, base, out, into)["Mean"]
    seconds += time.perf_counter() - t0
    scored += out.size
    best = int(np.argmin(mean))
    base = nb.swap_masks(base, out[best:best + 1], into[best:best + 1])[0]
print(json.dumps({"swaps_per_s": scored / seconds, "prepare_s": prepare_s}))
"""


def parse_variant(text: str) -> tuple[str, dict]:
    """``LABEL[:VAR=VALUE,...]`` -> (label, {VAR: VALUE or None to unset})."""
    label, _, rest = text.partition(":")
    if not label or any(c in label for c in " /=,"):
        raise SystemExit(f"--variant: the label must be a word before ':' (LABEL[:VAR=VALUE,...]), got {text!r}")
    env = {}
    for item in filter(None, rest.split(",")):
        var, eq, value = item.partition("=")
        if not eq or not var.replace("_", "").isalnum():
            raise SystemExit(f"--variant {label}: expected VAR=VALUE items separated by ',', got {item!r}")
        env[var] = value or None
    return label, env


#: the folder the measured processes run in: not a checkout, whose own ``arraysel`` folder would
#: come first on ``sys.path`` (``python -m`` and ``python -c`` put the current folder there) and
#: hide the checkout a variant puts on ``PYTHONPATH``
RUN_DIR = tempfile.gettempdir()


def variant_env(changes: dict) -> dict:
    """The environment of a variant's processes; the entries of its ``PYTHONPATH`` made absolute
    (they run in :data:`RUN_DIR`)."""
    env = dict(START_ENV)
    for var, value in changes.items():
        if value is None:
            env.pop(var, None)
        elif var == "PYTHONPATH":
            env[var] = os.pathsep.join(os.path.abspath(p) for p in value.split(os.pathsep) if p)
        else:
            env[var] = value
    return env


def scene_size(scene: str) -> tuple[int, int]:
    if scene in SIZES:
        return SIZES[scene]
    from arraysel.scenes.schema import load_scene

    sc = load_scene(scene)
    return int(sc.probe().n_elements), int(sc.k)


def write_masks(path: str, n: int, n_elements: int, k: int, seed: int) -> None:
    import numpy as np

    rng = np.random.default_rng(seed)
    with open(path, "w") as fh:
        for _ in range(n):
            fh.write(" ".join(map(str, np.sort(rng.choice(n_elements, k, replace=False)))) + "\n")


def _children_cpu_s() -> float:
    import resource

    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def timed(cmd: list[str], env: dict) -> tuple[float, float, str, float]:
    """(seconds, 1-minute load average at the start, stdout, CPU seconds) of one command; SystemExit
    on failure. The CPU seconds (user + system, every thread) count threads that spin too, and
    depend less on the machine's load than the wall time."""
    load = os.getloadavg()[0]
    cpu0 = _children_cpu_s()
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=RUN_DIR)
    s = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return s, load, proc.stdout, _children_cpu_s() - cpu0


def pymust_seconds(masks: int) -> float:
    """Seconds a mask of the cached-DAS PyMUST pipeline on the paper scene (after its warm-up mask)."""
    pp = C.load_pymust_pipeline()
    rand = C.random_masks(masks + 1, seed=1)
    scene = pp.PyMUSTScene()
    scene.kernel(rand[0])
    with C.Timer() as t:
        for m in rand[1:]:
            scene.kernel(m)
    return t.s / masks


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default="paper,l11-5v,c5-2v,matrix-1024",
                   help="scenes of the independent batches (names or .toml files; 'toy' too)")
    p.add_argument("--masks", type=int, default=512, help="masks of the large batch (default 512)")
    p.add_argument("--paper-masks", type=int, default=5000, help="masks of the large batch on paper (default 5000)")
    p.add_argument("--rounds", type=int, default=2, help="rounds of every measurement (default 2)")
    p.add_argument("--swap-scene", default="l11-5v", help="scene of the neighbourhood rate ('' for none)")
    p.add_argument("--pairs", type=int, default=256, help="neighbours a neighbourhood (default 256)")
    p.add_argument("--swap-rounds", type=int, default=6, help="neighbourhoods a measurement (default 6)")
    p.add_argument("--pymust-masks", type=int, default=0, help="PyMUST masks timed on paper (default 0: none)")
    p.add_argument("--variant", action="append", default=[], metavar="LABEL[:VAR=VALUE,...]",
                   help="a setting measured side by side with the others (default: one, 'default')")
    p.add_argument("--seed", type=int, default=0, help="seed of the random masks (default 0)")
    p.add_argument("--out", default=None, help="also write the JSON record to this file")
    a = p.parse_args(argv)
    for name in ("masks", "paper_masks", "rounds", "pairs", "swap_rounds"):
        if getattr(a, name) < (2 if "masks" in name else 1):
            p.error(f"--{name.replace('_', '-')} must be >= {2 if 'masks' in name else 1}")
    if a.pymust_masks < 0:
        p.error("--pymust-masks must be >= 0")
    a.variants = [parse_variant(v) for v in (a.variant or ["default"])]
    if len({label for label, _ in a.variants}) != len(a.variants):
        p.error("--variant labels must differ")
    return a


def measure_batches(args, tmp: str) -> dict:
    """{scene: {variant: {t1_s, tN_s, ms_per_mask, loads}}}, the runs interleaved."""
    evaluate = [sys.executable, "-m", "arraysel", "evaluate", "--no-progress"]
    scenes = [os.path.abspath(s) if os.path.isfile(s) else s for s in args.scenes.split(",") if s]
    files, times = {}, {}
    for scene in scenes:
        ne, k = scene_size(scene)
        n = args.paper_masks if scene == "paper" else args.masks
        tag = os.path.basename(scene).replace(".toml", "")
        files[scene] = {m: os.path.join(tmp, f"{tag}-{m}.txt") for m in (1, n)}
        for m, path in files[scene].items():
            write_masks(path, m, ne, k, args.seed)
        # untimed: the basis into the page cache (or built), the compiled kernels loaded once
        timed(evaluate + ["--scene", scene, "--masks", files[scene][1], "--out", os.path.join(tmp, "w.csv")],
              variant_env(args.variants[0][1]))
    for r in range(args.rounds):
        order = args.variants[r % len(args.variants):] + args.variants[:r % len(args.variants)]
        for scene in scenes:
            for label, changes in order:
                for m, path in files[scene].items():
                    s, load, _, cpu = timed(evaluate + ["--scene", scene, "--masks", path, "--out",
                                                        os.path.join(tmp, "o.csv")], variant_env(changes))
                    row = times.setdefault(scene, {}).setdefault(label, {"n": max(files[scene]), "t1_s": [],
                                                                         "tN_s": [], "cpu1_s": [], "cpuN_s": [],
                                                                         "loads": []})
                    row["t1_s" if m == 1 else "tN_s"].append(round(s, 3))
                    row["cpu1_s" if m == 1 else "cpuN_s"].append(round(cpu, 3))
                    row["loads"].append(round(load, 2))
                print(f"round {r + 1} {scene} {label}: 1 mask {row['t1_s'][-1]:.2f} s, {row['n']} masks "
                      f"{row['tN_s'][-1]:.2f} s (load {row['loads'][-1]})", file=sys.stderr, flush=True)
    for rows in times.values():
        for row in rows.values():
            marg = [(b - a) / (row["n"] - 1) * 1e3 for a, b in zip(row["t1_s"], row["tN_s"])]
            row["ms_per_mask"] = round(statistics.median(marg), 3)
            row["ms_per_mask_runs"] = [round(v, 3) for v in marg]
            cpu = [(b - a) / (row["n"] - 1) * 1e3 for a, b in zip(row["cpu1_s"], row["cpuN_s"])]
            row["cpu_ms_per_mask"] = round(statistics.median(cpu), 3)
    return times


def measure_swaps(args) -> dict:
    """{variant: {swaps_per_s (median), runs, loads}}, the runs interleaved."""
    out = {}
    if not args.swap_scene:
        return out
    scene = os.path.abspath(args.swap_scene) if os.path.isfile(args.swap_scene) else args.swap_scene
    cmd = [sys.executable, "-c", SWAPS, scene, str(args.pairs), str(args.swap_rounds)]
    for r in range(args.rounds):
        order = args.variants[r % len(args.variants):] + args.variants[:r % len(args.variants)]
        for label, changes in order:
            _, load, text, _ = timed(cmd, variant_env(changes))
            rec = json.loads(text.strip().splitlines()[-1])
            row = out.setdefault(label, {"runs": [], "loads": []})
            row["runs"].append(None if rec["swaps_per_s"] is None else round(rec["swaps_per_s"], 1))
            row["loads"].append(round(load, 2))
    for row in out.values():
        got = [v for v in row["runs"] if v is not None]
        row["swaps_per_s"] = round(statistics.median(got), 1) if got else None
    return out


def main(argv=None) -> int:
    args = parse_args(argv)
    record = {"command": " ".join(["python", "benchmarks/bench_regression.py", *(argv or sys.argv[1:])]),
              "variants": {label: {k: v for k, v in changes.items()} for label, changes in args.variants},
              "machine": C.machine(), "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    with tempfile.TemporaryDirectory() as tmp:
        record["batches"] = measure_batches(args, tmp)
    record["swaps"] = measure_swaps(args)
    if args.pymust_masks and "paper" in record["batches"]:
        s = pymust_seconds(args.pymust_masks)
        record["pymust_s_per_mask"] = round(s, 4)
        for row in record["batches"]["paper"].values():
            row["x_pymust_whole_process"] = round(row["n"] * s / statistics.median(row["tN_s"]), 1)
    rows = []
    for scene, by in record["batches"].items():
        for label, row in by.items():
            rows.append([scene, label, row["n"], f"{statistics.median(row['t1_s']):.2f}",
                         f"{statistics.median(row['tN_s']):.2f}", f"{row['ms_per_mask']:.2f}",
                         f"{row['cpu_ms_per_mask']:.2f}", row.get("x_pymust_whole_process", ""),
                         f"{statistics.mean(row['loads']):.1f}"])
    for label, row in record["swaps"].items():
        rows.append([f"neighbours {args.swap_scene}", label, args.pairs, "", "",
                     f"{row['swaps_per_s']} /s", "", "", f"{statistics.mean(row['loads']):.1f}"])
    print(C.table(rows, ["scene", "variant", "masks", "1 mask s", "N masks s", "ms/mask", "CPU ms/mask", "x PyMUST", "load"]))
    return C.finish(record, args.out)


if __name__ == "__main__":
    sys.exit(main())
