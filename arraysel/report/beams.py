"""The per-beam tables and the Pareto front of a sector scene's comparison (``docs/sector.md``).

``beams.csv``: one row per (configuration, point) with the exact per-beam metrics of the
configuration's listed selection (``PSL_dB``, ``ISLR_dB``, ``GLL_dB``, the -6 dB widths in mm), and
the rows of the fresh random selections' median (``random (fresh median)``).

``pareto.csv``: one row per distinct selection that the comparison made (every run of every
configuration, the full array and the fresh random median), summarised on two axes a designer
trades: the worst side lobe over the points (``worst_PSL_dB``, the largest ``PSL_dB``) and the
mean -6 dB main-lobe width (``mean_width_mm``, the mean over points of the widths in x and y; a
1-D scene's: the lateral widths, ``width_z_mm`` holding its axial widths).
``on_front`` marks the selections of ``k`` elements that no other selection of ``k`` elements
dominates (no worse on both axes and better on one); the full array is a reference, never on it.
:func:`pareto_figure` draws them, every baseline named.
"""
from __future__ import annotations

import numpy as np

from arraysel.report.plots import figure, styled

__all__ = ["BEAMS_COLUMNS", "PARETO_COLUMNS", "FRESH_RANDOM", "BASELINES", "beam_rows", "pareto_rows",
           "non_dominated", "pareto_figure"]

#: columns of ``beams.csv``
BEAMS_COLUMNS = ("config", "seed", "options", "point", "theta_x_deg", "theta_y_deg", "range_mm", "PSL_dB", "ISLR_dB",
                 "GLL_dB", "width_x_mm", "width_y_mm", "width_z_mm")
#: columns of ``pareto.csv``
PARETO_COLUMNS = ("config", "seed", "k", "worst_PSL_dB", "mean_width_mm", "worst_GLL_dB", "mean_ISLR_dB", "Mean",
                  "on_front", "baseline")
#: the configuration label of the fresh random selections' median
FRESH_RANDOM = "random (fresh median)"
#: configurations drawn as baselines
BASELINES = ("full", "uniform", "spiral", "random", FRESH_RANDOM)


def beam_rows(config: str, seed, options: str, points: list[tuple], metrics: dict, index: int = 0) -> list[dict]:
    """The ``beams.csv`` rows of one selection: ``points`` ``[(label, theta_x, theta_y, range_m)]``,
    ``metrics`` ``{name: (B, P)}`` of :meth:`SectorObjective.beam_metrics` (row ``index``)."""
    out = []
    for j, (label, ax, ay, r) in enumerate(points):
        out.append({"config": config, "seed": seed, "options": options, "point": label, "theta_x_deg": ax,
                    "theta_y_deg": ay, "range_mm": r * 1e3, "PSL_dB": metrics["PSL_dB"][index, j],
                    "ISLR_dB": metrics["ISLR_dB"][index, j], "GLL_dB": metrics["GLL_dB"][index, j],
                    "width_x_mm": metrics["width_x_6dB"][index, j] * 1e3,
                    "width_y_mm": metrics["width_y_6dB"][index, j] * 1e3,
                    "width_z_mm": metrics["width_z_6dB"][index, j] * 1e3 if "width_z_6dB" in metrics else np.nan})
    return out


def summary(metrics: dict, index: int) -> dict:
    """The two Pareto axes (and two more statistics) of selection ``index`` of ``metrics``."""
    wx, wy = metrics["width_x_6dB"][index], metrics["width_y_6dB"][index]
    w = np.where(np.isnan(wy), wx, (wx + wy) / 2) * 1e3       # a 1-D scene: the lateral width alone
    gll = metrics["GLL_dB"][index]
    return {"worst_PSL_dB": float(np.max(metrics["PSL_dB"][index])), "mean_width_mm": float(np.mean(w)),
            "worst_GLL_dB": float(np.max(gll)) if not np.isnan(gll).all() else float("nan"),
            "mean_ISLR_dB": float(np.mean(metrics["ISLR_dB"][index]))}


def non_dominated(a, b) -> np.ndarray:
    """Boolean (n,): the points ``(a_i, b_i)`` (both lower is better) that no other point dominates
    (no worse on both and better on one); NaN points are never on the front."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    ok = np.isfinite(a) & np.isfinite(b)
    out = np.zeros(a.shape, dtype=bool)
    for i in np.flatnonzero(ok):
        dom = ok & (a <= a[i]) & (b <= b[i]) & ((a < a[i]) | (b < b[i]))
        out[i] = not dom.any()
    return out


def pareto_rows(rows: list[dict], k: int) -> list[dict]:
    """``rows`` (each with ``config``, ``seed``, ``k``, the :func:`summary` keys, ``Mean``) with
    ``on_front`` (non-dominated among the rows of ``k`` elements) and ``baseline`` set."""
    fixed = [i for i, r in enumerate(rows) if int(r["k"]) == int(k)]
    front = non_dominated([rows[i]["worst_PSL_dB"] for i in fixed], [rows[i]["mean_width_mm"] for i in fixed])
    on = {i for i, f in zip(fixed, front) if f}
    return [{**r, "on_front": i in on, "baseline": str(r["config"]).split("[")[0] in BASELINES}
            for i, r in enumerate(rows)]


@styled
def pareto_figure(table):
    """The Pareto front (``pareto.csv`` as a DataFrame): worst side lobe against mean -6 dB width,
    each selection a dot, the front joined, every baseline marked and named. Returns a Figure."""
    fig = figure((6.4, 4.6))
    ax = fig.add_subplot(1, 1, 1)
    base = table[table["baseline"].astype(bool)]
    other = table[~table["baseline"].astype(bool)]
    for config, g in other.groupby("config", sort=False):
        ax.scatter(g["mean_width_mm"], g["worst_PSL_dB"], s=18, alpha=0.8, label=str(config))
    front = table[table["on_front"].astype(bool)].sort_values("mean_width_mm")
    if len(front):
        ax.step(front["mean_width_mm"], front["worst_PSL_dB"], where="post", color="k", lw=1.0, label="Pareto front")
    for _, r in base.drop_duplicates("config").iterrows():
        ax.scatter([r["mean_width_mm"]], [r["worst_PSL_dB"]], marker="s", s=40, edgecolors="k", facecolors="none")
        ax.annotate(str(r["config"]), (r["mean_width_mm"], r["worst_PSL_dB"]), textcoords="offset points",
                    xytext=(4, 4), fontsize=7)
    ax.set_xlabel("mean -6 dB main-lobe width over the points (mm)")
    ax.set_ylabel("worst side lobe over the points, PSL (dB)")
    ks = table.loc[table["on_front"].astype(bool), "k"] if table["on_front"].astype(bool).any() else table["k"]
    ax.set_title(f"Pareto front at k = {int(ks.min()) if len(ks) else 0}: lower left is better")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return fig
