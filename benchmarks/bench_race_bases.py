"""Neighbourhood bases kept for a race's descents: ``swap`` runs with the bases of the latest
selections kept (``PairBasis.swap_base_max_bytes``, the default) against one base kept, side by
side on the same seeds.

    python benchmarks/bench_race_bases.py --scenes paper,l11-5v,c5-2v --seeds 2,3 --evaluations 5000 --threads 1

Each run is ``arraysel compare --selectors swap --budget-evals N --budget-s 0`` in this process
(the defaults of ``swap``: a race of 16 descents taking turns, then the iterated local search);
an evaluation budget makes both variants take the same path, so their Means must be equal and
only the seconds differ. Each run is a fresh process, the two variants in turn (which goes first
alternating from seed to seed). A race's descents
take turns: with one base kept, every turn of a descent forms its selection's image and element
rows afresh from the basis (about 0.1 s on a 128-element scene); kept, only a descent's first
turn forms it. Printed per scene and seed: the seconds of each variant and their ratio; the last
line is one JSON record.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import machine, set_threads  # noqa: E402


def _child(scene: str, seed: int, evaluations: int, cap: int) -> None:
    """One run in this (fresh) process; prints ``seconds Mean``."""
    import arraysel
    from arraysel.physics.psf.basis import PairBasis

    PairBasis.swap_base_max_bytes = cap
    with tempfile.TemporaryDirectory() as out:
        arraysel.compare(scene, ["swap"], seeds=(seed,), budget_s=None, budget_evals=evaluations, out_dir=out,
                         force=True, progress=False, figures=False)
        with open(os.path.join(out, "runs.csv"), newline="") as f:
            row = next(r for r in csv.DictReader(f) if r["selector"] == "swap")
    print(row["seconds"], row["Mean"])


def _run(scene: str, seed: int, evaluations: int, cap: int, threads) -> tuple[float, float]:
    """A run in a fresh process (nothing carried from the run before: kept bases, hot blocks)."""
    cmd = [sys.executable, os.path.abspath(__file__), "--child", scene, str(seed), str(evaluations), str(cap)]
    if threads is not None:
        cmd += ["--threads", str(threads)]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.split()
    return float(out[-2]), float(out[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="paper,l11-5v,c5-2v")
    ap.add_argument("--seeds", default="2,3")
    ap.add_argument("--evaluations", type=int, default=5000, help="evaluations a run (default 5000)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--child", nargs=4, metavar=("SCENE", "SEED", "EVALUATIONS", "CAP"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    set_threads(args.threads)
    if args.child:
        scene, seed, evaluations, cap = args.child
        _child(scene, int(seed), int(evaluations), int(cap))
        return 0
    if args.evaluations < 100:
        raise SystemExit(f"--evaluations must be >= 100, got {args.evaluations}")
    seeds = [int(s) for s in args.seeds.split(",") if s]
    from arraysel.physics.psf.basis import PairBasis

    kept = PairBasis.swap_base_max_bytes
    record = {"evaluations": args.evaluations, "threads": args.threads, "machine": machine(), "scenes": {}}
    for scene in [s for s in args.scenes.split(",") if s]:
        rows = []
        print(f"{scene}: seconds with the bases kept / one base kept", flush=True)
        for i, seed in enumerate(seeds):
            variants = [("kept", kept), ("one", 1)][::1 if i % 2 == 0 else -1]   # alternate which goes first
            got = {name: _run(scene, seed, args.evaluations, cap, args.threads) for name, cap in variants}
            (t_kept, m_kept), (t_one, m_one) = got["kept"], got["one"]
            rows.append({"seed": seed, "kept_s": t_kept, "one_s": t_one, "Mean_kept": m_kept, "Mean_one": m_one})
            same = "same Mean" if m_kept == m_one else f"Means differ: {m_kept:.7f} vs {m_one:.7f}"
            print(f"  seed {seed}: {t_kept:.1f} s / {t_one:.1f} s  ({t_one / t_kept:.2f}x; {same})", flush=True)
        record["scenes"][scene] = rows
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
