"""Figures of a 2-D array drawn from its element positions: selections on a grid with blank rows
or on an imported layout, and an exported aperture.

Each element is a rectangle at its centre (axes in mm, x across, y up, as seen from the medium),
so blank rows and irregular layouts show as they are built. Same style as
:mod:`arraysel.report.plots` (each function returns a :class:`~matplotlib.figure.Figure`; save it
with :func:`arraysel.report.plots.save_figure`).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from arraysel.report.plots import MASK_CMAP, _as_numpy, _panels, figure, styled

__all__ = ["layout_masks_figure", "group_masks_figure", "aperture_figure", "apertures_figure", "TX_COLOUR",
           "RX_COLOUR"]

#: face colour of an element that only transmits, and of one that only receives
TX_COLOUR = "tab:red"
RX_COLOUR = "tab:blue"


def _element_size(pos: np.ndarray) -> tuple[float, float]:
    """A square's side for a layout known by its centres only: 0.8 x the smallest centre distance."""
    if len(pos) < 2:
        return 1.0, 1.0
    d = np.inf
    for start in range(0, len(pos), 1024):
        blk = pos[start:start + 1024]
        dist = np.sqrt(((blk[:, None, :] - pos[None, :, :]) ** 2).sum(-1))
        dist[np.arange(len(blk)), start + np.arange(len(blk))] = np.inf
        d = min(d, float(dist.min()))
    side = 0.8 * d if np.isfinite(d) and d > 0 else 1.0
    return side, side


def _draw(ax, pos_mm: np.ndarray, size_mm: tuple[float, float], faces, edges) -> None:
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle

    w, h = size_mm
    rects = [Rectangle((x - w / 2, y - h / 2), w, h) for x, y in pos_mm]
    ax.add_collection(PatchCollection(rects, facecolors=faces, edgecolors=edges, linewidths=0.4))
    pad = max(w, h)
    ax.set_xlim(pos_mm[:, 0].min() - pad, pos_mm[:, 0].max() + pad)
    ax.set_ylim(pos_mm[:, 1].min() - pad, pos_mm[:, 1].max() + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")


@styled
def layout_masks_figure(labels: Sequence[str], masks, positions, element_size=None):
    """The active elements of each selection (black) on an array known by its element centres
    ``positions`` ``(Ne, 2|3)`` in metres: one panel per label. ``element_size`` ``(width,
    height)`` in metres (default: 0.8 x the smallest distance between centres)."""
    import matplotlib

    pos = np.asarray(positions, dtype=np.float64)[:, :2]
    masks = _as_numpy(masks).astype(float).reshape(len(labels), len(pos))
    size = _element_size(pos) if element_size is None else tuple(float(v) for v in element_size)
    cmap = matplotlib.colormaps[MASK_CMAP]
    fig, axes = _panels(len(labels), size=2.6)
    for ax, lab, m in zip(axes, labels, masks):
        faces = [cmap(0.95) if v > 0.5 else "white" for v in m]
        _draw(ax, pos * 1e3, (size[0] * 1e3, size[1] * 1e3), faces, "0.6")
        ax.set_title(f"{lab} ({int((m > 0.5).sum())} of {len(m)})", fontsize=8)
    return fig


@styled
def group_masks_figure(labels: Sequence[str], masks, positions, groups, element_size=None):
    """The active elements of each selection drawn with their channel groups
    (:mod:`arraysel.constraints`): an active element is coloured by its place in its group (for
    ``mux-1024-4``, the bank it comes from), an inactive one white; a group holding more than one
    active element is edged red. The title gives the groups used and the most elements of one
    group."""
    import matplotlib

    pos = np.asarray(positions, dtype=np.float64)[:, :2]
    g = np.asarray(groups, dtype=np.int64).reshape(len(pos))
    masks = _as_numpy(masks).astype(bool).reshape(len(labels), len(pos))
    member = np.zeros(len(pos), dtype=np.int64)  # the place of each element in its group
    for grp in np.unique(g):
        idx = np.flatnonzero(g == grp)
        member[idx] = np.arange(idx.size)
    colours = matplotlib.colormaps["tab10"]
    size = _element_size(pos) if element_size is None else tuple(float(v) for v in element_size)
    fig, axes = _panels(len(labels), size=2.6)
    for ax, lab, m in zip(axes, labels, masks):
        count = np.bincount(g[m], minlength=int(g.max()) + 1)
        faces = [colours(int(member[e]) % 10) if m[e] else "white" for e in range(len(pos))]
        edges = ["red" if m[e] and count[g[e]] > 1 else "0.6" for e in range(len(pos))]
        _draw(ax, pos * 1e3, (size[0] * 1e3, size[1] * 1e3), faces, edges)
        ax.set_title(f"{lab}: {int((count > 0).sum())}/{count.size} groups, max {int(count.max())}", fontsize=7)
    return fig


def _role_faces(tx: np.ndarray, rx: np.ndarray) -> list:
    """Black: transmits and receives; red: transmits only; blue: receives only; white: off."""
    return ["black" if t and r else TX_COLOUR if t else RX_COLOUR if r else "white" for t, r in zip(tx, rx)]


@styled
def apertures_figure(labels: Sequence[str], transmit, receive, positions, element_size=None):
    """The transmit and receive apertures of each selection (``docs/apertures.md``) on the probe's
    element centres ``positions`` ``(Ne, 2|3)`` in metres, one panel per label: black transmits
    and receives, red transmits only, blue receives only, white is off. ``transmit``,
    ``receive``: boolean ``(len(labels), Ne)``."""
    pos = np.asarray(positions, dtype=np.float64)[:, :2]
    tx = _as_numpy(transmit).astype(bool).reshape(len(labels), len(pos))
    rx = _as_numpy(receive).astype(bool).reshape(len(labels), len(pos))
    size = _element_size(pos) if element_size is None else tuple(float(v) for v in element_size)
    fig, axes = _panels(len(labels), size=2.6)
    for ax, lab, t, r in zip(axes, labels, tx, rx):
        _draw(ax, pos * 1e3, (size[0] * 1e3, size[1] * 1e3), _role_faces(t, r), "0.6")
        ax.set_title(f"{lab}\ntx {int(t.sum())}, rx {int(r.sum())}, both {int((t & r).sum())}", fontsize=7)
    return fig


@styled
def aperture_figure(aperture, title: str | None = None):
    """An aperture (:class:`arraysel.physics.probe_files.Aperture`) on its probe: every element at
    its true size and position (blank rows and columns show as gaps); black: transmits and
    receives, red: transmits only, blue: receives only, white: off. Unequal weights shade the
    active elements (lighter = smaller weight, relative to the largest)."""
    probe = aperture.probe
    pos = probe.element_positions()[:, :2] * 1e3
    tx, rx, w = aperture.transmit, aperture.receive, aperture.weights
    top = float(w.max()) if w.max() > 0 else 1.0
    shade = np.clip(w / top, 0.15, 1.0)
    faces = []
    for t, r, s in zip(tx, rx, shade):
        if t and r:
            faces.append((1 - s, 1 - s, 1 - s, 1.0))
        elif t or r:
            import matplotlib.colors as mcolors

            rgb = mcolors.to_rgb(TX_COLOUR if t else RX_COLOUR)
            faces.append((*(1 - s * (1 - c) for c in rgb), 1.0))
        else:
            faces.append("white")
    span = np.ptp(pos, axis=0) if len(pos) > 1 else np.ones(2)
    aspect = float(span[1] / span[0]) if span[0] > 0 else 1.0
    fig = figure((6.0, min(9.0, max(2.5, 6.0 * aspect))))
    ax = fig.add_subplot(1, 1, 1)
    _draw(ax, pos, (probe.width * 1e3, probe.height * 1e3), faces, "0.55")
    both = int((tx & rx).sum())
    parts = [f"{int(aperture.active.sum())} of {probe.n_elements} elements"]
    if not np.array_equal(tx, rx):
        parts.append(f"transmit {int(tx.sum())} (red: only), receive {int(rx.sum())} (blue: only), both {both}")
    if np.ptp(w[aperture.active]) > 0:
        parts.append(f"weights {w[aperture.active].min():.3g} to {w.max():.3g}")
    ax.set_title(title or f"{probe.name}: " + "; ".join(parts), fontsize=8)
    return fig
