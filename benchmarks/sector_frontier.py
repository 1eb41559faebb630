"""How low a side lobe can go at a given main-lobe width on a sector scene: the frontier of smooth
apodizations of the full array, and where the baselines and optimised selections sit.

The reference designs are the full array apodized by ``w(x, y) = K_beta(rho_q / s)``: ``rho_q =
(|x|^q + |y|^q)^(1/q)`` the superellipse radius of an element (x, y normalised to the aperture's
half-width: ``q = 2`` a circle, large ``q`` the square), ``s`` the footprint's size (1: inscribed in
the aperture, 1.414 reaching its corners), ``K_beta(t) = I0(beta sqrt(1 - t^2)) / I0(beta)`` the
Kaiser window (``beta = 0``: uniform), zero past the footprint. They are the classic smooth tapers a
designer trades side lobes for width with; they use every element, with weights.

1. ``--stage scene``: the grid of ``(q, s, beta)`` on the scene's own points (its fast path): each
   taper's worst ``PSL_dB`` over the points and mean -6 dB width (``tapers.csv``), and the frontier
   (``frontier.csv``): for each width ratio to the fresh random selections' median width, the
   lowest worst side lobe of a taper at most that wide.
2. ``--stage heldout``: the frontier's tapers, the full array, the scene's fresh random selections
   and the selections named by ``--selections``/``--configs`` on ``--points`` random points of the
   sector that the scene does not hold (``arraysel.run.sector_exchange.random_sector_points``,
   ``--seed``), scored on the exact path (``scan_points``): ``heldout.csv`` (one row per design and
   point) and ``summary.csv`` (worst and median PSL, mean width, width over the fresh median),
   ``frontier.png``.

    python benchmarks/sector_frontier.py --stage scene --out DIR
    python benchmarks/sector_frontier.py --stage heldout --out DIR --points 16 --seed 20261208 \\
        --selections benchmarks/results/compare-matrix-sector/table1.csv --configs spiral random
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import set_threads  # noqa: E402
from sector_recheck import read_selections  # noqa: E402

RATIOS = (1.00, 1.02, 1.04, 1.05, 1.06, 1.08, 1.10, 1.15, 1.20)


def kaiser(t, beta: float):
    """The Kaiser window at ``t`` in [-1, 1] (1 at 0; 0 past |t| = 1)."""
    import numpy as np

    t = np.asarray(t, dtype=np.float64)
    inside = np.abs(t) <= 1.0
    return np.where(inside, np.i0(beta * np.sqrt(np.clip(1.0 - t ** 2, 0.0, 1.0))) / np.i0(beta), 0.0)


def taper_weights(positions, q: float, s: float, beta: float):
    """The weights (Ne,) of the superellipse Kaiser taper (module docstring) on element centres
    ``positions`` (Ne, 2|3), normalised to the aperture's half-width (half the span of the centres
    plus half an element step)."""
    import numpy as np

    from arraysel.selectors.layouts import _half_extent   # the spiral's aperture: the same normalisation

    pos = np.asarray(positions, dtype=np.float64)[:, :2]
    centre = 0.5 * (pos.min(0) + pos.max(0))
    xy = np.abs(pos - centre) / np.array([_half_extent(pos[:, 0]), _half_extent(pos[:, 1])])
    rq = (xy[:, 0] ** q + xy[:, 1] ** q) ** (1.0 / q)
    return kaiser(rq / s, beta)


def _frontier(rows, fresh_width: float, ratios=RATIOS) -> list[dict]:
    out = []
    for r in ratios:
        ok = [t for t in rows if t["mean_width_mm"] <= r * fresh_width]
        if ok:
            best = min(ok, key=lambda t: t["worst_PSL_dB"])
            out.append({"width_ratio_max": r, **best})
    return out


def stage_scene(args, obj, positions) -> None:
    import numpy as np
    import pandas as pd
    import torch

    b = obj.beams
    b.fast_min_masks = 1          # the cached fast models serve a batch of any size
    grid = [(q, s, beta) for q in args.q for s in args.s for beta in args.beta]
    W = np.stack([taper_weights(positions, *g) for g in grid])
    fresh = b.fresh_random_masks()
    t0 = time.perf_counter()
    bm = b.beam_metrics(torch.as_tensor(np.concatenate([W, fresh.astype(np.float64)])))
    seconds = time.perf_counter() - t0
    worst = bm["PSL_dB"].max(1)
    width = (bm["width_x_6dB"].mean(1) + bm["width_y_6dB"].mean(1)) / 2 * 1e3
    islr = bm["ISLR_dB"].mean(1)
    n = len(grid)
    fresh_width = float(np.median(width[n:]))
    rows = [{"q": q, "s": s, "beta": beta, "worst_PSL_dB": float(worst[j]), "mean_width_mm": float(width[j]),
             "width_ratio": float(width[j] / fresh_width), "mean_ISLR_dB": float(islr[j])}
            for j, (q, s, beta) in enumerate(grid)]
    pd.DataFrame(rows).to_csv(args.out / "tapers.csv", index=False)
    front = _frontier(rows, fresh_width)
    pd.DataFrame(front).to_csv(args.out / "frontier.csv", index=False)
    meta = {"fresh_median_width_mm": fresh_width, "tapers": n, "seconds": seconds}
    (args.out / "scene.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")
    print(f"{n} tapers and {len(fresh)} fresh random selections scored in {seconds:.0f} s; "
          f"fresh median width {fresh_width:.3f} mm")
    for f in front:
        print(f"  width <= {f['width_ratio_max']:.2f} x: worst {f['worst_PSL_dB']:7.2f} dB at {f['mean_width_mm']:.3f} mm "
              f"(q {f['q']:g}, s {f['s']:g}, beta {f['beta']:g})")


def stage_heldout(args, obj, positions) -> None:
    import numpy as np
    import pandas as pd

    from arraysel.report.beams import FRESH_RANDOM
    from arraysel.run.sector_exchange import random_sector_points, scan_points

    front = pd.read_csv(args.frontier or args.out / "frontier.csv")
    if args.band:
        every = pd.read_csv((args.frontier or args.out / "frontier.csv").with_name("tapers.csv"))
        lo, hi = args.band
        front = pd.concat([front, every[(every["width_ratio"] >= lo) & (every["width_ratio"] <= hi)]])
    front = front.drop_duplicates(["q", "s", "beta"])
    designs: dict[str, tuple[str, np.ndarray]] = {"full": ("full array", np.ones(obj.n_elements))}
    for _, f in front.iterrows():
        designs[f"taper q={f.q:g} s={f.s:g} beta={f.beta:g}"] = ("taper", taper_weights(positions, f.q, f.s, f.beta))
    if args.selections:
        for name, m in read_selections(args.selections, args.configs, obj.n_elements).items():
            designs[name] = ("selection", m.astype(np.float64))
    fresh = obj.beams.fresh_random_masks(args.fresh)
    for j, m in enumerate(fresh):
        designs[f"random (fresh {j})"] = ("fresh random", m.astype(np.float64))
    points = random_sector_points(args.scene, args.points, np.random.default_rng(args.seed),
                                  ranges=tuple(r * 1e-3 for r in args.ranges_mm), edge_deg=args.edge_deg)
    names = list(designs)
    t0 = time.perf_counter()
    res = scan_points(args.scene, np.stack([designs[n][1] for n in names]), points,
                      log=lambda line: print(f"[{time.perf_counter() - t0:6.0f} s] {line}", flush=True))
    rows = []
    for j, n in enumerate(names):
        for i, p in enumerate(points):
            rows.append({"design": n, "kind": designs[n][0], "point": f"{p[0]:g},{p[1]:g}@{p[2].replace(' ', '')}",
                         **{k: float(res[k][j, i]) for k in ("PSL_dB", "ISLR_dB", "width_x_6dB", "width_y_6dB")}})
    table = pd.DataFrame(rows)
    table.to_csv(args.out / "heldout.csv", index=False)
    summary = table.groupby("design", sort=False).agg(kind=("kind", "first"), worst_PSL_dB=("PSL_dB", "max"),
                                                      median_PSL_dB=("PSL_dB", "median"), mean_ISLR_dB=("ISLR_dB", "mean"),
                                                      wx=("width_x_6dB", "mean"), wy=("width_y_6dB", "mean"))
    summary["mean_width_mm"] = (summary.pop("wx") + summary.pop("wy")) / 2 * 1e3
    fresh_rows = summary[summary["kind"] == "fresh random"]
    # the fresh baseline's side lobe as compare's beams.csv forms it: each point's median over the fresh selections,
    # then the worst point (pareto.csv takes the median of the selections' own worst); its width as pareto.csv forms
    # it: the median of the selections' mean widths
    per_point = table[table["kind"] == "fresh random"].groupby("point", sort=False)
    med = {"kind": "fresh random", "worst_PSL_dB": float(per_point["PSL_dB"].median().max()),
           "median_PSL_dB": float(per_point["PSL_dB"].median().median()),
           "mean_ISLR_dB": float(fresh_rows["mean_ISLR_dB"].median()),
           "mean_width_mm": float(fresh_rows["mean_width_mm"].median())}
    summary.loc[FRESH_RANDOM] = med
    summary["width_ratio"] = summary["mean_width_mm"] / med["mean_width_mm"]
    summary.to_csv(args.out / "summary.csv")
    meta = {"command": shlex.join(["python", "benchmarks/sector_frontier.py", *sys.argv[1:]]), "points": points,
            "seconds": time.perf_counter() - t0}
    (args.out / "heldout.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")
    show = summary[summary["kind"] != "fresh random"].sort_values("mean_width_mm")
    show = pd.concat([show, summary.loc[[FRESH_RANDOM]]])
    print(show[["kind", "worst_PSL_dB", "median_PSL_dB", "mean_width_mm", "width_ratio"]].round(3).to_string())
    _figure(summary, args.out / "frontier.png")


def _figure(summary, path) -> None:
    """Worst held-out PSL against width: the tapers and their lower envelope, every other design, and
    the sector issue's target region (2 dB below every baseline, at most 5 % wider than the
    narrowest)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from arraysel.report.beams import BASELINES, FRESH_RANDOM

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    tapers = summary[summary["kind"] == "taper"].sort_values("width_ratio")
    ax.plot(tapers["width_ratio"], tapers["worst_PSL_dB"], "o", color="0.55", label="smooth tapers (full array)")
    ax.plot(tapers["width_ratio"], np.minimum.accumulate(tapers["worst_PSL_dB"].to_numpy()), "--", color="0.55",
            label="their lower envelope")
    base = summary[(summary["kind"] == "selection") | (summary.index == FRESH_RANDOM)
                   | (summary["kind"] == "full array")]
    marks = {"full array": "ks", "fresh random": "x"}
    for name, row in base.iterrows():
        ax.plot(row["width_ratio"], row["worst_PSL_dB"], marks.get(row["kind"], "o"), ms=7, label=name)
    if "spiral" in summary.index:
        # the sector issue's baselines: compare's, less the full array
        baselines = summary.loc[[n for n in BASELINES if n != "full" and n in summary.index]]
        top = float(baselines["worst_PSL_dB"].min()) - 2.0
        right = 1.05 * float(baselines["width_ratio"].min())
        ax.fill_between([0.98, right], [top, top], [top - 10, top - 10], color="tab:green", alpha=0.12,
                        label="target: 2 dB below every baseline, <= 5 % wider")
    ax.set_ylim(min(-38.0, float(summary["worst_PSL_dB"].min()) - 1), -14)
    ax.set_xlabel("mean -6 dB width / fresh random median")
    ax.set_ylabel("worst PSL over the held-out points (dB)")
    ax.legend(fontsize=6.5, loc="upper right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="matrix-1024-sector", help="a sector scene (name or TOML file)")
    ap.add_argument("--stage", choices=("scene", "heldout", "both", "figure"), default="both",
                    help="figure: frontier.png again from --out's summary.csv")
    ap.add_argument("--q", type=float, nargs="+", default=[2, 3, 4, 6, 10], help="superellipse exponents")
    ap.add_argument("--s", type=float, nargs="+", default=[1.0, 1.1, 1.2, 1.3, 1.414], help="footprint sizes")
    ap.add_argument("--beta", type=float, nargs="+", default=[0.5, 1, 1.5, 2, 2.5, 3], help="Kaiser betas")
    ap.add_argument("--selections", type=Path, nargs="*", default=[], help="CSVs with columns config, elements")
    ap.add_argument("--configs", nargs="*", default=[], help="the rows of --selections to score held out")
    ap.add_argument("--fresh", type=int, default=16, help="fresh random selections scored held out")
    ap.add_argument("--band", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="also every taper of tapers.csv (beside the frontier's) whose width ratio on the scene "
                         "lies in [LO, HI]")
    ap.add_argument("--frontier", type=Path, default=None,
                    help="the tapers to score held out (default: --out's frontier.csv, from --stage scene)")
    ap.add_argument("--points", type=int, default=16, help="held-out points")
    ap.add_argument("--seed", type=int, default=20261208, help="seed of the held-out points")
    ap.add_argument("--ranges-mm", type=float, nargs=2, default=(20.0, 110.0))
    ap.add_argument("--edge-deg", type=float, default=8.0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    set_threads(args.threads)
    from arraysel.objective.sector_objective import SectorObjective

    args.out.mkdir(parents=True, exist_ok=True)
    if args.stage == "figure":
        import pandas as pd

        _figure(pd.read_csv(args.out / "summary.csv", index_col=0), args.out / "frontier.png")
        return
    obj = SectorObjective(args.scene)
    positions = obj.beams.setup.probe.element_positions()
    if args.stage in ("scene", "both"):
        stage_scene(args, obj, positions)
    if args.stage in ("heldout", "both"):
        stage_heldout(args, obj, positions)


if __name__ == "__main__":
    main()
