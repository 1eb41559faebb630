"""The points of a sector scene as a designer reads them (``docs/sector.md``): each point's image,
the widths and side lobes per depth, the cysts' contrast.

* :func:`point_images_figure` (``points-40dB.png``, ``points-60dB.png``): one panel per selection
  (rows) and point (columns), the point's image on its surface (the one the scene scores: the
  sphere of its range over the sector, drawn at its lateral positions ``x = R u``, ``y = R v`` in
  mm) in dB relative to its own peak, down to the dynamic range;
* :func:`depth_table` (``depths.csv``) and :func:`depth_figure` (``depths.png``): the -6 dB widths
  and the peak side lobe of each selection per point, as the published tables give them (one row
  per selection, one column per point and metric), from ``beams.csv``;
* :func:`cyst_rows` (``cysts.csv``): CR and gCNR per selection and cyst; :func:`cyst_images_figure`
  a cyst's phantom image through each selection.
"""
from __future__ import annotations

import math

import numpy as np

from arraysel.errors import ParameterError
from arraysel.report.plots import figure, styled

__all__ = ["image_db", "point_images_figure", "DEPTH_METRICS", "depth_table", "depth_figure", "CYSTS_COLUMNS",
           "cyst_rows", "cyst_images_figure"]

#: the metrics of ``depths.csv``, from ``beams.csv``
DEPTH_METRICS = ("width_x_mm", "width_y_mm", "PSL_dB", "ISLR_dB", "GLL_dB")
#: columns of ``cysts.csv``
CYSTS_COLUMNS = ("config", "seed", "point", "theta_x_deg", "theta_y_deg", "range_mm", "radius_mm", "CR_dB", "gCNR")


def image_db(image, dynamic_range: float) -> np.ndarray:
    """``20 log10(|image| / max |image|)`` clipped below at ``-dynamic_range`` (float64): what a
    panel of :func:`point_images_figure` shows."""
    if not (isinstance(dynamic_range, (int, float)) and dynamic_range > 0):
        raise ParameterError(f"dynamic_range must be > 0 dB, got {dynamic_range!r}")
    a = np.abs(np.asarray(image))
    peak = a.max() if a.size else 0.0
    if not (peak > 0 and math.isfinite(peak)):
        raise ParameterError("an image is all zero or not finite")
    return np.maximum(20 * np.log10(np.maximum(a / peak, 1e-300)), -float(dynamic_range))


@styled
def point_images_figure(labels: list[str], point_labels: list[str], images, extents: list[tuple],
                        dynamic_range: float = 40.0):
    """The figure of the module docstring: ``images`` complex or real (B, P, H, W) (selection,
    point), ``extents`` one ``(x0, x1, y0, y1)`` in mm per point. Returns a Figure."""
    images = np.asarray(images)
    B, P = len(labels), len(point_labels)
    if images.ndim != 4 or images.shape[:2] != (B, P):
        raise ParameterError(f"images must have shape ({B}, {P}, H, W), got {images.shape}")
    if len(extents) != P:
        raise ParameterError(f"extents must hold one (x0, x1, y0, y1) per point ({P}), got {len(extents)}")
    fig = figure((2.3 * P + 0.9, 2.2 * B + 0.5))
    im = None
    for b, label in enumerate(labels):
        for p, point in enumerate(point_labels):
            ax = fig.add_subplot(B, P, b * P + p + 1)
            im = ax.imshow(image_db(images[b, p], dynamic_range), origin="lower", cmap="gray",
                           vmin=-dynamic_range, vmax=0, extent=extents[p], aspect="equal", interpolation="nearest")
            ax.set_title(f"{label}\n{point}", fontsize=7)
            ax.tick_params(labelsize=6)
            if b == B - 1:
                ax.set_xlabel("x = R u (mm)", fontsize=7)
            if p == 0:
                ax.set_ylabel("y = R v (mm)", fontsize=7)
    fig.subplots_adjust(hspace=0.5, wspace=0.35, top=1 - 0.45 / (2.2 * B + 0.5))
    if im is not None:
        bar = fig.colorbar(im, ax=fig.axes, shrink=0.5, fraction=0.03, pad=0.02)
        bar.set_label(f"dB re. the point's peak ({dynamic_range:g} dB range)")
    fig.suptitle("each point's image on its surface (the sphere of its range over the sector), as the scene "
                 "scores it", fontsize=8)
    return fig


def _on_axis(beams):
    ok = (beams["theta_x_deg"].abs() < 1e-9) & (beams["theta_y_deg"].abs() < 1e-9)
    return beams[ok] if ok.any() else beams


def depth_table(beams):
    """``depths.csv`` from ``beams.csv`` rows: one row per configuration, the columns
    ``{metric}@{point}`` for each metric of :data:`DEPTH_METRICS` and each point, in the order of
    the rows (points by range)."""
    import pandas as pd

    if not len(beams):
        return pd.DataFrame(columns=["config"])
    order = beams.drop_duplicates("point").assign(_r=lambda d: d["range_mm"].round(6)) \
        .sort_values(["_r", "theta_x_deg", "theta_y_deg"], kind="stable")
    points = list(order["point"])
    out = []
    for config, grp in beams.groupby("config", sort=False):
        row = {"config": config}
        by = grp.set_index("point")
        for metric in DEPTH_METRICS:
            for pt in points:
                row[f"{metric}@{pt}"] = float(by.loc[pt, metric]) if pt in by.index else math.nan
        out.append(row)
    return pd.DataFrame(out)


@styled
def depth_figure(beams):
    """``depths.png``: the -6 dB width in x and the peak side lobe against range for each
    configuration, on the points on the axis (all points when none is on the axis)."""
    sub = _on_axis(beams)
    fig = figure((9.0, 3.4))
    axes = [fig.add_subplot(1, 2, i + 1) for i in range(2)]
    for config, grp in sub.groupby("config", sort=False):
        g = grp.sort_values("range_mm")
        style = "--" if str(config).split(" ")[0] in ("full", "uniform", "spiral", "random") else "-"
        axes[0].plot(g["range_mm"], g["width_x_mm"], style, marker="o", ms=3, label=str(config))
        axes[1].plot(g["range_mm"], g["PSL_dB"], style, marker="o", ms=3, label=str(config))
    axes[0].set_ylabel("-6 dB width in x (mm)")
    axes[1].set_ylabel("peak side lobe over the sector (dB)")
    for ax in axes:
        ax.set_xlabel("range (mm)")
        ax.grid(True)
    axes[1].legend(fontsize=6, loc="best")
    fig.suptitle("per depth, points on the axis (beams.csv)", fontsize=8)
    return fig


def cyst_rows(config: str, seed, points: list[tuple], radius_m: float, metrics: dict, index: int) -> list[dict]:
    """The ``cysts.csv`` rows of one selection: ``points`` ``[(label, theta_x, theta_y, range_m)]``
    of the cysts, ``metrics`` of :func:`~arraysel.objective.cysts.score_cysts` (row ``index``)."""
    return [{"config": config, "seed": seed, "point": label, "theta_x_deg": ax, "theta_y_deg": ay,
             "range_mm": r * 1e3, "radius_mm": radius_m * 1e3, "CR_dB": float(metrics["CR_dB"][index, j]),
             "gCNR": float(metrics["gCNR"][index, j])} for j, (label, ax, ay, r) in enumerate(points)]


@styled
def cyst_images_figure(labels: list[str], envelopes, extent: tuple, radius_mm: float, centre_mm=(0.0, 0.0),
                       dynamic_range: float = 40.0, titles: list[str] | None = None):
    """One panel a selection: a cyst phantom's envelope image (B, H, W) in dB re. its own peak,
    ``extent`` ``(x0, x1, y0, y1)`` mm, shown out to three radii around the cyst, its outline
    (``radius_mm`` around ``centre_mm``) dashed; ``titles`` (default the labels) above the panels. Returns a Figure."""
    env = np.asarray(envelopes, dtype=np.float64)
    if env.ndim != 3 or env.shape[0] != len(labels):
        raise ParameterError(f"envelopes must have shape ({len(labels)}, H, W), got {env.shape}")
    n = len(labels)
    cols = min(n, 4)
    rows = max(1, math.ceil(n / cols))
    fig = figure((2.6 * cols + 0.8, 2.5 * rows + 0.4))
    t = np.linspace(0, 2 * math.pi, 181)
    im = None
    for b in range(n):
        ax = fig.add_subplot(rows, cols, b + 1)
        im = ax.imshow(image_db(env[b], dynamic_range), origin="lower", cmap="gray", vmin=-dynamic_range, vmax=0,
                       extent=extent, aspect="equal", interpolation="bilinear")
        ax.plot(centre_mm[0] + radius_mm * np.cos(t), centre_mm[1] + radius_mm * np.sin(t), "c--", lw=0.6)
        ax.set_xlim(centre_mm[0] - 3 * radius_mm, centre_mm[0] + 3 * radius_mm)   # the cyst and its ring
        ax.set_ylim(centre_mm[1] - 3 * radius_mm, centre_mm[1] + 3 * radius_mm)
        ax.set_title((titles or labels)[b], fontsize=7)
        ax.tick_params(labelsize=6)
        ax.set_xlabel("x (mm)", fontsize=7)
    fig.subplots_adjust(hspace=0.55, wspace=0.3)
    if im is not None:
        bar = fig.colorbar(im, ax=fig.axes, shrink=0.5, fraction=0.03, pad=0.02)
        bar.set_label(f"envelope, dB re. peak ({dynamic_range:g} dB)")
    return fig
