"""Deterministic element layouts: evenly thinned arrays and density-tapered Fermat spirals.

One home for the layouts the deterministic baselines use (``uniform`` and ``spiral`` in
``plugins/``): each function returns a sorted list of exactly ``k`` distinct element indices.

Conventions (``docs/selectors.md``, "Layouts"):

* a 1-D array is indexed ``0 .. Ne - 1`` along the array;
* a matrix array is a grid ``(ny, nx)`` with element index ``iy * nx + ix``; a grid with holes
  (blank rows) or an irregular layout is known by its element centres (``positions``);
  ``positions`` (when given) are the elements' centres, an ``(Ne, 2)`` or ``(Ne, 3)`` array in
  metres in that order (only x and y are used).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from arraysel.errors import ParameterError, check_choice, check_number
from arraysel.objective.contract import check_element_grid

__all__ = ["GOLDEN_ANGLE_DEG", "TAPERS", "uniform_layout", "uniform_subgrid", "taper_density", "grid_of_positions",
           "spread_layout", "planar_uniform_layout", "is_planar",
           "fermat_spiral_points", "fermat_spiral_layout", "tapered_line_layout", "snap_to_elements",
           "CHIRP_PERIODS", "TUKEY_ALPHA", "chirped_layouts"]

#: the golden angle, 180 (3 - sqrt 5) degrees = 137.5078 degrees, between successive spiral points
GOLDEN_ANGLE_DEG = 180.0 * (3.0 - math.sqrt(5.0))
#: ranges of the draws of :func:`chirped_layouts`: local periods at the centre and at the edges
#: (multiples of the finest period, ``1 / min(k/Ne, 1 - k/Ne)`` pitches, two for half the
#: elements; drawn log-uniformly), the exponent of the period's change from the centre outwards
#: and the centre's offset (normalised aperture, -1 to 1)
CHIRP_PERIODS = {"centre": (1.0, 4.0), "edge": (1.0, 6.0), "growth": (0.5, 4.0), "offset": (-0.15, 0.15)}
#: the density tapers of :func:`taper_density`
TAPERS = ("none", "cosine", "blackman", "tukey")
#: the default share of the radius over which the ``tukey`` taper falls (the published 50 % Tukey)
TUKEY_ALPHA = 0.5


def _check_k(k, n: int) -> int:
    return int(check_number("k", k, lo=1, hi=n, integer=True))


# --------------------------------------------------------------------------
# uniform thinning
# --------------------------------------------------------------------------

def uniform_subgrid(grid, k: int) -> tuple[int, int]:
    """The sub-grid ``(ky, kx)`` of :func:`uniform_layout` on a ``(ny, nx)`` grid.

    The thinning factors ``ny / ky`` and ``nx / kx`` as equal as the grid allows (a square sub-array
    spacing for equal pitches) and ``ky * kx`` as close to ``k`` as possible: ``ky0 = sqrt(k ny /
    nx)`` (equal factors with ``ky kx = k``), candidates ``ky`` in ``{floor ky0, ceil ky0}`` and
    ``kx`` in ``{floor(k / ky), ceil(k / ky)}``, each clipped to the grid; the candidate with the
    smallest ``|ky kx - k|`` wins, then the one with the smallest ``|log((ny/ky) / (nx/kx))|``,
    then the smaller ``ky``.
    """
    ny, nx = check_element_grid(grid)
    k = _check_k(k, ny * nx)
    ky0 = math.sqrt(k * ny / nx)
    best = None
    for ky in {min(max(math.floor(ky0), 1), ny), min(max(math.ceil(ky0), 1), ny)}:
        for kx in {min(max(k // ky, 1), nx), min(max(-(-k // ky), 1), nx)}:
            key = (abs(ky * kx - k), abs(math.log((ny / ky) / (nx / kx))), ky)
            if best is None or key < best[0]:
                best = (key, (ky, kx))
    return best[1]


def _even(n: int, m: int) -> np.ndarray:
    """``floor(i n / m)``, i = 0 .. m-1: m evenly spaced of n (the 1-D uniform rule)."""
    return (np.arange(m) * n) // m


def uniform_layout(n_elements: int, k: int, grid=None, cells=None) -> list[int]:
    """``k`` evenly spaced elements.

    1-D (``grid`` None): ``floor(i Ne / k)``, ``i = 0 .. k-1`` (every second element for
    ``k = Ne / 2``).

    2-D (``grid = (ny, nx)``, ``ny nx = Ne``): the same rule on each axis of the sub-grid
    ``(ky, kx)`` of :func:`uniform_subgrid` (rows ``floor(j ny / ky)``, columns
    ``floor(i nx / kx)``), then exactly ``k`` by the fewest changes:

    * too many (``ky kx > k``): remove, one at a time, the active element farthest from the grid's
      centre (in element steps; the largest index on ties), so the corners go first;
    * too few: add, one at a time, the free element farthest from every active element (it fills
      the largest gap; on ties the one nearest the grid's centre, then the smallest index).

    A grid with holes (blank rows, missing elements): ``cells`` gives the grid cell
    ``iy * nx + ix`` of each element (Ne distinct cells, ``Ne <= ny nx``); the sub-grid's cells
    that hold no element are dropped, then the same fewest changes among the elements.

    A ``(1, Ne)`` grid gives the 1-D layout.
    """
    n = int(check_number("n_elements", n_elements, lo=1, integer=True))
    k = _check_k(k, n)
    if grid is None:
        return [int(i) for i in _even(n, k)]
    ny, nx = check_element_grid(grid, n if cells is None else None)
    cells = np.arange(n) if cells is None else _check_cells(cells, n, ny * nx)
    ky, kx = uniform_subgrid((ny, nx), k)
    iy, ix = _even(ny, ky), _even(nx, kx)
    active = np.zeros((ny, nx), dtype=bool)
    active[np.ix_(iy, ix)] = True
    yy, xx = np.meshgrid(np.arange(ny, dtype=float), np.arange(nx, dtype=float), indexing="ij")
    yy, xx = yy.ravel()[cells], xx.ravel()[cells]
    centre2 = (yy - (ny - 1) / 2) ** 2 + (xx - (nx - 1) / 2) ** 2
    flat = active.ravel()[cells]
    order = np.arange(n)
    while flat.sum() > k:
        cand = np.flatnonzero(flat)
        # farthest from the centre first, the largest index on ties
        i = cand[np.lexsort((-order[cand], -centre2[cand]))[0]]
        flat[i] = False
    while flat.sum() < k:
        act = np.flatnonzero(flat)
        free = np.flatnonzero(~flat)
        if act.size:
            d2 = ((yy[free, None] - yy[None, act]) ** 2 + (xx[free, None] - xx[None, act]) ** 2).min(axis=1)
        else:
            d2 = np.zeros(free.size)
        i = free[np.lexsort((order[free], centre2[free], -d2))[0]]
        flat[i] = True
    return [int(i) for i in np.flatnonzero(flat)]


def _check_cells(cells, n: int, n_cells: int) -> np.ndarray:
    c = np.asarray(cells)
    if (c.shape != (n,) or not np.issubdtype(c.dtype, np.integer) or c.min() < 0 or c.max() >= n_cells
            or np.unique(c).size != n):
        raise ParameterError(f"cells must be {n} distinct grid cells in [0, {n_cells - 1}] (one per element)")
    return c


def grid_of_positions(positions) -> tuple[tuple[int, int], np.ndarray] | None:
    """``((ny, nx), cells)`` when the element centres ``positions`` ``(Ne, 2|3)`` lie on a regular
    grid (steps: the smallest distance between distinct x and between distinct y; cell
    ``iy * nx + ix`` from the lowest x and y), with or without holes; None otherwise (an irregular
    layout, or a grid of more than 4096 cells along an axis)."""
    pos = _positions_xy(positions)
    index = []
    for v in (pos[:, 1], pos[:, 0]):
        u = np.unique(v)
        tol = 1e-9 * max(1.0, float(np.abs(u).max()))
        u = u[np.concatenate([[True], np.diff(u) > tol])]
        step = float(np.min(np.diff(u))) if len(u) > 1 else 1.0
        i = np.round((v - u[0]) / step)
        if np.abs(i * step + u[0] - v).max() > 1e-6 * step or i.max() >= 4096:
            return None
        index.append(i.astype(np.int64))
    (iy, ix), shape = index, (int(index[0].max()) + 1, int(index[1].max()) + 1)
    cells = iy * shape[1] + ix
    return (shape, cells) if np.unique(cells).size == len(cells) else None


def spread_layout(positions, k: int) -> list[int]:
    """``k`` elements spread evenly over an irregular planar layout (farthest-point order): the
    element nearest the centre of the centres' bounding box first, then, one at a time, the
    element farthest from every chosen one (the smallest index on ties). Sorted."""
    pos = _positions_xy(positions)
    k = _check_k(k, len(pos))
    centre = 0.5 * (pos.min(axis=0) + pos.max(axis=0))
    d2 = ((pos - centre) ** 2).sum(axis=1)
    chosen = [int(np.argmin(d2))]
    near = ((pos - pos[chosen[0]]) ** 2).sum(axis=1)
    while len(chosen) < k:
        i = int(np.argmax(near))      # first maximum: the smallest index on ties
        chosen.append(i)
        near = np.minimum(near, ((pos - pos[i]) ** 2).sum(axis=1))
    return sorted(chosen)


def planar_uniform_layout(positions, k: int) -> list[int]:
    """``uniform`` on a matrix array known by its element centres only (a grid with blank rows, an
    imported layout): on the grid they lie on (:func:`grid_of_positions`), :func:`uniform_layout`
    on its rows and columns that hold elements when the missing cells form whole rows or columns
    (blank rows squeezed out: the rule of a full grid on the connected rows), else on the grid
    with its holes; :func:`spread_layout` on an irregular layout."""
    pos = _positions_xy(positions)
    found = grid_of_positions(pos)
    if found is None:
        return spread_layout(pos, k)
    (ny, nx), cells = found
    rows, iy = np.unique(cells // nx, return_inverse=True)
    cols, ix = np.unique(cells % nx, return_inverse=True)
    if len(rows) * len(cols) == len(cells):  # whole rows or columns missing: squeeze them out
        return uniform_layout(len(pos), k, (len(rows), len(cols)), iy.reshape(-1) * len(cols) + ix.reshape(-1))
    return uniform_layout(len(pos), k, (ny, nx), cells)


def is_planar(positions) -> bool:
    """Whether element centres ``(Ne, 2|3)`` span both x and y (a matrix array, not a line)."""
    if positions is None:
        return False
    pos = _positions_xy(positions)
    return bool(np.ptp(pos[:, 0]) > 0 and np.ptp(pos[:, 1]) > 0)


# --------------------------------------------------------------------------
# density-tapered Fermat spiral
# --------------------------------------------------------------------------

def taper_density(rho, taper: str = "cosine", alpha: float = TUKEY_ALPHA) -> np.ndarray:
    """The element density (relative to the centre) at the normalised radius ``rho`` in [0, 1].

    * ``none``: 1 (the plain sunflower: uniform density);
    * ``cosine``: ``cos(pi rho / 2)``;
    * ``blackman``: ``0.42 + 0.5 cos(pi rho) + 0.08 cos(2 pi rho)`` (the centred Blackman window);
    * ``tukey``: 1 out to ``1 - alpha``, then ``(1 + cos(pi (rho - 1 + alpha) / alpha)) / 2`` (the
      tapered cosine; ``alpha`` in (0, 1], the share of the radius it falls over: 1 is the Hann
      window, 0.5 the published 50 % Tukey).

    Each is 1 at the centre; ``cosine``, ``blackman`` and ``tukey`` fall to 0 at the rim.
    """
    check_choice("taper", taper, TAPERS)
    rho = np.clip(np.asarray(rho, dtype=np.float64), 0.0, 1.0)
    if taper == "none":
        return np.ones_like(rho)
    if taper == "cosine":
        return np.cos(0.5 * np.pi * rho)
    if taper == "tukey":
        a = check_number("alpha", alpha, lo=0.0, lo_open=True, hi=1.0)
        return np.where(rho <= 1.0 - a, 1.0, 0.5 * (1.0 + np.cos(np.pi * (rho - 1.0 + a) / a)))
    return 0.42 + 0.5 * np.cos(np.pi * rho) + 0.08 * np.cos(2 * np.pi * rho)


def _inverse_cumulative(u: np.ndarray, taper: str, dim: int, alpha: float = TUKEY_ALPHA) -> np.ndarray:
    """``G^{-1}(u)`` with ``G(rho) = int_0^rho w(s) s^(dim-1) ds / int_0^1 w(s) s^(dim-1) ds``."""
    rho = np.linspace(0.0, 1.0, 8193)
    f = taper_density(rho, taper, alpha) * rho ** (dim - 1)
    g = np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(rho))])
    g /= g[-1]
    # g is strictly increasing on [0, 1) (w > 0 there); drop the flat tail a zero rim density may leave
    keep = np.concatenate([[True], np.diff(g) > 0])
    return np.interp(u, g[keep], rho[keep])


def fermat_spiral_points(k: int, taper: str = "cosine", rotation_deg: float = 0.0,
                         alpha: float = TUKEY_ALPHA) -> np.ndarray:
    """``k`` points of a density-tapered Fermat (sunflower) spiral in the unit disc, ``(k, 2)``.

    Point ``n = 0 .. k-1`` is at angle ``n * GOLDEN_ANGLE_DEG + rotation_deg`` and radius
    ``rho_n = G^{-1}(n / k)``, where ``G(rho) = int_0^rho w(s) s ds / int_0^1 w(s) s ds``
    is the fraction of the tapered density ``w`` (:func:`taper_density`) inside ``rho``: each point
    owns an equal share of the tapered area, so the local density of points follows ``w``. Without
    a taper, ``rho_n = sqrt(n / k)`` (Vogel's sunflower); point 0 is the centre.
    """
    k = int(check_number("k", k, lo=1, integer=True))
    rot = check_number("rotation_deg", rotation_deg)
    n = np.arange(k, dtype=np.float64)
    rho = _inverse_cumulative(n / k, taper, dim=2, alpha=alpha)
    theta = np.deg2rad(n * GOLDEN_ANGLE_DEG + rot)
    return np.stack([rho * np.cos(theta), rho * np.sin(theta)], axis=1)


def snap_to_elements(points: np.ndarray, positions: np.ndarray) -> list[int]:
    """Each point (in order) takes the nearest element not taken yet (the smallest index on ties):
    ``len(points)`` distinct element indices, in the order of the points."""
    points = np.asarray(points, dtype=np.float64)
    positions = np.asarray(positions, dtype=np.float64)
    if len(points) > len(positions):
        raise ParameterError(f"{len(points)} points cannot take distinct elements of {len(positions)}")
    free = np.ones(len(positions), dtype=bool)
    out = []
    for p in points:
        d2 = ((positions - p) ** 2).sum(axis=1)
        d2[~free] = np.inf
        i = int(np.argmin(d2))       # first minimum: the smallest index on ties
        free[i] = False
        out.append(i)
    return out


def _grid_positions(ny: int, nx: int) -> np.ndarray:
    iy, ix = np.divmod(np.arange(ny * nx), nx)
    return np.stack([ix.astype(float), iy.astype(float)], axis=1)


def _positions_xy(layout) -> np.ndarray:
    """(Ne, 2) x, y positions of a grid ``(ny, nx)`` (element steps) or of an ``(Ne, 2|3)`` array."""
    if isinstance(layout, tuple) or (isinstance(layout, Sequence) and len(layout) == 2
                                     and all(np.ndim(v) == 0 for v in layout)):
        ny, nx = check_element_grid(layout)
        return _grid_positions(ny, nx)
    pos = np.asarray(layout, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] not in (2, 3) or pos.shape[0] < 1:
        raise ParameterError(f"positions must be an (Ne, 2) or (Ne, 3) array of element centres, "
                             f"got shape {pos.shape}")
    if not np.isfinite(pos).all():
        raise ParameterError("positions holds non-finite values")
    return pos[:, :2]


def _half_extent(v: np.ndarray) -> float:
    """Half the aperture along one axis: half the span of the centres plus half an element step."""
    u = np.unique(v)
    step = float(np.min(np.diff(u))) if len(u) > 1 else 0.0
    return 0.5 * float(u[-1] - u[0]) + 0.5 * step


def fermat_spiral_layout(layout, k: int, taper: str = "cosine", rotation_deg: float = 0.0,
                         alpha: float = TUKEY_ALPHA) -> list[int]:
    """``k`` elements of a matrix array along a density-tapered Fermat spiral, sorted.

    ``layout`` is a grid ``(ny, nx)`` (element index ``iy * nx + ix``, unit steps) or the elements'
    centres ``(Ne, 2|3)`` in metres. The points of :func:`fermat_spiral_points` are scaled to the
    ellipse inscribed in the aperture (centred on the middle of the centres' bounding box, half-axes
    half the span of the centres plus half an element step; a circle on a square grid) and snapped
    in order (centre outwards) to the nearest free element (:func:`snap_to_elements`): exactly
    ``k`` distinct elements, the same for the same arguments.
    """
    pos = _positions_xy(layout)
    n = len(pos)
    k = _check_k(k, n)
    check_choice("taper", taper, TAPERS)
    pts = fermat_spiral_points(k, taper, rotation_deg, alpha)
    centre = 0.5 * (pos.min(axis=0) + pos.max(axis=0))
    half = np.array([_half_extent(pos[:, 0]), _half_extent(pos[:, 1])])
    half = np.where(half > 0, half, 1.0)
    return sorted(snap_to_elements(centre + pts * half, pos))


def tapered_line_layout(n_elements: int, k: int, taper: str = "cosine", alpha: float = TUKEY_ALPHA) -> list[int]:
    """The 1-D analogue of the density-tapered spiral: ``k`` of ``Ne`` elements on a line, sorted.

    Points ``t_n = H^{-1}((n + 1/2) / k)`` in [-1, 1], ``H`` the normalised cumulative of the
    density ``w(|t|)`` of :func:`taper_density` over [-1, 1] (the points follow the tapered
    density; without a taper they are evenly spaced), mapped to the array
    (``(Ne - 1) / 2 + t Ne / 2``, element steps) and snapped, the points nearest the centre first,
    to the nearest free element.
    """
    n = int(check_number("n_elements", n_elements, lo=1, integer=True))
    k = _check_k(k, n)
    check_choice("taper", taper, TAPERS)
    u = (np.arange(k, dtype=np.float64) + 0.5) / k
    # symmetric density on [-1, 1]: H(t) = 1/2 + sign(t) G(|t|) / 2 with G the 1-D cumulative
    a = _inverse_cumulative(np.abs(2 * u - 1), taper, dim=1, alpha=alpha)
    t = np.sign(2 * u - 1) * a
    pts = (n - 1) / 2 + t * n / 2
    order = np.argsort(np.abs(t), kind="stable")
    chosen = snap_to_elements(pts[order, None], np.arange(n, dtype=np.float64)[:, None])
    return sorted(chosen)


# --------------------------------------------------------------------------
# chirped (aperiodic) layouts
# --------------------------------------------------------------------------

def _chirp_phase(u: np.ndarray, p_centre: float, p_edge: float, growth: float, centre: float) -> np.ndarray:
    """Phase (in cycles) along a line of elements at normalised positions ``u`` (in [-1, 1]) of a
    square wave whose local period (in elements, ``n`` elements spanning 2) goes from
    ``p_centre`` at ``centre`` to ``p_edge`` at a distance 1 as ``|u - centre| ** growth``
    (growing or shrinking)."""
    n = u.size
    period = p_centre + (p_edge - p_centre) * np.minimum(np.abs(u - centre), 1.0) ** growth
    phase = np.cumsum(1.0 / period)
    return phase - np.interp(centre, u, phase) if n > 1 else phase


def chirped_layouts(rng: np.random.Generator, n_elements: int, k: int, m: int, grid=None) -> np.ndarray:
    """``m`` random *chirped* selections of ``k`` of ``n_elements``: a boolean array ``(m, Ne)``.

    A chirped layout keeps the elements where a square wave along the array is high, the wave's
    local period changing smoothly from the centre to the edges: aperiodic layouts of the kind
    good sparse arrays take (for half the elements, say, nearly alternating elements in the
    middle and blocks of adjacent elements towards the edges, or blocks throughout on a probe
    whose pitch exceeds the wavelength), whose irregular spacing spreads the grating lobes of a
    periodic thinning; equal periods give periodic block layouts, the uniform one among them.
    Each layout draws its centre and edge periods, exponent, centre offset and phase from
    :data:`CHIRP_PERIODS`; the ``k`` elements with the highest ``cos(2 pi phase)`` (a matrix
    grid: the product of the row's and the column's) are kept, so any ``k`` gives exactly ``k``
    (ties broken at random).

    Used as start selections of the swap searches (``start = chirp``), never as a result.
    """
    n = int(check_number("n_elements", n_elements, lo=1, integer=True))
    k = _check_k(k, n)
    m = int(check_number("m", m, lo=1, integer=True))
    if grid is not None:
        ny, nx = check_element_grid(grid, n)
        axes = [(np.linspace(-1.0, 1.0, ny) if ny > 1 else np.zeros(1)),
                (np.linspace(-1.0, 1.0, nx) if nx > 1 else np.zeros(1))]
    else:
        axes = [np.linspace(-1.0, 1.0, n) if n > 1 else np.zeros(1)]
    duty = min(k, n - k) / n
    finest = 1.0 / duty if duty > 0 else 2.0
    out = np.zeros((m, n), dtype=bool)
    for j in range(m):
        periods = [finest * math.exp(rng.uniform(*np.log(CHIRP_PERIODS[key]))) for key in ("centre", "edge")]
        growth, offset = rng.uniform(*CHIRP_PERIODS["growth"]), rng.uniform(*CHIRP_PERIODS["offset"])
        wave = np.ones(1)
        for u in axes:
            phase = _chirp_phase(u, periods[0], periods[1], growth, offset)
            wave = np.multiply.outer(wave, np.cos(2.0 * np.pi * (phase + rng.uniform(0.0, 1.0))))
        score = wave.reshape(-1) + 1e-9 * rng.random(n)
        out[j, np.argpartition(-score, k - 1)[:k]] = True
    return out
