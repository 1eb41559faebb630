"""Transmit delay laws for linear and convex arrays.

Every function returns a float64 array of shape (n_tx, Ne) in seconds, one
delay law per row, shifted so that the smallest delay of each row is 0: an
element with a larger delay fires later. Geometry follows
:meth:`arraysel.physics.probes.Probe.element_positions` (x along the array, x = 0 at
its centre, z depth, positive into the medium). The laws are the ones of
MUST's ``txdelay``:

* plane wave of tilt a: t_e = (x_e sin a + z_e cos a) / c. The wave travels
  in the direction (sin a, cos a), so a positive tilt steers it towards +x and
  delays the elements at positive x;
* focused at (x0, z0), z0 > 0: t_e = -|r_e - r0| / c (the farthest element
  fires first, all wavefronts meet at the focus);
* diverging from a virtual source (x0, z0), z0 < 0, behind the array:
  t_e = +|r_e - r0| / c;
* circular (diverging) wave given by a sector tilt and angular width
  (linear arrays only): the virtual source sits behind the array where the
  two lines through it and the end elements make the angles tilt - width/2
  and tilt + width/2 with the z axis.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from arraysel.errors import ParameterError, check_number
from arraysel.physics.probes import Acquisition, Probe, check_sound_speed

__all__ = [
    "plane_wave_tilts",
    "plane_wave_delays",
    "focused_delays",
    "diverging_delays",
    "circular_virtual_source",
]


# ---------------------------------------------------------------------- helpers
def _speed(c: Any) -> float:
    if isinstance(c, Acquisition):
        return c.c
    return check_sound_speed(c)


def _check_probe(probe: Any) -> Probe:
    if not isinstance(probe, Probe):
        raise ParameterError(f"probe must be an arraysel.physics.probes.Probe, got {type(probe).__name__}")
    return probe


def _vector(name: str, values: Any) -> np.ndarray:
    """A scalar or 1-D sequence of finite real numbers as a float64 1-D array."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number or a 1-D sequence of numbers, got {values!r}") from None
    if arr.ndim > 1:
        raise ParameterError(f"{name} must be a number or a 1-D sequence, got an array of shape {arr.shape}")
    arr = np.atleast_1d(arr)
    if arr.size == 0:
        raise ParameterError(f"{name} must not be empty")
    bad = ~np.isfinite(arr)
    if bad.any():
        raise ParameterError(f"{name} must be finite, got {arr[bad][0]!r} at index {int(np.argmax(bad))}")
    return arr


def _broadcast(names: tuple[str, str], a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if a.size != b.size and a.size != 1 and b.size != 1:
        raise ParameterError(
            f"{names[0]} and {names[1]} must have the same length (or one of them a single value); "
            f"got {a.size} and {b.size}")
    return np.broadcast_arrays(a, b)


def _rows_from_zero(t: np.ndarray) -> np.ndarray:
    t = t - t.min(axis=1, keepdims=True)
    return np.ascontiguousarray(t, dtype=np.float64)


def _check_tilts(name: str, tilts: np.ndarray) -> None:
    bad = np.abs(tilts) >= math.pi / 2
    if bad.any():
        i = int(np.argmax(bad))
        raise ParameterError(
            f"{name} = {tilts[i]!r} rad (index {i}) is out of range; allowed: (-pi/2, pi/2)")


# ---------------------------------------------------------------------- public API
def plane_wave_tilts(n: int = 7, max_deg: float = 10.0) -> np.ndarray:
    """Tilt angles (rad) linspace(-max_deg, +max_deg, n) in degrees converted to radians.

    The paper scene uses 7 tilts over +-10 degrees. ``n = 1`` gives the single
    unsteered tilt 0.
    """
    n = check_number("n", n, lo=1, integer=True)
    max_deg = check_number("max_deg", max_deg, lo=0.0, hi=90.0, hi_open=True)
    if n == 1:
        return np.zeros(1, dtype=np.float64)
    return np.deg2rad(np.linspace(-max_deg, max_deg, n, dtype=np.float64))


def plane_wave_delays(probe: Probe, tilts: Any, c: float | Acquisition = 1540.0) -> np.ndarray:
    """Delays (s), shape (len(tilts), Ne), for plane waves of the given tilts (rad, |tilt| < pi/2).

    Positive tilt steers the wave towards +x: elements at positive x fire
    later. Works for linear and convex arrays.
    """
    probe = _check_probe(probe)
    tilts = _vector("tilts", tilts)
    _check_tilts("tilts", tilts)
    c = _speed(c)
    xe, ze, _, _ = probe.element_positions()
    t = (np.sin(tilts)[:, None] * xe[None, :] + np.cos(tilts)[:, None] * ze[None, :]) / c
    return _rows_from_zero(t)


def focused_delays(probe: Probe, x0: Any, z0: Any, c: float | Acquisition = 1540.0) -> np.ndarray:
    """Delays (s), shape (n_tx, Ne), focusing at (x0, z0) (m).

    ``z0 > 0``: converging wave focused at (x0, z0). ``z0 < 0``: diverging wave
    from the virtual source (x0, z0) behind the array. ``z0 = 0`` is refused.
    ``x0`` and ``z0`` may be scalars or 1-D sequences of the same length (one
    row per focus). Works for linear and convex arrays.
    """
    probe = _check_probe(probe)
    x0, z0 = _broadcast(("x0", "z0"), _vector("x0", x0), _vector("z0", z0))
    zero = z0 == 0
    if zero.any():
        raise ParameterError(
            f"z0 = 0.0 (index {int(np.argmax(zero))}) is not allowed: use z0 > 0 for a focus "
            "in the medium or z0 < 0 for a virtual source behind the array")
    c = _speed(c)
    xe, ze, _, _ = probe.element_positions()
    dist = np.hypot(xe[None, :] - x0[:, None], ze[None, :] - z0[:, None])
    t = -np.sign(z0)[:, None] * dist / c
    return _rows_from_zero(t)


def circular_virtual_source(probe: Probe, tilts: Any, widths: Any) -> tuple[np.ndarray, np.ndarray]:
    """Virtual source positions (x0, z0) (m, z0 < 0) of circular waves of given tilt and width (rad).

    The lines from the source through the first and last elements make the
    angles ``tilt - width/2`` and ``tilt + width/2`` with the z axis. Needs a
    linear array with at least two elements, 0 < width < pi and
    |tilt| + width/2 < pi/2.
    """
    probe = _check_probe(probe)
    if not probe.is_linear:
        raise ParameterError(
            f"probe {probe.name!r} is convex (radius = {probe.radius!r}): circular-wave delays "
            "(tilts, widths) need a linear array; use focused_delays with z0 < 0 instead")
    if probe.n_elements < 2:
        raise ParameterError(
            f"n_elements = {probe.n_elements}: circular-wave delays need at least 2 elements")
    tilts, widths = _broadcast(("tilts", "widths"), _vector("tilts", tilts), _vector("widths", widths))
    _check_tilts("tilts", tilts)
    bad = (widths <= 0) | (widths >= math.pi)
    if bad.any():
        i = int(np.argmax(bad))
        raise ParameterError(f"widths = {widths[i]!r} rad (index {i}) is out of range; allowed: (0, pi)")
    lo = tilts - widths / 2
    hi = tilts + widths / 2
    bad = (lo <= -math.pi / 2) | (hi >= math.pi / 2)
    if bad.any():
        i = int(np.argmax(bad))
        raise ParameterError(
            f"tilts = {tilts[i]!r} and widths = {widths[i]!r} rad (index {i}) are out of range: "
            "the sector edges tilt -+ width/2 must lie in (-pi/2, pi/2)")
    xe = probe.element_positions()[0]
    aperture = float(xe[-1] - xe[0])
    depth = aperture / (np.tan(hi) - np.tan(lo))   # distance of the source behind the array
    x0 = xe[0] - depth * np.tan(lo)
    return x0, -depth


def diverging_delays(probe: Probe, tilts: Any, widths: Any, c: float | Acquisition = 1540.0) -> np.ndarray:
    """Delays (s), shape (n_tx, Ne), of circular (diverging) waves, MUST's txdelay(param, tilt, width).

    ``tilts`` (|tilt| < pi/2) and ``widths`` (0 < width < pi), in radians,
    describe the angular sector covered by the wave; scalars or 1-D sequences
    of the same length. Linear arrays only.
    """
    x0, z0 = circular_virtual_source(probe, tilts, widths)
    return focused_delays(probe, x0, z0, c)
