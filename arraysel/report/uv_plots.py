"""The two-way beam pattern of selections in direction cosines: ``beampattern.png`` of a sector
scene's comparison (``docs/sector.md``).

One panel a selection: the broadband two-way (transmit x receive) power pattern
:meth:`~arraysel.physics.beampattern.BeamPattern.pattern` over the shifts ``(du, dv)`` from the
beam's own direction, in dB relative to its peak, down to ``dynamic_range`` dB. Drawn over it:

* the **visible region** of a beam steered straight ahead, the unit circle ``du^2 + dv^2 = 1``;
* the **sector's region**, the rectangle ``|du| <= 2 sin theta_x,max``, ``|dv| <= 2 sin
  theta_y,max``: the shifts under which one beam of the sector sees a point of the sector;
* the **grating lobes of the probe's lattice** at the centre frequency, ``(m lambda / p_x, n lambda
  / p_y)`` (crosses): where a fully populated probe puts them, whatever the selection;
* the **grating lobes of the selection's own lattice** over the band (lines,
  :meth:`~arraysel.physics.beampattern.BeamPattern.grating_directions`): periodic thinning
  (``uniform``) shows here.
"""
from __future__ import annotations

import math

import numpy as np

from arraysel.errors import ParameterError
from arraysel.report.plots import figure, styled

__all__ = ["lattice_grating_lobes", "beam_pattern_figure"]


def lattice_grating_lobes(wavelength: float, pitch_x: float, pitch_y: float, extent: tuple[float, float]) -> np.ndarray:
    """The grating-lobe shifts ``(m lambda / p_x, n lambda / p_y)``, ``(m, n) != (0, 0)``, of a
    rectangular lattice of pitches ``pitch_x``, ``pitch_y`` (metres) at ``wavelength`` (metres),
    within ``|du| <= extent[0]``, ``|dv| <= extent[1]``: an (n, 2) array (empty when none)."""
    for name, v in (("wavelength", wavelength), ("pitch_x", pitch_x), ("pitch_y", pitch_y)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ParameterError(f"{name} must be a positive length in metres, got {v!r}")
    gx, gy = wavelength / pitch_x, wavelength / pitch_y
    mx, my = int(extent[0] // gx), int(extent[1] // gy)
    out = [(m * gx, n * gy) for m in range(-mx, mx + 1) for n in range(-my, my + 1) if m or n]
    return np.array(out, dtype=np.float64).reshape(-1, 2)


@styled
def beam_pattern_figure(labels: list[str], patterns: np.ndarray, du: np.ndarray, dv: np.ndarray,
                        sines: tuple[float, float], lattice_lobes: np.ndarray | None = None,
                        segments: list | None = None, dynamic_range: float = 50.0):
    """The figure of the module docstring: ``patterns`` (B, Hv, Hu) real powers on the axes ``du``
    (Hu,) and ``dv`` (Hv,), ``sines`` the sector's ``(sin theta_x,max, sin theta_y,max)``,
    ``lattice_lobes`` (n, 2) from :func:`lattice_grating_lobes`, ``segments`` one (G, 2, 2) array
    of grating-lobe segments a selection. Returns a Figure."""
    patterns = np.asarray(patterns, dtype=np.float64)
    if patterns.ndim != 3 or patterns.shape[0] != len(labels) or patterns.shape[1:] != (len(dv), len(du)):
        raise ParameterError(f"patterns must have shape ({len(labels)}, {len(dv)}, {len(du)}), got {patterns.shape}")
    if not (dynamic_range > 0):
        raise ParameterError(f"dynamic_range must be > 0 dB, got {dynamic_range!r}")
    n = len(labels)
    cols = min(n, 3)
    rows = max(1, math.ceil(n / cols))
    fig = figure((3.6 * cols + 0.8, 3.4 * rows))
    t = np.linspace(0, 2 * math.pi, 361)
    sx, sy = 2 * sines[0], 2 * sines[1]
    im = None
    for i, label in enumerate(labels):
        ax = fig.add_subplot(rows, cols, i + 1)
        p = np.clip(patterns[i], 0, None)
        peak = p.max()
        db = 10 * np.log10(np.maximum(p / peak, 1e-30)) if peak > 0 else np.full(p.shape, -np.inf)
        im = ax.imshow(np.maximum(db, -dynamic_range), origin="lower", cmap="inferno", vmin=-dynamic_range, vmax=0,
                       extent=(du[0], du[-1], dv[0], dv[-1]), aspect="equal", interpolation="nearest")
        ax.plot(np.cos(t), np.sin(t), color="w", lw=0.7, ls="--")
        ax.plot([-sx, sx, sx, -sx, -sx], [-sy, -sy, sy, sy, -sy], color="c", lw=0.8)
        if lattice_lobes is not None and len(lattice_lobes):
            ax.scatter(lattice_lobes[:, 0], lattice_lobes[:, 1], marker="x", s=22, color="lime", lw=0.9)
        if segments is not None and i < len(segments):
            for seg in np.asarray(segments[i], dtype=np.float64).reshape(-1, 2, 2):
                ax.plot(seg[:, 0], seg[:, 1], color="lime", lw=1.0, alpha=0.6)
        ax.set_xlim(du[0], du[-1])
        ax.set_ylim(dv[0], dv[-1])
        ax.set_title(str(label), fontsize=9)
        ax.set_xlabel("du")
        ax.set_ylabel("dv")
    if im is not None:
        bar = fig.colorbar(im, ax=fig.axes, shrink=0.8)
        bar.set_label("two-way power (dB re. peak)")
    fig.suptitle("two-way beam pattern; dashed: visible region at broadside; cyan: the sector's shifts; "
                 "green: grating lobes (x: the probe's lattice, lines: the selection's)", fontsize=8)
    return fig
