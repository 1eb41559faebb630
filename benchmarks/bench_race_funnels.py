"""How well the Mean of a raced ``swap`` descent early on predicts the local optimum it ends in.

    python benchmarks/bench_race_funnels.py --scenes c5-2v --seeds 0,1 --threads 1

With its defaults ``swap`` first races descents from its chirped start and ``race - 1`` fresh
selections (chirped and random, the ones a 120 s run races) and halves them by their Mean after
each turn: at 120 s a run the first turn gives each a few hundred scored selections. Here every
start of a seed's race is instead descended to its local optimum, without a budget, by the
plugin's own descent (guided first-improvement swaps, then segment shifts), and its Mean is
recorded after ``--marks`` scored selections. Printed per start: whether it is chirped or
random, its Mean at the start, at each mark and at the local optimum (with the gap to the
scene's best known), the selections it scored and its seconds. Per seed: the Spearman rank
correlation between the Mean at each mark and at the local optimum (near 1: halving at that
mark keeps the descents that end lowest), and the rank at each mark of the descent that ends
lowest (0: first). A descent that ends before a mark counts with its local optimum there.
The last line is one JSON record.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import emit_json, machine, set_threads, table  # noqa: E402


def _descents(scene: str, seed: int, marks: list[int]) -> list[dict]:
    """Each start of ``swap``'s race on ``scene`` (seed ``seed``), descended to its local optimum."""
    import numpy as np

    from arraysel.objective.neighbours import prepare_neighbourhoods
    from arraysel.objective.psf_objective import build_objective
    from arraysel.selectors.contract import Budget, BudgetedObjective, Recorder, numpy_rng
    from arraysel.selectors.registry import get_registry
    from arraysel.selectors.starts import start_selection

    raw = build_objective(scene)
    prepare_neighbourhoods(raw)
    k = int(raw.k)
    budget = Budget().start(raw)
    objective = BudgetedObjective(raw, budget, Recorder(raw, budget), k)
    selector = get_registry()["swap"]()
    o = selector.options
    rng = numpy_rng(seed)
    start = start_selection(o["start"], objective, k, rng, o["elements"])  # as the plugin draws them
    search = selector.search(objective, k, rng)
    start = search._start_mask(start)
    m = search.race - 1
    extra = search._race_starts(m)
    chirped = search.race_chirped(m)
    kinds = [o["start"]] + ["chirp"] * chirped + ["random"] * (len(extra) - chirped)
    rows = []
    for i, (mask, kind) in enumerate(zip([start] + extra, kinds)):
        value = float(search.score(mask[None])[0])
        first, scored0, t0 = value, search.scored, time.perf_counter()
        at = {}
        for mask, value in search._descent(mask.copy(), value):
            for q in marks:
                if q not in at and search.scored - scored0 >= q:
                    at[q] = value
        rows.append({"start": i, "kind": kind, "k": k, "first": first,
                     "at": {q: at.get(q, value) for q in marks}, "optimum": value,
                     "scored": search.scored - scored0, "seconds": time.perf_counter() - t0})
    return rows


def _spearman(x, y) -> float:
    from scipy.stats import spearmanr

    return float(spearmanr(x, y)[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="c5-2v")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--marks", default="250,500,1000,2000",
                    help="scored selections of a descent at which its Mean is recorded")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    set_threads(args.threads)
    from arraysel.scenes.best_known import best_known

    marks = sorted({int(q) for q in args.marks.split(",") if q})
    if not marks or marks[0] < 1:
        raise SystemExit("--marks: positive counts of scored selections, e.g. 250,500,1000")
    record = {"machine": machine(), "threads": args.threads, "marks": marks, "scenes": {}}
    for scene in [s for s in args.scenes.split(",") if s]:
        record["scenes"][scene] = {}
        for seed in [int(s) for s in args.seeds.split(",") if s]:
            rows = _descents(scene, seed, marks)
            known = best_known(scene, rows[0]["k"])
            ref = None if known is None else float(known["Mean"])
            gap = (lambda v: "" if ref is None else f"{100 * (v / ref - 1):+.1f} %")
            print(f"\n{scene}, seed {seed}: each start of the race descended to its local optimum")
            print(table([[r["start"], r["kind"], f"{r['first']:.6f}"] + [f"{r['at'][q]:.6f}" for q in marks]
                         + [f"{r['optimum']:.7f}", gap(r["optimum"]), r["scored"], f"{r['seconds']:.1f}"]
                         for r in rows],
                        ["start", "kind", "Mean at start"] + [f"at {q}" for q in marks]
                        + ["local optimum", "gap to best known", "scored", "s"]))
            final = [r["optimum"] for r in rows]
            lowest = int(min(range(len(rows)), key=lambda i: final[i]))
            summary = {}
            for q in marks:
                at = [r["at"][q] for r in rows]
                summary[q] = {"spearman": _spearman(at, final),
                              "rank_of_lowest": int(sorted(at).index(at[lowest]))}
            print(table([[q, f"{summary[q]['spearman']:.2f}", summary[q]["rank_of_lowest"]] for q in marks],
                        ["mark (scored)", "Spearman with the local optimum", "rank of the lowest-ending descent"]))
            record["scenes"][scene][str(seed)] = {"descents": rows, "by_mark": {str(q): v for q, v in summary.items()},
                                                  "best_known": ref}
    emit_json(record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
