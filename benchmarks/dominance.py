"""Does a comparison's best optimised selection dominate every baseline? Read from a finished sector
(or per-beam) comparison's ``pareto.csv``: for each selection of ``k`` elements that no baseline
row names (the searches' runs), its worst side lobe's gap to each baseline's (dB, negative: lower)
and its mean -6 dB width over the baseline's; it dominates when its worst side lobe is at most
``--max-psl`` dB and at least ``--gap`` dB below each baseline's, at a width at most ``--width``
times each baseline's (the sector scenes' issue: -20 dB, 2 dB, 1.05). Baselines: the rows
``pareto.csv`` marks ``baseline`` but ``full``.

    python benchmarks/dominance.py benchmarks/results/compare-matrix-sector
"""
from __future__ import annotations

import argparse
from pathlib import Path


def dominance(pareto, gap: float = 2.0, width: float = 1.05, max_psl: float = -20.0):
    """``(table, baselines)``: one row per searched selection of ``pareto`` (a DataFrame of
    ``pareto.csv``), its gaps and width ratios to each baseline and ``dominates``, best first."""
    import pandas as pd

    k = int(pareto.loc[pareto["config"] != "full", "k"].mode().iloc[0])
    base = pareto[pareto["baseline"].astype(bool) & (pareto["config"] != "full")]
    runs = pareto[~pareto["baseline"].astype(bool) & (pareto["k"] == k)]
    rows = []
    for _, r in runs.iterrows():
        row = {"config": r["config"], "seed": r["seed"], "worst_PSL_dB": r["worst_PSL_dB"],
               "mean_width_mm": r["mean_width_mm"]}
        ok = r["worst_PSL_dB"] <= max_psl
        for _, b in base.iterrows():
            d = r["worst_PSL_dB"] - b["worst_PSL_dB"]
            w = r["mean_width_mm"] / b["mean_width_mm"]
            row[f"dPSL vs {b['config']}"], row[f"width / {b['config']}"] = d, w
            ok = ok and d <= -gap and w <= width
        row["dominates"] = bool(ok)
        rows.append(row)
    return pd.DataFrame(rows).sort_values("worst_PSL_dB"), base


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path, help="a finished comparison's --out folder (its pareto.csv)")
    ap.add_argument("--gap", type=float, default=2.0)
    ap.add_argument("--width", type=float, default=1.05)
    ap.add_argument("--max-psl", type=float, default=-20.0)
    args = ap.parse_args(argv)
    import pandas as pd

    table, base = dominance(pd.read_csv(args.folder / "pareto.csv"), args.gap, args.width, args.max_psl)
    print(base[["config", "worst_PSL_dB", "mean_width_mm"]].to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    print(table.to_string(index=False, float_format=lambda v: f"{v:.3f}"))


if __name__ == "__main__":
    main()
