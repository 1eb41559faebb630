"""Planar 2-D arrays: a grid of elements (:class:`MatrixProbe`, optionally with blank rows or
columns) and an arbitrary planar layout (:class:`PlanarProbe`).

Both are arrays of identical rectangular elements on the plane z = 0 (``width`` along x,
``height`` along y; z is depth, (x, y, z) right-handed, as in MUST's 3-D functions), and both
give the 3-D physics what it reads: ``element_positions()`` (Ne, 3), ``n_elements``, the element
size and the pulse band (``docs/matrix.md``).

**Element index of a grid.** The grid has ``nx`` columns and ``ny`` rows of cells, centred on
(0, 0): cell ``(ix, iy)`` is centred at ``((ix - (nx - 1) / 2) pitch_x, (iy - (ny - 1) / 2)
pitch_y)``. Rows listed in ``blank_rows`` and columns in ``blank_columns`` hold no element
(unconnected rows, as on probes wired in banks); they keep their place in the grid. The
elements are the connected cells in row order (x fastest), skipping the blank ones: element
``e`` is the ``e``-th connected cell counted row by row. Without blank rows or columns this is
the rule **element index = iy * nx + ix**. ``probe.cells`` maps each element to its cell
``iy * nx + ix``; ``element_grid(e)`` gives ``(ix, iy)``, ``element_index(ix, iy)`` the inverse.

**Element index of a planar layout**: the order of the positions it was given.

:func:`probe_from_positions` turns a list of element centres into the simplest probe that
holds them exactly: a :class:`MatrixProbe` (with its blank rows and columns) when the centres
are the connected cells of a grid centred on (0, 0) listed in element order, a
:class:`PlanarProbe` otherwise.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from arraysel.errors import ParameterError, check_number
from arraysel.physics.probe_fields import (Baffle, check_field_names, check_name, check_sound_speed,
                                           check_transducer, positive)

__all__ = ["MatrixProbe", "PlanarProbe", "probe_from_positions", "MAX_PLANAR_ELEMENTS", "POSITION_TOL"]

#: most elements of a :class:`PlanarProbe`
MAX_PLANAR_ELEMENTS = 16384
#: positions closer than this (m) are the same point when a grid is recognised in a layout
POSITION_TOL = 1e-9


class _PlanarArray:
    """What a grid and a planar layout share (they define ``n_elements``, ``element_positions``)."""

    @property
    def is_matrix(self) -> bool:
        """True: a 2-D array (element positions in x and y)."""
        return True

    def wavelength(self, c: float = 1540.0) -> float:
        """Wavelength c / fc at the centre frequency (m)."""
        return check_sound_speed(c) / self.fc

    def check_elements(self, index: Any, what: str = "elements") -> np.ndarray:
        """``index`` as an integer array after checking every entry lies in ``[0, Ne - 1]``."""
        e = np.asarray(index)
        if e.size and (not np.issubdtype(e.dtype, np.integer) or e.min() < 0 or e.max() >= self.n_elements):
            raise ParameterError(f"{what}: an element index must be an integer in [0, {self.n_elements - 1}] "
                                 f"(probe {self.name!r} has {self.n_elements} elements), got {e!r}")
        return e

    def mask(self, indices: Any) -> np.ndarray:
        """0/1 float64 mask (Ne,) with ones at the element ``indices``, checked: integers in
        ``[0, Ne - 1]``, no repeats, at most Ne of them."""
        idx = np.asarray(indices).reshape(-1)
        if idx.size > self.n_elements:
            raise ParameterError(f"k = {idx.size} elements is out of range for probe {self.name!r}; allowed: "
                                 f"[1, {self.n_elements}]")
        self.check_elements(idx)
        if np.unique(idx).size != idx.size:
            raise ParameterError(f"elements repeat an index: {sorted(idx.tolist())[:8]}")
        m = np.zeros(self.n_elements, dtype=np.float64)
        m[idx] = 1.0
        return m

    def to_dict(self) -> dict[str, Any]:
        """The fields as a plain dict (same names as the dataclass)."""
        return dataclasses.asdict(self)

    def to_must_dict(self) -> dict[str, Any]:
        """The geometry under the PARAM field names of MUST's 3-D functions (``elements`` 2 x Ne)."""
        pos = self.element_positions()
        return {"elements": pos[:, :2].T.copy(), "Nelements": self.n_elements, "width": self.width,
                "height": self.height, "fc": self.fc, "bandwidth": self.bandwidth, "baffle": self.baffle}


def _index_list(name: str, values: Any, n: int, axis: str) -> tuple[int, ...]:
    """Sorted distinct grid lines in ``[0, n - 1]``, fewer than ``n`` of them."""
    if values is None:
        return ()
    if isinstance(values, (str, bytes)) or not hasattr(values, "__iter__"):
        raise ParameterError(f"{name} must be a list of {axis} indices, got {values!r}")
    out = [int(check_number(f"{name}[{i}]", v, lo=0, hi=n - 1, integer=True)) for i, v in enumerate(values)]
    if len(set(out)) != len(out):
        raise ParameterError(f"{name} repeats an index: {sorted(out)}")
    if len(out) >= n:
        raise ParameterError(f"{name} = {sorted(out)} leaves no {axis} connected (the grid has {n})")
    return tuple(sorted(out))


@dataclass(frozen=True, repr=False)
class MatrixProbe(_PlanarArray):
    """Geometry and pulse band of a planar grid of rectangular elements (see the module docstring).

    Attributes:
        name: label of the probe.
        nx, ny: grid columns (along x) and rows (along y), blank ones included (integers >= 1).
        pitch_x, pitch_y: centre-to-centre distances along x and y (m, > 0).
        width: element size along x (m, 0 < width <= pitch_x).
        height: element size along y (m, 0 < height <= pitch_y).
        fc: centre frequency (Hz, > 0).
        bandwidth: pulse-echo -6 dB fractional bandwidth (%, in (0, 200)).
        baffle: 'soft', 'rigid' or a positive impedance ratio, as for a 1-D probe.
        blank_rows, blank_columns: grid rows (``iy``) and columns (``ix``) without elements
            (0-based, distinct; default none).
    """

    name: str
    nx: int
    ny: int
    pitch_x: float
    pitch_y: float
    width: float
    height: float
    fc: float
    bandwidth: float = 75.0
    baffle: Baffle = "soft"
    blank_rows: tuple = ()
    blank_columns: tuple = ()

    def __post_init__(self) -> None:
        set_ = lambda field, value: object.__setattr__(self, field, value)  # noqa: E731
        check_name(self.name)
        set_("nx", check_number("nx", self.nx, lo=1, hi=4096, integer=True))
        set_("ny", check_number("ny", self.ny, lo=1, hi=4096, integer=True))
        for pitch, size in (("pitch_x", "width"), ("pitch_y", "height")):
            p = positive(pitch, getattr(self, pitch))
            set_(pitch, p)
            v = positive(size, getattr(self, size))
            if v > p:
                raise ParameterError(
                    f"{size} = {getattr(self, size)!r} is out of range; allowed: (0, {pitch}] = (0, {p!r}] "
                    "(an element cannot be larger than the pitch)")
            set_(size, v)
        check_transducer(self, set_)
        set_("blank_rows", _index_list("blank_rows", self.blank_rows, self.ny, "row"))
        set_("blank_columns", _index_list("blank_columns", self.blank_columns, self.nx, "column"))

    def __repr__(self) -> str:
        # the fields of a full grid only, as before blank rows existed (the fast path's cache keys)
        names = [f.name for f in dataclasses.fields(self)]
        if not self.blank_rows and not self.blank_columns:
            names = names[:-2]
        return f"MatrixProbe({', '.join(f'{n}={getattr(self, n)!r}' for n in names)})"

    # ------------------------------------------------------------------ derived
    @property
    def n_elements(self) -> int:
        """Number of elements: the connected cells, ``(ny - len(blank_rows)) * (nx - len(blank_columns))``."""
        return (self.ny - len(self.blank_rows)) * (self.nx - len(self.blank_columns))

    @property
    def grid_shape(self) -> tuple[int, int]:
        """``(ny, nx)``: the grid, blank rows and columns included."""
        return self.ny, self.nx

    @property
    def layout_grid(self) -> tuple[int, int] | None:
        """``(ny, nx)`` when every cell holds an element (a mask ``reshape``s to it), else None:
        what an objective reports as its ``element_grid``."""
        return None if (self.blank_rows or self.blank_columns) else (self.ny, self.nx)

    @property
    def connected(self) -> np.ndarray:
        """Boolean ``(ny, nx)``: True where a cell holds an element."""
        out = np.ones((self.ny, self.nx), dtype=bool)
        out[list(self.blank_rows), :] = False
        out[:, list(self.blank_columns)] = False
        return out

    @property
    def cells(self) -> np.ndarray:
        """int64 (Ne,): the grid cell ``iy * nx + ix`` of each element, increasing."""
        return np.flatnonzero(self.connected.ravel())

    @property
    def aperture(self) -> tuple[float, float]:
        """Distances between the outermost cell centres along x and along y (m), blank ones included."""
        return (self.nx - 1) * self.pitch_x, (self.ny - 1) * self.pitch_y

    def element_index(self, ix: Any, iy: Any) -> np.ndarray:
        """Element index of grid column ``ix`` and row ``iy`` (checked; a blank cell is refused)."""
        ix = np.asarray(ix)
        iy = np.asarray(iy)
        for name, v, n in (("ix", ix, self.nx), ("iy", iy, self.ny)):
            if v.size and (not np.issubdtype(v.dtype, np.integer) or v.min() < 0 or v.max() >= n):
                raise ParameterError(f"{name} must be integers in [0, {n - 1}], got {v!r}")
        if not self.blank_rows and not self.blank_columns:
            return iy * self.nx + ix
        lookup = np.full(self.ny * self.nx, -1, dtype=np.int64)
        lookup[self.cells] = np.arange(self.n_elements)
        e = lookup[iy * self.nx + ix]
        if e.size and e.min() < 0:
            raise ParameterError(f"(ix, iy) names a blank cell of probe {self.name!r} (blank rows "
                                 f"{list(self.blank_rows)}, blank columns {list(self.blank_columns)})")
        return e

    def element_grid(self, index: Any) -> tuple[np.ndarray, np.ndarray]:
        """``(ix, iy)`` of element indices (checked against ``[0, Ne - 1]``)."""
        e = self.check_elements(index)
        cell = e if (not self.blank_rows and not self.blank_columns) else self.cells[e]
        return cell % self.nx, cell // self.nx

    def element_positions(self) -> np.ndarray:
        """Element centres, float64 (Ne, 3) in metres: columns x, y, z (z = 0), in element order."""
        x = (np.arange(self.nx, dtype=np.float64) - (self.nx - 1) / 2.0) * self.pitch_x
        y = (np.arange(self.ny, dtype=np.float64) - (self.ny - 1) / 2.0) * self.pitch_y
        X, Y = np.meshgrid(x, y)  # (ny, nx): row iy, column ix
        keep = self.connected.ravel()
        return np.stack([X.ravel()[keep], Y.ravel()[keep], np.zeros(self.n_elements)], axis=1)

    def replace(self, **changes: Any) -> "MatrixProbe":
        """A validated copy with some fields changed; unknown names raise :class:`ParameterError`."""
        check_field_names(changes, tuple(f.name for f in dataclasses.fields(MatrixProbe)))
        return dataclasses.replace(self, **changes)


def _check_positions(positions: Any) -> tuple[tuple[float, float], ...]:
    """(Ne, 2) finite element centres in metres (an (Ne, 3) array with z = 0 is accepted)."""
    try:
        p = np.asarray(positions, dtype=np.float64)
    except (TypeError, ValueError):
        raise ParameterError("positions must be an (Ne, 2) array of element centres x, y in metres") from None
    if p.ndim == 2 and p.shape[1] == 3:
        if np.any(p[:, 2] != 0):
            raise ParameterError("positions: every element must lie on the plane z = 0 (a planar array)")
        p = p[:, :2]
    if p.ndim != 2 or p.shape[1] != 2 or not 1 <= p.shape[0] <= MAX_PLANAR_ELEMENTS:
        raise ParameterError(f"positions must be an (Ne, 2) array of element centres x, y in metres with "
                             f"1 <= Ne <= {MAX_PLANAR_ELEMENTS}, got shape {p.shape}")
    if not np.isfinite(p).all() or np.abs(p).max() > 1.0:
        raise ParameterError("positions must be finite and within 1 m of the origin (metres)")
    return tuple((float(x), float(y)) for x, y in p)


def _check_no_overlap(p: np.ndarray, width: float, height: float) -> None:
    """Refuse two elements whose rectangles overlap (naming them)."""
    shrink = 1.0 - 1e-9
    for start in range(0, len(p), 1024):
        blk = p[start:start + 1024]
        dx = np.abs(blk[:, None, 0] - p[None, :, 0]) < width * shrink
        dy = np.abs(blk[:, None, 1] - p[None, :, 1]) < height * shrink
        hit = dx & dy
        hit[np.arange(len(blk)), start + np.arange(len(blk))] = False
        if hit.any():
            i, j = np.argwhere(hit)[0]
            raise ParameterError(f"positions: elements {start + i} and {j} overlap (centres "
                                 f"{p[start + i].tolist()} and {p[j].tolist()} m closer than width = {width!r} "
                                 f"along x and height = {height!r} along y)")


@dataclass(frozen=True)
class PlanarProbe(_PlanarArray):
    """Identical rectangular elements at arbitrary centres on the plane z = 0.

    Attributes:
        name: label of the probe.
        positions: element centres ``((x, y), ...)`` in metres, in element order (an (Ne, 2)
            array is accepted; 1 <= Ne <= :data:`MAX_PLANAR_ELEMENTS`; no two elements overlap).
        width, height: element size along x and y (m, > 0).
        fc, bandwidth, baffle: as for :class:`MatrixProbe`.
    """

    name: str
    positions: tuple
    width: float
    height: float
    fc: float
    bandwidth: float = 75.0
    baffle: Baffle = "soft"

    def __post_init__(self) -> None:
        set_ = lambda field, value: object.__setattr__(self, field, value)  # noqa: E731
        check_name(self.name)
        set_("positions", _check_positions(self.positions))
        set_("width", positive("width", self.width))
        set_("height", positive("height", self.height))
        check_transducer(self, set_)
        _check_no_overlap(np.asarray(self.positions), self.width, self.height)

    @property
    def n_elements(self) -> int:
        """Number of elements (positions)."""
        return len(self.positions)

    @property
    def layout_grid(self) -> None:
        """None: a planar layout has no grid (``element_positions`` describes it)."""
        return None

    @property
    def aperture(self) -> tuple[float, float]:
        """Spans of the element centres along x and along y (m)."""
        p = np.asarray(self.positions)
        return float(np.ptp(p[:, 0])), float(np.ptp(p[:, 1]))

    def element_positions(self) -> np.ndarray:
        """Element centres, float64 (Ne, 3) in metres: x, y, z = 0, in element order."""
        p = np.asarray(self.positions, dtype=np.float64)
        return np.concatenate([p, np.zeros((len(p), 1))], axis=1)

    def replace(self, **changes: Any) -> "PlanarProbe":
        """A validated copy with some fields changed; unknown names raise :class:`ParameterError`."""
        check_field_names(changes, tuple(f.name for f in dataclasses.fields(PlanarProbe)))
        return dataclasses.replace(self, **changes)


def _axis_lattice(v: np.ndarray, size: float) -> tuple[int, float, np.ndarray] | None:
    """``(n, pitch, index)`` of coordinates ``v`` on a lattice centred on 0, or None."""
    u = np.unique(np.round(v / POSITION_TOL) * POSITION_TOL)
    if len(u) > 1:
        keep = np.concatenate([[True], np.diff(u) > 2 * POSITION_TOL])
        u = u[keep]
    # the smallest step, to 12 significant digits (a pitch written as 0.3 mm reads back as 0.3 mm)
    pitch = float(f"{float(np.min(np.diff(u))):.12g}") if len(u) > 1 else size
    half = max(abs(u[0]), abs(u[-1]))
    n = int(round(2 * half / pitch)) + 1
    if n > 4096:
        return None
    index = np.round((v + (n - 1) / 2 * pitch) / pitch).astype(np.int64)
    if np.abs(index * pitch - (n - 1) / 2 * pitch - v).max() > 10 * POSITION_TOL:
        return None
    return n, pitch, index


def probe_from_positions(name: str, positions: Any, width: float, height: float, fc: float,
                         bandwidth: float = 75.0, baffle: Baffle = "soft") -> "MatrixProbe | PlanarProbe":
    """The probe whose elements are centred at ``positions`` ((Ne, 2) or (Ne, 3) with z = 0, metres),
    in that order: a :class:`MatrixProbe` when they are the connected cells of a grid centred on
    (0, 0), listed row by row, whose empty cells form whole rows or columns (its blank rows and
    columns; the pitch is the smallest step between distinct coordinates, a single column or row
    takes the element's size as its pitch), a :class:`PlanarProbe` otherwise."""
    pos = np.asarray(_check_positions(positions))
    common = dict(width=width, height=height, fc=fc, bandwidth=bandwidth, baffle=baffle)
    ax = _axis_lattice(pos[:, 0], positive("width", width))
    ay = _axis_lattice(pos[:, 1], positive("height", height))
    if ax is not None and ay is not None and ax[1] >= width and ay[1] >= height:
        (nx, px, ix), (ny, py, iy) = ax, ay
        cells = iy * nx + ix
        rows = sorted(set(range(ny)) - set(iy.tolist()))
        cols = sorted(set(range(nx)) - set(ix.tolist()))
        if (len(cells) == (ny - len(rows)) * (nx - len(cols)) and np.all(np.diff(cells) > 0)
                and len(rows) < ny and len(cols) < nx):
            probe = MatrixProbe(name, nx, ny, px, py, blank_rows=tuple(rows), blank_columns=tuple(cols), **common)
            if np.abs(probe.element_positions()[:, :2] - pos).max() <= 10 * POSITION_TOL:
                return probe
    return PlanarProbe(name, pos, **common)
