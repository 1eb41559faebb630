"""Every figure arraysel draws: each function returns a matplotlib :class:`~matplotlib.figure.Figure`
and the caller (a command, ``compare``) saves it with :func:`save_figure` (atomic PNG,
:data:`DPI`). Nothing here selects a matplotlib backend or touches pyplot state: figures are
built with the object API (``matplotlib.figure.Figure``), so notebooks keep their own backend.

One style for every figure of arraysel (``compare``, ``psf --plot``, ``train``): fonts and
resolution from :data:`STYLE`, applied by :func:`figure_style` while a figure is built (the
:func:`styled` decorator) and while it is saved; PSF images in dB over :data:`DYN_RANGE_DB`
(:data:`IMAGE_CMAP`, peak at 0 dB), profiles down to :data:`PROFILE_FLOOR_DB`, masks in
:data:`MASK_CMAP`, axes in millimetres from the peak when the pixel pitch is known (pixels
otherwise, e.g. the toy objective's synthetic kernels).

Every figure function also draws into a caller's matplotlib Axes: ``ax=`` one Axes for a
one-panel figure, or a sequence of as many Axes as the figure has panels (the function's
docstring says how many, in order); it then returns the caller's Figure, leaves its layout alone
(no ``tight_layout``) and adds the colour bar, where there is one, next to those Axes.

Public helpers for other figure modules (``arraysel.e2e.figures``): :func:`styled`,
:func:`figure`, :func:`db`, :func:`extent_mm`, :func:`psf_image` (one PSF on an axis),
:func:`profile_lines` (lateral and axial profiles through the peaks), :func:`mask_strip`
(active elements, one row per selection).
"""
from __future__ import annotations

import contextlib
import contextvars
import functools
import io
import math
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from arraysel.selection import Selection

__all__ = ["DYN_RANGE_DB", "PROFILE_FLOOR_DB", "DPI", "IMAGE_CMAP", "MASK_CMAP", "STYLE", "figure_style", "styled",
           "figure", "db", "extent_mm", "psf_image", "profile_lines", "mask_strip", "masks_figure", "selections_figure", "psfs_figure", "profiles_figure", "trace_figure", "psf_figure", "plot_anytime",
           "ecdf_targets", "save_figure", "collect_figures",
           "matrix_masks_figure", "plane_extent_mm", "plane_image", "planes_figure", "lateral_profiles_figure"]

#: dynamic range (dB) of every PSF image
DYN_RANGE_DB = 40.0
#: lower limit (dB) of every PSF profile plot
PROFILE_FLOOR_DB = -60.0
#: resolution of every saved figure
DPI = 110
#: colour map of every PSF and B-mode image
IMAGE_CMAP = "gray"
#: colour map of every element mask (active elements black)
MASK_CMAP = "Greys"
#: matplotlib settings of every figure (:func:`figure_style`)
STYLE = {
    "font.family": "DejaVu Sans", "font.size": 9.0, "axes.titlesize": 9.0, "axes.labelsize": 9.0,
    "xtick.labelsize": 8.0, "ytick.labelsize": 8.0, "legend.fontsize": 7.0, "figure.titlesize": 10.0,
    "figure.dpi": DPI, "savefig.dpi": DPI, "image.cmap": IMAGE_CMAP, "grid.alpha": 0.3,
}

#: where :func:`collect_figures` keeps the figures :func:`save_figure` saves (None: not kept)
_FIGURES: "contextvars.ContextVar[dict | None]" = contextvars.ContextVar("arraysel_figures", default=None)


@contextlib.contextmanager
def figure_style():
    """Context manager: matplotlib's settings are :data:`STYLE` inside it (``rc_context``; the
    caller's settings come back after it)."""
    import matplotlib

    with matplotlib.rc_context(STYLE):
        yield


def styled(fn):
    """Decorator of a function that builds a figure: it runs under :func:`figure_style`."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with figure_style():
            return fn(*args, **kwargs)
    return wrapper


def _axes(ax, n: int, figsize, **subplots):
    """``(figure, [n Axes])``: a new figure of ``figsize`` with ``fig.subplots(**subplots)`` when
    ``ax`` is None, else the caller's ``ax`` (one Axes, or a sequence of ``n``) and its figure."""
    if ax is None:
        fig = figure(figsize)
        return fig, list(np.atleast_1d(fig.subplots(**subplots)).ravel())
    axes = [ax] if hasattr(ax, "figure") and not isinstance(ax, (list, tuple, np.ndarray)) else \
        list(np.asarray(ax, dtype=object).ravel())
    if len(axes) != n:
        from arraysel.errors import ParameterError

        raise ParameterError(f"ax: this figure draws {n} panel(s); give {'one Axes' if n == 1 else f'{n} Axes'}, "
                             f"got {len(axes)}")
    return axes[0].figure, axes


def figure(figsize):
    """A new :class:`~matplotlib.figure.Figure` of ``figsize`` inches (object API, no pyplot)."""
    from matplotlib.figure import Figure

    return Figure(figsize=figsize)


# ---------------------------------------------------------------------------
# saving
# ---------------------------------------------------------------------------

def save_figure(fig, path: str | Path) -> None:
    """Write ``fig`` as a PNG (:data:`DPI`, tight box) to ``path`` atomically (:mod:`arraysel.io.atomic`)."""
    from arraysel.io.atomic import atomic_write_bytes

    buf = io.BytesIO()
    with figure_style():
        fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())
    sink = _FIGURES.get()
    if sink is not None:
        sink[Path(path).stem] = fig


@contextlib.contextmanager
def collect_figures():
    """Context manager: the figures saved inside it are also kept, ``{file stem: Figure}``
    (the Python API returns them to notebooks)."""
    sink: dict = {}
    token = _FIGURES.set(sink)
    try:
        yield sink
    finally:
        _FIGURES.reset(token)


# ---------------------------------------------------------------------------
# building blocks
# ---------------------------------------------------------------------------

def db(k: np.ndarray, ref_peak: float | None = None) -> np.ndarray:
    """``20 log10(|k| / ref_peak)`` (``ref_peak``: the peak of ``|k|`` itself), floored at -240 dB."""
    mag = np.abs(np.asarray(k))
    peak = float(mag.max()) if ref_peak is None else float(ref_peak)
    return 20 * np.log10(np.maximum(mag / max(peak, np.finfo(float).tiny), 1e-12))


def extent_mm(shape: tuple[int, int], pitch: float | None) -> list[float] | None:
    """``imshow`` extent (left, right, bottom, top) in mm of a ``(rows, cols)`` window centred on its
    middle pixel, rows going down; ``None`` without a pitch (pixel axes)."""
    if pitch is None:
        return None
    rows, cols = shape
    return [-cols / 2 * pitch * 1e3, cols / 2 * pitch * 1e3, rows / 2 * pitch * 1e3, -rows / 2 * pitch * 1e3]


def _axis_labels(ax, pitch: float | None) -> None:
    if pitch is None:
        ax.set_xlabel("lateral pixel")
        ax.set_ylabel("axial pixel")
    else:
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("z - z_peak (mm)")


def psf_image(ax, kernel: np.ndarray, pitch: float | None = None, *, ref_peak: float | None = None,
              title: str | None = None, ticks: bool = True):
    """Draw ``|kernel|`` in dB (:data:`DYN_RANGE_DB`, relative to ``ref_peak`` or its own peak) on
    ``ax``, in mm when ``pitch`` (metres per pixel) is given; returns the image (for a colorbar)."""
    im = ax.imshow(db(kernel, ref_peak), vmin=-DYN_RANGE_DB, vmax=0, cmap=IMAGE_CMAP,
                   extent=extent_mm(np.shape(kernel), pitch))
    if title is not None:
        ax.set_title(title)
    if ticks:
        _axis_labels(ax, pitch)
    else:
        ax.set_xticks([])
        ax.set_yticks([])
    return im


def mask_strip(ax, labels: Sequence[str], masks: np.ndarray) -> None:
    """Active elements (black), one row per selection: ``masks`` ``(rows, Ne)`` of 0/1."""
    masks = np.asarray(masks, dtype=float).reshape(len(labels), -1)
    if len(labels):
        ax.imshow(masks, aspect="auto", cmap=MASK_CMAP, vmin=0, vmax=1, interpolation="nearest")
    ax.set_yticks(range(len(labels)), list(labels))
    ax.set_xlabel("element index")
    ax.set_title("active elements")


# ---------------------------------------------------------------------------
# figures of ``arraysel compare``
# ---------------------------------------------------------------------------

@styled
def masks_figure(labels: Sequence[str], masks: np.ndarray, *, ax=None):
    """``masks.png``: the active elements of every configuration (``masks`` ``(rows, Ne)``); one panel."""
    fig, (axis,) = _axes(ax, 1, (8, 0.4 * max(len(labels), 1) + 1.2))
    mask_strip(axis, labels, masks)
    return fig


def selections_figure(selections: Mapping[str, Selection], *, ax=None):
    """``masks.png`` of named :class:`~arraysel.selection.Selection` s (the empty ones left out); one panel."""
    kept = {name: sel for name, sel in selections.items() if len(sel)}
    n = max((sel.n_elements for sel in kept.values()), default=1)
    masks = np.array([sel.mask for sel in kept.values()], dtype=bool).reshape(len(kept), n)
    return masks_figure(list(kept), masks, ax=ax)


@styled
def psfs_figure(labels: Sequence[str], kernels: np.ndarray, ref: np.ndarray, pitch: float | None = None, *,
                ax=None):
    """``psfs.png``: the full array's PSF, then each configuration's, in dB relative to the full
    array's peak; ``len(labels) + 1`` panels (the full array's first)."""
    peak = float(np.abs(ref).max())
    cols = min(4, len(labels) + 1)
    rows = math.ceil((len(labels) + 1) / cols)
    fig, axes = _axes(ax, len(labels) + 1, (3 * cols, 3 * rows), nrows=rows, ncols=cols)
    if ax is not None:
        cols = len(axes)  # the caller's layout: labels on every panel but the first's y label
    im = None
    for i, (ax, (lab, kk)) in enumerate(zip(axes, [("full (reference)", ref)] + list(zip(labels, kernels)))):
        im = psf_image(ax, kk, pitch, ref_peak=peak, title=lab)
        if i % cols:  # axis labels on the first column and the bottom row only
            ax.set_ylabel("")
        if i + cols <= len(labels):
            ax.set_xlabel("")
    for ax in axes[len(labels) + 1:]:
        ax.axis("off")
    fig.colorbar(im, ax=list(axes), label="dB", shrink=0.8)
    return fig


def profile_lines(ax_l, ax_a, kernels: dict, pitch: float | None = None, *, ref_peak: float | None = None,
                  bold: Sequence[str] = ("full",)) -> None:
    """Lateral (``ax_l``) and axial (``ax_a``) profiles through each kernel's peak, in dB of
    ``ref_peak`` (each kernel's own peak without it) down to :data:`PROFILE_FLOOR_DB`, against
    the distance from the peak (mm with ``pitch``, pixels without); ``kernels`` ``{label: kernel}``,
    the labels in ``bold`` drawn thick and black."""
    for lab, kk in kernels.items():
        kk = np.asarray(kk)
        r, c = np.unravel_index(int(np.argmax(np.abs(kk))), kk.shape)
        style = dict(color="k", lw=2) if lab in bold else dict(lw=1)
        x_l = np.arange(kk.shape[1]) - c
        x_a = np.arange(kk.shape[0]) - r
        if pitch is not None:
            x_l, x_a = x_l * pitch * 1e3, x_a * pitch * 1e3
        peak = float(np.abs(kk).max()) if ref_peak is None else ref_peak
        ax_l.plot(x_l, db(kk[r, :], peak), label=lab, **style)
        ax_a.plot(x_a, db(kk[:, c], peak), label=lab, **style)
    unit = "pixel" if pitch is None else "mm"
    for ax, what in ((ax_l, "lateral"), (ax_a, "axial")):
        ax.set_ylim(PROFILE_FLOOR_DB, 3)
        ax.set_xlabel(f"{what} distance from the peak ({unit})")
        ax.set_ylabel("dB")
        ax.set_title(f"{what} profile through the peak")
    ax_a.legend()


@styled
def profiles_figure(labels: Sequence[str], kernels: np.ndarray, ref: np.ndarray, pitch: float | None = None, *,
                    ax=None):
    """``profiles.png``: lateral and axial profiles through each PSF's peak, against the full
    array's; two panels (lateral, axial)."""
    fig, (ax_l, ax_a) = _axes(ax, 2, (10, 4), nrows=1, ncols=2)
    profile_lines(ax_l, ax_a, {"full": ref, **dict(zip(labels, kernels))}, pitch,
                  ref_peak=float(np.abs(ref).max()))
    return fig


@styled
def trace_figure(trace, full_mean: float | None = None, *, ax=None):
    """``trace.png``: the best Mean against time of every run (log time); one panel."""
    fig, (ax,) = _axes(ax, 1, (7, 4.5))
    if trace is not None and len(trace):
        for (config, seed), g in trace.groupby(["config", "seed"], sort=False):
            g = g.sort_values("seconds")
            x = np.maximum(g["seconds"].to_numpy(float), 1e-4)
            y = g["best_Mean"].to_numpy(float)
            line, = ax.step(x, y, where="post", label=f"{config} (seed {seed})")
            ax.plot(x[-1:], y[-1:], marker="o", ms=4, color=line.get_color())  # single-point runs too
        ax.set_xscale("log")
        ax.legend()
    if full_mean is not None and np.isfinite(full_mean):
        ax.axhline(float(full_mean), color="k", ls="--", lw=1, label="full")
    ax.set_xlabel("seconds")
    ax.set_ylabel("best Mean")
    ax.set_title("best Mean vs time")
    return fig


# ---------------------------------------------------------------------------
# ``arraysel psf --plot``
# ---------------------------------------------------------------------------

@styled
def psf_figure(kernel: np.ndarray, ref: np.ndarray, pitch: float | None, elements: Sequence[int] | Selection,
               n_elements: int, *, ax=None):
    """One selection's PSF and the full array's, each in dB of its own peak, with the mask
    (``elements``: a :class:`~arraysel.selection.Selection` or its indices); three panels (the
    selection's PSF, the full array's, the mask)."""
    fig, axes = _axes(ax, 3, (12, 4), nrows=1, ncols=3, gridspec_kw={"width_ratios": [1, 1, 1.2]})
    im = None
    for ax, k, title in ((axes[0], kernel, "selection"), (axes[1], ref, "full array")):
        im = psf_image(ax, k, pitch, title=f"PSF, {title}")
    axes[1].set_ylabel("")
    fig.colorbar(im, ax=list(axes[:2]), label="dB")
    mask = np.zeros(n_elements)
    mask[list(elements)] = 1
    axes[2].bar(np.arange(n_elements), mask, width=0.8)
    axes[2].set_title(f"active elements ({len(elements)} of {n_elements})")
    axes[2].set_xlabel("element")
    axes[2].set_yticks([])
    return fig



def _best_at(g, x: np.ndarray, column: str) -> np.ndarray:
    """Best-so-far Mean of one run at the points ``x`` of ``column`` (+inf before its first row;
    after its last row the run's final best holds)."""
    g = g.sort_values([column, "best_Mean"], ascending=[True, False])
    xs = g[column].to_numpy(float)
    ys = np.minimum.accumulate(g["best_Mean"].to_numpy(float))
    idx = np.searchsorted(xs, x, side="right") - 1
    return np.where(idx >= 0, ys[np.clip(idx, 0, None)], np.inf)


def _grid(values: np.ndarray, points: int = 200) -> np.ndarray:
    v = values[np.isfinite(values) & (values > 0)]
    if not v.size:
        return np.array([1.0])
    lo, hi = float(v.min()), float(v.max())
    if hi <= lo:
        hi = lo * 1.01
    return np.unique(np.concatenate([np.geomspace(lo, hi, points), v]))


def ecdf_targets(trace, count: int = 51) -> np.ndarray:
    """Targets of the ECDF: ``count`` values spaced evenly in log(Mean) between the best
    Mean any run reached and the largest first value of a run."""
    firsts = trace.sort_values("evaluations").groupby(["config", "seed"], sort=False)["best_Mean"].first()
    lo = float(trace["best_Mean"].min())
    hi = float(firsts.max())
    if not (np.isfinite(lo) and np.isfinite(hi)) or lo <= 0 or hi <= lo:
        return np.array([lo])
    return np.geomspace(hi, lo, count)


@styled
def plot_anytime(trace, full_mean: float | None = None, targets: np.ndarray | None = None, *, ax=None):
    """Anytime comparison over seeds; returns a matplotlib ``Figure`` (the caller saves it); three
    panels (against seconds, against evaluations, the ECDF).

    Panels: per config, the median over its runs of the best-so-far Mean with
    the interquartile band, (a) against wall seconds and (b) against
    evaluations (log x), and (c) the ECDF of (run, target) pairs reached
    against seconds, COCO / IOHanalyzer style: for each run and each target of
    :func:`ecdf_targets`, the time the run's best first reached the target;
    the curve is the fraction of all (run, target) pairs of the config reached
    by then. Every config appears, runs of one evaluation included (their curve
    starts at that point, marked, and holds to the end of the x range).
    ``full_mean`` draws the full array's Mean as a dashed line.
    """
    own = ax is None  # a caller's figure keeps its layout
    fig, (ax_t, ax_e, ax_c) = _axes(ax, 3, (15, 4.6), nrows=1, ncols=3)
    if trace is None or not len(trace):
        for ax in (ax_t, ax_e, ax_c):
            ax.text(0.5, 0.5, "no trace", ha="center", va="center", transform=ax.transAxes)
        return fig
    trace = trace[np.isfinite(trace["best_Mean"].astype(float))].copy()
    trace["seconds"] = np.maximum(trace["seconds"].astype(float), 1e-4)
    trace["evaluations"] = np.maximum(trace["evaluations"].astype(float), 1.0)
    targets = ecdf_targets(trace) if targets is None else np.asarray(targets, dtype=float)
    colours = {}
    for config, gc in trace.groupby("config", sort=False):
        runs = [g for _, g in gc.groupby("seed", sort=False)]
        colour = None
        for ax, column, label in ((ax_t, "seconds", "seconds"), (ax_e, "evaluations", "evaluations")):
            x = _grid(trace[column].to_numpy(float))
            y = np.array([_best_at(g, x, column) for g in runs])
            with np.errstate(invalid="ignore"):
                q25, med, q75 = np.percentile(y, [25, 50, 75], axis=0)
            ok = np.isfinite(med)
            line, = ax.step(x[ok], med[ok], where="post", color=colour, lw=1.5,
                            label=f"{config} ({len(runs)} run{'s' if len(runs) != 1 else ''})")
            colour = line.get_color()
            band = ok & np.isfinite(q25) & np.isfinite(q75)
            ax.fill_between(x[band], q25[band], q75[band], step="post", color=colour, alpha=0.2, lw=0)
            if ok.any():
                first = int(np.flatnonzero(ok)[0])
                ax.plot([x[first]], [med[first]], marker="o", ms=4, color=colour)
            ax.set_xscale("log")
            ax.set_xlabel(label)
        colours[config] = colour
        # ECDF of (run, target) pairs over time
        hits = []
        for g in runs:
            g = g.sort_values("seconds")
            best = np.minimum.accumulate(g["best_Mean"].to_numpy(float))
            secs = g["seconds"].to_numpy(float)
            for tgt in targets:
                reached = np.flatnonzero(best <= tgt)
                hits.append(secs[reached[0]] if reached.size else np.inf)
        hits = np.sort(np.asarray(hits, dtype=float))
        x = _grid(trace["seconds"].to_numpy(float))
        frac = np.searchsorted(hits, x, side="right") / max(len(hits), 1)
        ax_c.step(x, frac, where="post", color=colour, label=config)
        ax_c.plot([x[-1]], [frac[-1]], marker="o", ms=4, color=colour)
    for ax, what in ((ax_t, "time"), (ax_e, "evaluations")):
        if full_mean is not None and np.isfinite(full_mean):
            ax.axhline(full_mean, color="k", ls="--", lw=1, label="full array")
        ax.set_yscale("log")
        ax.set_ylabel("best Mean so far (median, IQR band)")
        ax.set_title(f"best Mean vs {what}")
    ax_t.legend()
    ax_c.set_xscale("log")
    ax_c.set_ylim(-0.02, 1.02)
    ax_c.set_xlabel("seconds")
    ax_c.set_ylabel("fraction of (run, target) pairs reached")
    ax_c.set_title(f"ECDF, {len(targets)} targets in [{targets.min():.3g}, {targets.max():.3g}]")
    if own:
        fig.tight_layout()
    return fig


# ---------------------------------------------------------------------------
# matrix probes: masks on the grid, the planes of a 3-D PSF, lateral profiles
# ---------------------------------------------------------------------------

def _as_numpy(x) -> np.ndarray:
    """A numpy array of ``x`` (numpy, list or a torch tensor on any device, detached)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _panels(n: int, cols: int = 4, size: float = 3.0, extra_width: float = 0.0):
    """A figure with ``n`` axes in rows of at most ``cols``; the unused axes switched off."""
    cols = max(1, min(cols, n))
    rows = max(1, math.ceil(n / cols))
    fig = figure((size * cols + extra_width, size * rows))
    axes = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    for ax in axes[n:]:
        ax.axis("off")
    return fig, axes[:n]


@styled
def matrix_masks_figure(labels: Sequence[str], masks: np.ndarray, grid: tuple[int, int], *, ax=None):
    """The active elements of each selection on a matrix array: one ``ny x nx`` image per label
    (element index ``iy * nx + ix``; black = active), columns ``ix`` across, rows ``iy`` up; one
    panel per label."""
    ny, nx = (int(v) for v in grid)
    masks = _as_numpy(masks).astype(float).reshape(len(labels), ny * nx)
    fig, axes = _panels(len(labels), size=2.6) if ax is None else _axes(ax, len(labels), None)
    for ax, lab, m in zip(axes, labels, masks):
        ax.imshow(m.reshape(ny, nx), cmap="Greys", vmin=0, vmax=1, origin="lower", interpolation="nearest",
                  extent=(-0.5, nx - 0.5, -0.5, ny - 0.5))
        ax.set_title(f"{lab} ({int(m.sum())} of {ny * nx})", fontsize=8)
        ax.set_xlabel("element column ix")
        ax.set_ylabel("element row iy")
    return fig


def _plane_axes(coords: np.ndarray) -> tuple[int, int]:
    """The coordinate (0 x, 1 y, 2 z) that varies along the columns and along the rows of a plane."""
    from arraysel.errors import ParameterError

    h, w = coords.shape[:2]
    if h < 2 or w < 2 or coords.shape[-1] != 3:
        raise ParameterError(f"a plane's coords must be (H, W, 3) with H, W >= 2, got {coords.shape}")
    hc = int(np.argmax(np.abs(coords[0, 1] - coords[0, 0])))
    vc = int(np.argmax(np.abs(coords[1, 0] - coords[0, 0])))
    return hc, vc


def plane_extent_mm(coords) -> tuple[list[float], str, str]:
    """``imshow`` extent (left, right, bottom, top) in mm of a plane with pixel positions ``coords``
    ``(H, W, 3)`` (metres; row 0 on top), and the labels of its horizontal and vertical axes."""
    c = _as_numpy(coords).astype(float) * 1e3
    hc, vc = _plane_axes(c)
    hv, vv = c[0, :, hc], c[:, 0, vc]
    dh = hv[1] - hv[0] if len(hv) > 1 else 1.0
    dv = vv[1] - vv[0] if len(vv) > 1 else 1.0
    extent = [hv[0] - dh / 2, hv[-1] + dh / 2, vv[-1] + dv / 2, vv[0] - dv / 2]
    names = "xyz"
    return [float(e) for e in extent], f"{names[hc]} (mm)", f"{names[vc]} (mm)"


def plane_image(ax, plane, coords, *, ref_peak: float | None = None, title: str | None = None, labels: bool = True):
    """Draw ``|plane|`` in dB (:data:`DYN_RANGE_DB`, relative to ``ref_peak`` or its own peak) on
    ``ax`` with axes in mm from the pixel positions ``coords`` ``(H, W, 3)``; returns the image."""
    extent, xlabel, ylabel = plane_extent_mm(coords)
    im = ax.imshow(db(_as_numpy(plane), ref_peak), vmin=-DYN_RANGE_DB, vmax=0, cmap="gray", extent=extent)
    if title is not None:
        ax.set_title(title, fontsize=8)
    if labels:
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
    return im


@styled
def planes_figure(labels: Sequence[str], planes: dict, coords: dict, ref: dict | None = None, *, ax=None):
    """The planes of 3-D PSFs at :data:`DYN_RANGE_DB`, axes in mm: one row per selection (the full
    array's first when ``ref`` is given), one column per plane (the C-plane ``xy``, ``xz``, ``yz``).

    ``planes`` maps each plane name to an array ``(B, H, W)``, B = ``len(labels)``; ``coords`` to
    its ``(H, W, 3)`` pixel positions (metres); ``ref`` to the full array's ``(H, W)`` (or
    ``(1, H, W)``). Every row is in dB of its own peak over its planes (a sparse array's echo is
    weaker than the full array's: its shape is what the figure compares). Panels: rows x planes,
    row by row.
    """
    names = list(planes)
    rows = [(lab, {n: _as_numpy(planes[n])[i] for n in names}) for i, lab in enumerate(labels)]
    if ref is not None:
        ref = {n: _as_numpy(ref[n]).reshape(_as_numpy(ref[n]).shape[-2:]) for n in names}
        rows.insert(0, ("full array", ref))
    fig, flat = _axes(ax, len(rows) * len(names), (3.2 * len(names) + 1.0, 3.0 * len(rows)), nrows=len(rows),
                      ncols=len(names), squeeze=False)
    axes = np.array(flat, dtype=object).reshape(len(rows), len(names))
    im = None
    for r, (lab, row) in enumerate(rows):
        own = max(float(np.abs(v).max()) for v in row.values())
        for c, name in enumerate(names):
            im = plane_image(axes[r, c], row[name], coords[name], ref_peak=own, title=f"{lab}: {name}")
    fig.colorbar(im, ax=list(axes.ravel()), label="dB", shrink=0.8)
    return fig


@styled
def lateral_profiles_figure(labels: Sequence[str], c_planes, coords, ref=None, *, ax=None):
    """Lateral profiles of the C-plane through its peak, along x and along y, each in dB of its own
    peak, the full array (``ref``) in black; the legend
    gives each -6 dB width (:func:`arraysel.objective.metrics3d.main_lobe_widths`).

    ``c_planes`` ``(B, H, W)`` (B = ``len(labels)``), ``coords`` ``(H, W, 3)`` metres, ``ref``
    ``(H, W)`` or ``(1, H, W)``. Two panels (along x, along y).
    """
    from arraysel.objective.metrics3d import c_plane_profiles, main_lobe_widths

    c = _as_numpy(coords)
    items = [(lab, _as_numpy(c_planes)[i]) for i, lab in enumerate(labels)]
    if ref is not None:
        ref = _as_numpy(ref).reshape(_as_numpy(ref).shape[-2:])
        items.insert(0, ("full", ref))
    fig, (ax_x, ax_y) = _axes(ax, 2, (10, 4), nrows=1, ncols=2)
    for lab, plane in items:
        prof = c_plane_profiles(plane, c)
        widths = main_lobe_widths(plane, c)
        style = dict(color="k", lw=2) if (ref is not None and lab == "full") else dict(lw=1)
        own = float(np.abs(plane).max())
        for ax, letter in ((ax_x, "x"), (ax_y, "y")):
            s, a = prof[letter]
            w = float(widths[letter][0])
            text = f"{w * 1e3:.2f} mm" if np.isfinite(w) else "> window"
            ax.plot(s[0] * 1e3, db(a[0], own), label=f"{lab} (-6 dB: {text})", **style)
    for ax, letter in ((ax_x, "x"), (ax_y, "y")):
        ax.set_ylim(PROFILE_FLOOR_DB, 3)
        ax.axhline(-6.0, color="0.6", lw=0.8, ls=":")
        ax.set_xlabel(f"{letter} (mm)")
        ax.set_ylabel("dB")
        ax.set_title(f"C-plane profile along {letter} through the peak")
        ax.legend(fontsize=7)
    return fig
