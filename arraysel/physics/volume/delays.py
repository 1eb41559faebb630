"""Transmit delay laws for matrix probes.

Every function returns a float64 array (n_tx, Ne) in seconds, one law per row, shifted so that
the smallest delay of each row is 0 (the earliest element fires at 0), columns in the element
order ``iy * nx + ix`` of :class:`~arraysel.physics.probes.MatrixProbe`.

* Plane wave of tilts (ax, ay): ``t_e = (x_e sin ax + y_e sin ay) / c``. The wave travels along
  the unit vector ``u = (sin ax, sin ay, sqrt(1 - sin^2 ax - sin^2 ay))``: a positive ``ax``
  steers it towards +x (the elements at +x fire later), a positive ``ay`` towards +y. MUST's
  ``txdelay3(param, TILTx, TILTy)`` (tilts about the axes) is the same law with
  ``ax = TILTy`` and ``ay = -TILTx``.
* Focused at (x0, y0, z0), z0 > 0: ``t_e = -|r_e - r0| / c``; diverging from a virtual source
  behind the array, z0 < 0: ``t_e = +|r_e - r0| / c`` (MUST's ``txdelay3(x0, y0, z0, param)``).
* Diverging wave of tilts (ax, ay) from a source at ``distance`` behind the array centre:
  the source sits at ``-distance * u`` (u as for a plane wave), so the wave's axis has the
  direction of the plane wave of the same tilts.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from arraysel.errors import ParameterError, check_number
from arraysel.physics.delays import _broadcast, _rows_from_zero, _speed, _vector
from arraysel.physics.probes import Acquisition, MatrixProbe, PlanarProbe

__all__ = ["plane_wave_delays3", "focused_delays3", "virtual_sources3", "diverging_delays3", "tilt_grid"]


def _check_matrix(probe: Any) -> MatrixProbe:
    if not isinstance(probe, (MatrixProbe, PlanarProbe)):
        raise ParameterError(f"probe must be an arraysel.physics.probes.MatrixProbe or PlanarProbe (a 2-D array), "
                             f"got {type(probe).__name__}")
    return probe


def _tilt_pairs(tilts_x: Any, tilts_y: Any) -> tuple[np.ndarray, np.ndarray]:
    ax, ay = _broadcast(("tilts_x", "tilts_y"), _vector("tilts_x", tilts_x), _vector("tilts_y", tilts_y))
    s2 = np.sin(ax) ** 2 + np.sin(ay) ** 2
    bad = (np.abs(ax) >= math.pi / 2) | (np.abs(ay) >= math.pi / 2) | (s2 >= 1.0)
    if bad.any():
        i = int(np.argmax(bad))
        raise ParameterError(
            f"tilts_x = {ax[i]!r}, tilts_y = {ay[i]!r} rad (index {i}) are out of range; allowed: "
            "|tilt| < pi/2 and sin^2(tilt_x) + sin^2(tilt_y) < 1")
    return np.array(ax, dtype=np.float64), np.array(ay, dtype=np.float64)


def plane_wave_delays3(probe: MatrixProbe, tilts_x: Any, tilts_y: Any,
                       c: float | Acquisition = 1540.0) -> np.ndarray:
    """Delays (s), shape (n_tx, Ne), of plane waves of tilts ``tilts_x``, ``tilts_y`` (rad;
    scalars or 1-D sequences of one length): ``t_e = (x_e sin ax + y_e sin ay) / c``."""
    probe = _check_matrix(probe)
    ax, ay = _tilt_pairs(tilts_x, tilts_y)
    c = _speed(c)
    pos = probe.element_positions()
    t = (np.sin(ax)[:, None] * pos[None, :, 0] + np.sin(ay)[:, None] * pos[None, :, 1]) / c
    return _rows_from_zero(t)


def focused_delays3(probe: MatrixProbe, x0: Any, y0: Any, z0: Any,
                    c: float | Acquisition = 1540.0) -> np.ndarray:
    """Delays (s), shape (n_tx, Ne): focused at (x0, y0, z0) for z0 > 0, diverging from the
    virtual source (x0, y0, z0) for z0 < 0 (z0 = 0 is refused). Scalars or 1-D sequences of
    one length (or length 1)."""
    probe = _check_matrix(probe)
    x0, y0 = _broadcast(("x0", "y0"), _vector("x0", x0), _vector("y0", y0))
    x0, z0 = _broadcast(("x0", "z0"), x0, _vector("z0", z0))
    y0, _ = _broadcast(("y0", "z0"), y0, z0)
    zero = z0 == 0
    if zero.any():
        raise ParameterError(
            f"z0 = 0.0 (index {int(np.argmax(zero))}) is not allowed: use z0 > 0 for a focus in the "
            "medium or z0 < 0 for a virtual source behind the array")
    c = _speed(c)
    pos = probe.element_positions()
    dist = np.sqrt((pos[None, :, 0] - x0[:, None]) ** 2 + (pos[None, :, 1] - y0[:, None]) ** 2
                   + z0[:, None] ** 2)
    return _rows_from_zero(-np.sign(z0)[:, None] * dist / c)


def virtual_sources3(tilts_x: Any, tilts_y: Any, distance: Any) -> np.ndarray:
    """Virtual sources (n, 3) in metres of diverging waves of tilts (ax, ay) (rad) whose source
    lies ``distance`` (m, > 0) behind the array centre: ``-distance * u``,
    ``u = (sin ax, sin ay, sqrt(1 - sin^2 ax - sin^2 ay))``."""
    ax, ay = _tilt_pairs(tilts_x, tilts_y)
    d = _vector("distance", distance)
    ax, d = _broadcast(("tilts_x", "distance"), ax, d)
    ay, d = _broadcast(("tilts_y", "distance"), ay, d)
    bad = ~(d > 0)
    if bad.any():
        raise ParameterError(f"distance = {d[np.argmax(bad)]!r} m must be > 0 (the source lies behind the array)")
    sx, sy = np.sin(ax), np.sin(ay)
    u = np.stack([sx, sy, np.sqrt(1.0 - sx ** 2 - sy ** 2)], axis=1)
    return -d[:, None] * u


def diverging_delays3(probe: MatrixProbe, tilts_x: Any, tilts_y: Any, distance: Any,
                      c: float | Acquisition = 1540.0) -> np.ndarray:
    """Delays (s), shape (n_tx, Ne), of diverging waves from :func:`virtual_sources3`."""
    src = virtual_sources3(tilts_x, tilts_y, distance)
    return focused_delays3(probe, src[:, 0], src[:, 1], src[:, 2], c)


def tilt_grid(n_x: int, n_y: int, max_deg_x: float, max_deg_y: float) -> tuple[np.ndarray, np.ndarray]:
    """Tilt pairs (rad) of an ``n_x`` x ``n_y`` grid of linspace(-max, max) in degrees (one
    axis: 0 when its n is 1), flattened with tilt_x fastest: ``(tilts_x, tilts_y)``."""
    n_x = check_number("n_x", n_x, lo=1, hi=64, integer=True)
    n_y = check_number("n_y", n_y, lo=1, hi=64, integer=True)
    mx = check_number("max_deg_x", max_deg_x, lo=0.0, hi=90.0, hi_open=True)
    my = check_number("max_deg_y", max_deg_y, lo=0.0, hi=90.0, hi_open=True)
    ax = np.deg2rad(np.linspace(-mx, mx, n_x)) if n_x > 1 else np.zeros(1)
    ay = np.deg2rad(np.linspace(-my, my, n_y)) if n_y > 1 else np.zeros(1)
    AX, AY = np.meshgrid(ax, ay)
    return AX.ravel(), AY.ravel()
