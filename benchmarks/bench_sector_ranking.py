"""How well the sector scene's search objective (the two-way beam pattern) ranks selections against
their per-beam metrics on the points' PSFs (``docs/sector.md``; issue: the beam-pattern ranking did
not carry over to the points' worst side lobe).

Scores a set of selections of ``k`` elements of ``matrix-1024-sector`` on both:

* fresh random selections (``--random``, seed 1);
* Fermat spirals: every taper (none, cosine, blackman) at ``--rotations`` rotations;
* periodic thinning by 2 at its four offsets;
* optimised: ``swap`` and ``ste`` runs on the beam pattern (``--runs`` seeds, ``--run-s`` seconds
  each) and the selections of ``--compare`` (a comparison folder's ``table1.csv``), and
  perturbations of each (1 to 64 random swaps);

the search side: ``Mean`` and the pattern's ``bp_PSL_dB``, ``bp_ISLR_dB``, widths; the per-beam side
(the sector fast path, :meth:`SectorObjective.beam_metrics`): the worst ``PSL_dB`` over the points,
the mean -6 dB width and the per-beam loss (:meth:`SectorObjective.beam_loss`, width cap 1.05 x the
full array's mean width). Reports Spearman's rho (``scipy.stats.spearmanr``) of every search
column against every per-beam column, over all selections and per group; checks the fast path
against the exact path on ``--exact-check`` selections first. Writes ``masks.csv``-like
``scores.csv``, ``spearman.csv`` and ``summary.json`` to ``--out``.

    python benchmarks/bench_sector_ranking.py --out benchmarks/results/sector-ranking
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import set_threads  # noqa: E402


def _masks_from_compare(folder: str, n: int):
    import numpy as np
    import pandas as pd

    path = os.path.join(folder, "table1.csv")
    if not os.path.exists(path):
        return []
    out = []
    for _, r in pd.read_csv(path).iterrows():
        if r["config"] not in ("ste", "swap", "gumbel", "anneal", "random") or not isinstance(r.get("elements"), str):
            continue   # the selections searched on the beam pattern (random: its best of N)
        m = np.zeros(n, dtype=bool)
        m[[int(v) for v in r["elements"].split()]] = True
        out.append((f"compare:{r['config']}", m))
    return out


def selections(obj, args):
    """``[(group, label, mask (Ne,) bool)]``."""
    import numpy as np

    from arraysel.run.experiment import Experiment
    from arraysel.selectors.budget import Budget
    from arraysel.selectors.layouts import TAPERS, fermat_spiral_layout, uniform_layout

    n, k = obj.n_elements, obj.k
    ny, nx = obj.element_grid
    out = [("random", f"random:{i}", m) for i, m in enumerate(obj.fresh_random_masks(args.random, seed=1))]
    for taper in TAPERS:
        for rot in np.linspace(0, 360, args.rotations, endpoint=False):
            m = np.zeros(n, dtype=bool)
            m[fermat_spiral_layout((ny, nx), k, taper=taper, rotation_deg=float(rot))] = True
            out.append(("spiral", f"spiral:{taper}:{rot:.0f}", m))
    grid = np.arange(n).reshape(ny, nx)
    for oy in (0, 1):
        for ox in (0, 1):
            m = np.zeros(n, dtype=bool)
            m[grid[oy::2, ox::2].reshape(-1)] = True
            out.append(("uniform", f"uniform:{oy}{ox}", m))
    m = np.zeros(n, dtype=bool)
    m[uniform_layout(n, k, (ny, nx))] = True
    if not any((m == o[2]).all() for o in out if o[0] == "uniform"):
        out.append(("uniform", "uniform:layout", m))
    opt = _masks_from_compare(args.compare, n) if args.compare else []
    for sel in ("swap", "ste"):
        for seed in range(args.runs):
            row = Experiment(obj, sel, budget=Budget(seconds=args.run_s), seed=seed).execute()
            if row["elements"] is None:
                print(f"  {sel} seed {seed}: no selection ({row.get('error')})", flush=True)
                continue
            opt.append((f"{sel}:{seed}", np.asarray(row["elements"].mask, dtype=bool)))
            print(f"  {sel} seed {seed}: Mean {row['Mean']:.4g}", flush=True)
    rng = np.random.default_rng(2)
    for label, m in opt:
        out.append(("optimised", label, m))
        on, off = np.flatnonzero(m), np.flatnonzero(~m)
        for s in args.perturb:
            for r in range(args.per_level):
                p = m.copy()
                p[rng.choice(on, s, replace=False)] = False
                p[rng.choice(off, s, replace=False)] = True
                out.append(("perturbed", f"{label}+{s}swaps:{r}", p))
    return out


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
    ap.add_argument("--random", type=int, default=200)
    ap.add_argument("--rotations", type=int, default=12)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--run-s", type=float, default=15.0)
    ap.add_argument("--compare", default="benchmarks/results/compare-matrix-sector")
    ap.add_argument("--perturb", type=int, nargs="+", default=[1, 4, 16, 64])
    ap.add_argument("--per-level", type=int, default=2)
    ap.add_argument("--exact-check", type=int, default=2)
    ap.add_argument("--points", type=int, nargs="+", default=None,
                    help="score on these points only (default all)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    set_threads(args.threads)
    import numpy as np
    import pandas as pd
    import torch
    from scipy.stats import spearmanr

    from arraysel.objective.sector_objective import SectorObjective

    obj = SectorObjective(args.scene)
    pts = list(range(obj.n_points)) if args.points is None else list(args.points)
    t0 = time.perf_counter()
    ready = [obj.fast_point(i) for i in pts]
    t_fast = time.perf_counter() - t0
    print(f"fast path ready on points {ready} in {t_fast:.1f} s (refused: {obj.fast_refused})", flush=True)
    sels = selections(obj, args)
    masks = np.stack([s[2] for s in sels])
    print(f"{len(sels)} selections", flush=True)
    search = obj.evaluate(masks)
    full = np.ones((1, obj.n_elements), dtype=bool)
    fm = obj.beam_metrics(full, points=pts)
    cap = 1.05 * float((fm["width_x_6dB"].mean() + fm["width_y_6dB"].mean()) / 2)
    t0 = time.perf_counter()
    bm = obj.beam_metrics(masks, points=pts)
    t_beam = time.perf_counter() - t0
    loss, summ = obj.beam_loss(masks, width_cap=cap, metrics=bm)
    print(f"per-beam scoring (fast path): {t_beam:.1f} s, {t_beam / len(masks) * 1e3:.0f} ms a mask", flush=True)
    # the fast path against the exact path on a few selections, one of each kind
    check = []
    picks = [g for g in ("random", "spiral", "optimised", "uniform", "perturbed")
             if any(s[0] == g for s in sels)][:args.exact_check]
    for g in picks:
        i = next(j for j, s in enumerate(sels) if s[0] == g)
        w = torch.as_tensor(masks[i:i + 1], dtype=obj.dtype)
        errs = []
        for p in pts:
            f = obj.point_images(w, p).to(torch.complex128)
            e = obj.point_images(w, p, exact=True).to(torch.complex128)
            a = (f.conj() * e).sum() / (f.conj() * f).sum()
            errs.append(float(((a * f - e).abs() ** 2).sum() / (e.abs() ** 2).sum()))
        ex = obj.beam_metrics(masks[i:i + 1], points=pts, exact=True)
        check.append({"label": sels[i][1], "max_SI_MSE": max(errs),
                      "PSL_dB_fast": bm["PSL_dB"][i].round(3).tolist(), "PSL_dB_exact": ex["PSL_dB"][0].round(3).tolist(),
                      "max_abs_dPSL_dB": float(np.abs(bm["PSL_dB"][i] - ex["PSL_dB"][0]).max()),
                      "max_rel_dwidth": float(np.abs(bm["width_x_6dB"][i] / ex["width_x_6dB"][0] - 1).max())})
        print("  exact check", check[-1], flush=True)
    df = pd.DataFrame({"group": [s[0] for s in sels], "label": [s[1] for s in sels],
                       **{c: search[c] for c in ("Mean", "bp_PSL_dB", "bp_ISLR_dB", "bp_width_u_6dB", "bp_width_v_6dB")},
                       "worst_PSL_dB": summ["worst_PSL_dB"], "mean_width_mm": summ["mean_width_m"] * 1e3,
                       "worst_GLL_dB": bm["GLL_dB"].max(1), "mean_ISLR_dB": bm["ISLR_dB"].mean(1), "beam_loss": loss})
    rows = []
    groups = {"all": df, **{g: d for g, d in df.groupby("group") if len(d) >= 8},
              "optimised+perturbed": df[df.group.isin(["optimised", "perturbed"])]}
    for gname, d in groups.items():
        for a in ("Mean", "bp_PSL_dB", "bp_ISLR_dB"):
            for b in ("worst_PSL_dB", "mean_width_mm", "mean_ISLR_dB", "beam_loss"):
                rho, pval = spearmanr(d[a], d[b])
                rows.append({"group": gname, "n": len(d), "search": a, "per_beam": b, "rho": float(rho),
                             "p": float(pval)})
    sp = pd.DataFrame(rows)
    print(sp[sp.search.isin(["Mean", "bp_PSL_dB"])].to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    summary = {"scene": args.scene, "points": pts, "selections": len(df), "groups": df.group.value_counts().to_dict(),
               "width_cap_mm": cap * 1e3, "fast_ready_s": t_fast, "per_beam_ms_a_mask": t_beam / len(masks) * 1e3,
               "exact_check": check, "threads": args.threads, "argv": _argv_without_out(sys.argv[1:] if argv is None else list(argv))}
    print(json.dumps(summary))
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        df.to_csv(os.path.join(args.out, "scores.csv"), index=False)
        sp.to_csv(os.path.join(args.out, "spearman.csv"), index=False)
        with open(os.path.join(args.out, "summary.json"), "w") as f:
            json.dump(summary, f, indent=1)


if __name__ == "__main__":
    main()
