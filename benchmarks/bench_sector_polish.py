"""Polish selections of a sector scene on the per-beam loss and check whether the best one dominates
the baselines (``docs/sector.md``; the target of the sector scenes' issue: worst side lobe at most
-20 dB and at least 2 dB below each baseline's, at a mean -6 dB width at most 5 % wider).

Baselines, scored on the sector fast path: the median of ``--fresh`` fresh random selections
(seed 0, as ``compare`` does), the best random selection of a comparison (``--compare``'s
``table1.csv``, row ``random``), periodic thinning (``uniform``) and the untapered Fermat spiral.
The width cap of the loss is 1.05 x the narrowest baseline's mean width (every baseline's 5 %).
Starts: the comparison's optimised selections (``ste``, ``swap``: searched on the beam pattern),
its best random selection and the untapered spiral; each is polished for ``--seconds``
(:func:`~arraysel.objective.sector_polish.polish_on_beams`). The best polished selection is then
re-scored on the exact path. Writes ``polish.csv`` (one row per baseline and polished selection,
with its elements) and ``summary.json`` to ``--out``.

    python benchmarks/bench_sector_polish.py --seconds 150 --out benchmarks/results/sector-polish
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import set_threads  # noqa: E402


def _argv_without_out(argv: list) -> list:
    """The arguments as given, less ``--out`` and its folder (the results' own place)."""
    out = list(argv)
    if "--out" in out:
        i = out.index("--out")
        del out[i:i + 2]
    return [a for a in out if not a.startswith("--out=")]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="matrix-1024-sector")
    ap.add_argument("--compare", default="benchmarks/results/compare-matrix-sector")
    ap.add_argument("--fresh", type=int, default=16)
    ap.add_argument("--seconds", type=float, default=150.0)
    ap.add_argument("--starts", nargs="+", default=["ste", "swap", "random", "spiral"])
    ap.add_argument("--from-csv", default=None,
                    help="a polish.csv of an earlier run: its polished selections (and only those) are the starts")
    ap.add_argument("--only", nargs="+", default=None,
                    help="with --from-csv: only the polished selections of these configs")
    ap.add_argument("--batch", type=int, default=48)
    ap.add_argument("--patience", type=int, default=20)
    ap.add_argument("--screen-db", type=float, default=0.0,
                    help="screen on the points within this many dB of the worst (inf: score every point)")
    ap.add_argument("--guide", type=float, default=0.0,
                    help="the share of each round's swaps proposed by the gradient (0: all random)")
    ap.add_argument("--soft-db", type=float, default=0.0,
                    help="search on the smooth maximum over the points at this temperature (0: the worst)")
    ap.add_argument("--width-ratio", type=float, default=1.05,
                    help="the loss's width cap over the narrowest baseline's mean width")
    ap.add_argument("--keep", type=int, default=4)
    ap.add_argument("--points", type=int, nargs="+", default=None,
                    help="score on these points only (default all)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    set_threads(args.threads)
    import numpy as np
    import pandas as pd

    from arraysel.objective.sector_objective import SectorObjective
    from arraysel.objective.sector_polish import polish_on_beams
    from arraysel.selectors.layouts import fermat_spiral_layout, uniform_layout

    obj = SectorObjective(args.scene)
    n, k = obj.n_elements, obj.k
    pts = list(range(obj.n_points)) if args.points is None else list(args.points)
    t0 = time.perf_counter()
    ready = [obj.fast_point(i) for i in pts]
    print(f"fast path on points {ready} in {time.perf_counter() - t0:.1f} s", flush=True)

    def mask_of(idx):
        m = np.zeros(n, dtype=bool)
        m[list(idx)] = True
        return m

    path = os.path.join(args.compare, "table1.csv") if args.compare else ""
    table = pd.read_csv(path) if path and os.path.exists(path) else pd.DataFrame(columns=["config", "elements"])
    comp = {r["config"]: mask_of(int(v) for v in r["elements"].split()) for _, r in table.iterrows()
            if isinstance(r.get("elements"), str) and r["config"] != "full"}
    ny, nx = obj.element_grid
    masks = {"uniform": mask_of(uniform_layout(n, k, (ny, nx))),
             "spiral": mask_of(fermat_spiral_layout((ny, nx), k, taper="none"))}
    if "random" in comp:
        masks["random"] = comp["random"]
    fresh = obj.fresh_random_masks(args.fresh, seed=0)
    bm = obj.beam_metrics(fresh, points=pts)
    fw = (bm["width_x_6dB"].mean(1) + bm["width_y_6dB"].mean(1)) / 2
    rows = [{"config": "random (fresh median)", "kind": "baseline", "worst_PSL_dB": float(np.median(bm["PSL_dB"].max(1))),
             "mean_width_mm": float(np.median(fw)) * 1e3, "elements": ""}]
    for name, m in masks.items():
        b = obj.beam_metrics(m[None], points=pts)
        rows.append({"config": name, "kind": "baseline", "worst_PSL_dB": float(b["PSL_dB"].max()),
                     "mean_width_mm": float((b["width_x_6dB"].mean() + b["width_y_6dB"].mean()) / 2) * 1e3,
                     "elements": " ".join(map(str, np.flatnonzero(m)))})
    base = pd.DataFrame(rows)
    print(base[["config", "worst_PSL_dB", "mean_width_mm"]].to_string(index=False), flush=True)
    cap = args.width_ratio * float(base["mean_width_mm"].min()) * 1e-3
    starts = {s: (comp[s] if s in comp else masks[s]) for s in args.starts if s in comp or s in masks}
    if args.from_csv:
        prev = pd.read_csv(args.from_csv)
        starts = {r["config"]: mask_of(int(v) for v in r["elements"].split())
                  for _, r in prev[prev["kind"] == "polished"].iterrows() if not args.only or r["config"] in args.only}
    for s, m in starts.items():
        res = polish_on_beams(obj, m, width_cap=cap, seconds=args.seconds, batch=args.batch, keep=args.keep, seed=0,
                              points=pts, patience=args.patience, screen_db=args.screen_db, soft_db=args.soft_db,
                              guide=args.guide)
        print(f"  {s}: loss {res['start_loss']:.2f} -> {res['loss']:.2f} dB, worst PSL {res['worst_PSL_dB']:.2f} dB, "
              f"width {res['mean_width_m'] * 1e3:.3f} mm; {res['rounds']} rounds, {res['accepted']} accepted, "
              f"{res['evaluations']} full + {res['screened']} screened scores in {res['seconds']:.0f} s", flush=True)
        rows.append({"config": f"{s} + polish", "kind": "polished", "worst_PSL_dB": res["worst_PSL_dB"],
                     "mean_width_mm": res["mean_width_m"] * 1e3, "start_loss": res["start_loss"], "loss": res["loss"],
                     "rounds": res["rounds"], "accepted": res["accepted"], "evaluations": res["evaluations"],
                     "screened": res["screened"], "seconds": res["seconds"],
                     "elements": " ".join(map(str, np.flatnonzero(res["mask"])))})
    df = pd.DataFrame(rows)
    pol = df[df.kind == "polished"]
    best = pol.loc[pol["loss"].idxmin()]
    checks = {}
    for _, b in base.iterrows():
        checks[b["config"]] = {"dPSL_dB": float(best["worst_PSL_dB"] - b["worst_PSL_dB"]),
                               "width_ratio": float(best["mean_width_mm"] / b["mean_width_mm"])}
    dominates = bool(best["worst_PSL_dB"] <= -20 and all(c["dPSL_dB"] <= -2 and c["width_ratio"] <= 1.05
                                                            for c in checks.values()))
    bm_exact = obj.beam_metrics(mask_of(int(v) for v in best["elements"].split())[None], points=pts, exact=True)
    exact = {"worst_PSL_dB": float(bm_exact["PSL_dB"].max()),
             "mean_width_mm": float((bm_exact["width_x_6dB"].mean() + bm_exact["width_y_6dB"].mean()) / 2) * 1e3}
    print(df.drop(columns=["elements"]).to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    summary = {"scene": args.scene, "points": pts, "width_cap_mm": cap * 1e3, "best": str(best["config"]),
               "best_fast": {"worst_PSL_dB": float(best["worst_PSL_dB"]), "mean_width_mm": float(best["mean_width_mm"])},
               "best_exact": exact, "against_baselines": checks, "dominates_every_baseline": dominates,
               "seconds_per_start": args.seconds, "argv": _argv_without_out(sys.argv[1:] if argv is None else list(argv))}
    print(json.dumps(summary))
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        df.to_csv(os.path.join(args.out, "polish.csv"), index=False)
        with open(os.path.join(args.out, "summary.json"), "w") as f:
            json.dump(summary, f, indent=1)


if __name__ == "__main__":
    main()
