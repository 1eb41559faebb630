"""The per-beam view of a sector scene (``docs/sector.md``): its points read the way a designer reads
them.

A sector scene's :class:`~arraysel.objective.psf_objective.Objective` searches on the beam pattern
(:mod:`arraysel.objective.sector_objective`); its per-beam view (``Objective.beams``,
:class:`SectorBeams`, given by :func:`~arraysel.objective.imagers.scene_beams`) holds one imager per
point (:class:`SectorPointImager`: the point's PSF on its surface over the sector,
:class:`~arraysel.physics.volume.sector.SectorPSF`, on its fast path where it is built and checked
(:func:`sector_fast_state`, cached), else exact), whose plane sets are scored per beam
(:meth:`SectorBeams.beam_metrics`, :func:`~arraysel.objective.lobes.lobe_metrics`: its main lobe
from its own PSF, ``PSL_dB`` outside it, ``ISLR_dB``, ``GLL_dB`` on the grating lobes that the
selection's lattice predicts around the point, the -6 dB widths in x and y in metres) and, from
them, the per-beam loss (:meth:`SectorBeams.beam_loss`).
"""
from __future__ import annotations

import hashlib
import math

import numpy as np
import torch

from arraysel.errors import NumericalError, check_number
from arraysel.objective.lobes import lobe_metrics
from arraysel.objective.tensors import check_masks, checked_masks
from arraysel.physics.imaging import Imager, PlaneSet

__all__ = ["SectorBeams", "SectorPointImager", "BEAM_COLUMNS", "sector_fast_state", "point_label",
           "SECTOR_FAST_VERSION", "per_beam_attribute"]

#: the per-beam metrics of :meth:`SectorBeams.beam_metrics`, per point
BEAM_COLUMNS = ("PSL_dB", "ISLR_dB", "GLL_dB", "width_x_6dB", "width_y_6dB")


def per_beam_attribute(name: str, what: str) -> property:
    """A read-only attribute of an objective that reads ``name`` of its per-beam view
    (``objective.beams``: a sector scene's :class:`SectorBeams`); on any other scene an
    AttributeError (``hasattr`` is False, as on an objective without the view)."""

    def get(self):
        beams = self.__dict__.get("beams")
        if beams is None:
            raise AttributeError(f"{name}: scene {self.settings.name!r} has no per-beam view (a sector scene has)")
        return getattr(beams, name)

    return property(get, doc=f"{what} (a sector scene's per-beam view, :class:`~arraysel.objective."
                             f"sector_beams.SectorBeams`.{name}).")


class SectorPointImager(Imager):
    """The imager of one point of a sector scene: its complex PSF on its surface over the sector as
    one plane (:data:`~arraysel.physics.volume.sector.SURFACE`), at the surface's positions; on the
    point's fast path when it is in use (:meth:`SectorBeams.fast_point`), else exact.

    Parameters: ``beams``, the scene's :class:`SectorBeams`; ``index``, the point's index.
    """

    def __init__(self, beams: "SectorBeams", index: int):
        from arraysel.physics.volume.sector import SURFACE

        self.beams, self.index = beams, int(index)
        self.setup = beams.setup
        self.n_elements = beams.n_elements
        self.dtype, self.device = beams.dtype, beams.device
        self.plane_names = (SURFACE,)

    @property
    def model(self):
        """The points' :class:`~arraysel.physics.volume.sector.SectorPSF`."""
        return self.beams.exact

    @property
    def coords(self):
        return self.beams.exact.coords[self.index]

    def image(self, weights: torch.Tensor, receive: torch.Tensor | None = None, exact: bool = False,
              base: torch.Tensor | None = None) -> PlaneSet:
        """The point's image of weights (B, Ne) (``receive``: separate receive weights): the fast path
        in batches of the objective's ``chunk`` when it is in use and ``exact`` is False, else the
        exact path one selection at a time. The fast model is built when it is not cached only for a
        batch of at least :attr:`SectorBeams.fast_min_masks` selections (below that, its build costs
        more than the exact path). ``base`` (Ne,): a selection each row differs from in a few
        elements (a local search's moves: the fast path's receive sums then come from it,
        :meth:`~arraysel.physics.volume.fast.MatrixFastPSF.image`; the same images)."""
        from arraysel.physics.volume.sector import SURFACE

        b, i = self.beams, self.index
        fast = not exact and b.fast_point(i, build=weights.shape[0] >= b.fast_min_masks)
        step = max(1, b.chunk) if fast else 1
        parts = [b.exact.surfaces(weights[s:s + step], i, exact=not fast,
                                  receive=None if receive is None else receive[s:s + step], base=base)[SURFACE]
                 for s in range(0, weights.shape[0], step)]
        img = torch.cat(parts)
        if not bool(torch.isfinite(img).all()):
            raise NumericalError(f"the PSF of point {i} is not finite")
        return self.wrap(img)

    def layout(self):
        probe = self.setup.probe
        return probe.layout_grid, probe.element_positions()

    def masks_per_batch(self) -> int:
        return max(1, self.beams.chunk)


class SectorBeams:
    """The per-beam view of a sector scene's objective (module docstring): its points' imagers
    (:attr:`imagers`, one :class:`SectorPointImager` a point), their per-beam metrics and loss, and
    the fresh random selections they are read against.

    Parameters: ``objective``, the scene's :class:`~arraysel.objective.psf_objective.Objective`
    (its scene, ``k``, device, dtype, ``chunk``, ``fast_requested`` and its beam pattern imager).
    """

    def __init__(self, objective):
        self.objective = objective
        scene = objective.scene
        self.setup = scene.sector_setup()
        self.n_elements, self.k = int(objective.n_elements), int(objective.k)
        self.dtype, self.device = objective.dtype, objective.device
        self.points = list(self.setup.points)
        self.n_points = len(self.points)
        #: the two-way beam pattern over the sector (the search imager's model): the lattice of its
        #: grating lobes
        self.pattern = objective.imagers[0].model
        self.fresh_random = int(scene.value("sector", "fresh_random"))
        #: whether the per-beam scoring may use the points' fast models; the points refused, with why
        self.fast_exact, self.fast_refused = bool(objective.fast_requested), {}
        #: the fewest selections a call must score to build a point's fast model that is not cached
        self.fast_min_masks = 64
        self._mirrors = None
        self._exact = None
        self._segments: dict = {}
        #: the points' imagers, one per point
        self.imagers = [SectorPointImager(self, i) for i in range(self.n_points)]

    @property
    def chunk(self) -> int:
        """Masks per batch of the points' fast path: the objective's ``chunk``."""
        return int(self.objective.chunk)

    def as_masks(self, masks) -> torch.Tensor:
        return checked_masks(masks, self.n_elements, self.device, self.dtype)

    # ------------------------------------------------------------------ exact per-beam scoring
    @property
    def exact(self):
        """The points' PSFs (:class:`~arraysel.physics.volume.sector.SectorPSF`, built on first use;
        with ``fast``, each point's fast model installed on first use, :meth:`fast_point`)."""
        if self._exact is None:
            from arraysel.physics.volume.sector import SectorPSF
            self._exact = SectorPSF(self.setup, dtype=self.dtype, device=self.device)
        return self._exact

    def fast_point(self, i: int, build: bool = True) -> bool:
        """Install point ``i``'s fast model (from the on-disk cache, or, with ``build``, built,
        checked against the exact path on the full array and two random selections of ``k``
        elements, and cached); True when it is in use, False when the fast path is off, refused
        (the reason in :attr:`fast_refused`) or, without ``build``, not cached."""
        psf = self.exact
        if psf.has_fast(i):
            return True
        if not self.fast_exact or i in self.fast_refused:
            return False
        from arraysel.physics.volume.fast import FastPathUnavailable
        from arraysel.physics.volume.sector import MirroredModel, mirrors

        if self._mirrors is None:
            self._mirrors = mirrors(self.setup)
        perms, pairs = self._mirrors
        j, name = pairs.get(int(i), (None, None))
        if j is not None and self.fast_point(j, build=build):
            # the mirror image of an earlier point: its model, the weights permuted, the image mirrored
            psf.install_fast(i, MirroredModel(psf._fast[j], perms[name], name))
            return True

        state = sector_fast_state(self, i, build=build)
        if state is None:
            return False
        if "refused" in state:
            self.fast_refused[i] = str(state.get("why", "refused when it was built"))
            return False
        try:
            psf.install_fast(i, psf.fast_from_state(i, state))
        except (ValueError, FastPathUnavailable) as exc:
            self.fast_refused[i] = str(exc)
            return False
        return True

    def point_images(self, masks, i: int, exact: bool = False, receive=None, base=None) -> torch.Tensor:
        """Point ``i``'s complex images (B, Hv, Hu) of hard masks or weights (B, Ne): the fast path
        in batches of :attr:`chunk` when available and ``exact`` is False, else the exact path one
        selection at a time. The fast model is built when it is not cached only for a batch of at
        least :attr:`fast_min_masks` selections (below that, its build costs more than the exact
        path; :meth:`fast_point` builds it on demand). ``receive``: separate receive masks or
        weights (B, Ne), ``masks`` then the transmit apodization; ``base``: a selection each mask
        differs from in a few elements (:meth:`SectorPointImager.image`)."""
        m = self.as_masks(masks) if not isinstance(masks, torch.Tensor) else masks
        m = m.to(self.device, self.dtype)
        r = None
        if receive is not None:
            r = self.as_masks(receive) if not isinstance(receive, torch.Tensor) else receive
            r = r.to(self.device, self.dtype)
        return self.imagers[i].image(m, r, exact=exact, base=self._base(base)).kernel

    def _base(self, base) -> torch.Tensor | None:
        """``base`` (a selection, any array of Ne values) as weights on the objective's device."""
        return None if base is None else \
            torch.as_tensor(np.asarray(base, dtype=np.float64)).reshape(-1).to(self.device, self.dtype)

    def _grating(self, masks: torch.Tensor, i: int) -> list[torch.Tensor]:
        """Per mask, the grating-lobe segments (G, 2, 2) in u-v around point ``i`` over the pulse's
        band: those of the coarsest lattice that holds its elements
        (:func:`~arraysel.physics.beampattern.lattice_periods`), within the point's surface."""
        from arraysel.physics.beampattern import grating_lobe_segments, lattice_periods

        p = self.pattern
        if p.path != "grid":
            return [torch.zeros(0, 2, 2, dtype=torch.float64) for _ in range(masks.shape[0])]
        nx, ny, px, py, _, index = p.lattice
        w = masks.detach().cpu().double()
        nodes = w.new_zeros(w.shape[0], nx * ny).index_copy(1, torch.as_tensor(index), w)
        band = (float(p.wavelengths.min()), float(p.wavelengths.max()))
        st = self.setup
        bounds = (float(st.u[0]), float(st.u[-1]), float(st.v[0]), float(st.v[-1]))
        out = []
        for mx, my in lattice_periods(nodes, nx, ny).tolist():
            key = (mx, my, i)
            if key not in self._segments:
                self._segments[key] = (torch.zeros(0, 2, 2, dtype=torch.float64) if not (mx or my) else
                                       grating_lobe_segments(mx * px if mx else math.inf, my * py if my else math.inf,
                                                             band, steer=st.direction_of(i), bounds=bounds))
            out.append(self._segments[key])
        return out

    def beam_metrics(self, masks, points=None, exact: bool = False, receive=None, base=None) -> dict[str, np.ndarray]:
        """The per-beam metrics (module docstring) of hard masks (B, Ne) on the points' PSFs (the
        fast path when available, :meth:`point_images`; ``exact``: the exact path): ``{name: float64
        (B, P)}`` for the names of :data:`BEAM_COLUMNS` (dB; widths in metres), one column per point
        of ``points`` (default all). Not counted as evaluations of the search. ``receive``:
        separate receive masks (B, Ne) (grating lobes then from the lattice of both apertures' elements).
        Each point's plane sets come from its imager (:class:`SectorPointImager`); ``base``: as
        :meth:`point_images`."""
        m = self.as_masks(masks)
        r = None if receive is None else self.as_masks(receive)
        both = m if r is None else torch.maximum(m, r)
        pts = list(range(self.n_points)) if points is None else [int(p) for p in points]
        out = {k: np.zeros((m.shape[0], len(pts))) for k in BEAM_COLUMNS}
        step = max(1, self.chunk)
        with torch.no_grad():
            for j, i in enumerate(pts):
                for b0 in range(0, m.shape[0], step):
                    mb = m[b0:b0 + step]
                    rb = None if r is None else r[b0:b0 + step]
                    ps = self.imagers[i].image(mb, rb, exact=exact, base=self._base(base))
                    res = lobe_metrics(ps.images, ps.coords, target=self.points[i],
                                       grating_uv=self._grating(both[b0:b0 + step], i), terms=BEAM_COLUMNS)
                    for k in BEAM_COLUMNS:
                        out[k][b0:b0 + mb.shape[0], j] = res[k].double().cpu().numpy()
        return out

    def beam_loss(self, masks, width_cap: float, width_weight: float = 100.0, exact: bool = False,
                  metrics: dict | None = None, points=None, base=None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The per-beam loss of hard masks (B, Ne) on the points' PSFs: the worst ``PSL_dB`` over
        the points plus ``width_weight`` dB per unit of the mean -6 dB width's relative excess over
        ``width_cap`` (metres; the mean over points of the x and y widths). Returns
        ``(loss float64 (B,), summary)``, the summary ``{"worst_PSL_dB", "mean_width_m"}`` (B,) and
        ``"PSL_dB"`` (B, P) per point. ``metrics``: the masks' :meth:`beam_metrics`, if already
        computed (``masks`` is then not scored again); ``points``: over these points only (default
        all); ``base``: as :meth:`point_images`."""
        cap = check_number("width_cap", width_cap, lo=0, lo_open=True, hi=1.0)
        wt = check_number("width_weight", width_weight, lo=0)
        bm = self.beam_metrics(masks, points=points, exact=exact, base=base) if metrics is None else metrics
        worst = bm["PSL_dB"].max(1)
        width = (bm["width_x_6dB"].mean(1) + bm["width_y_6dB"].mean(1)) / 2
        loss = worst + wt * np.maximum(width / cap - 1.0, 0.0)
        return loss, {"worst_PSL_dB": worst, "mean_width_m": width, "PSL_dB": bm["PSL_dB"]}

    def fresh_random_masks(self, n: int | None = None, seed: int = 0) -> np.ndarray:
        """``n`` (default the scene's ``sector.fresh_random``) random selections of ``k`` elements,
        boolean (n, Ne), from ``seed``."""
        from arraysel.selection import random_masks

        return random_masks(self.n_elements, self.k, self.fresh_random if n is None else int(n), seed)


#: the version of the cached sector fast-path tensors (bumped when their meaning changes)
SECTOR_FAST_VERSION = 2


def _point_key(setup, i: int) -> tuple:
    """A cache key of point ``i`` of a :class:`~arraysel.physics.volume.sector.SectorSetup`: its
    point setup, the delays by digest and the grid of directions."""
    ps = setup.point_setup(i)
    d = np.ascontiguousarray(ps.delays, dtype=np.float64)
    uv = np.concatenate([setup.u, setup.v]).astype(np.float64)
    fields = (ps.probe, ps.acq, ps.scatterer, ps.reflectivity, ps.iq_bandwidth, ps.options)
    return (repr(fields), d.shape, hashlib.sha256(d.tobytes()).hexdigest(), hashlib.sha256(uv.tobytes()).hexdigest())


def sector_fast_state(objective, i: int, build: bool = True) -> dict | None:
    """The cached fast-path tensors of point ``i`` of a sector scene (``objective``: its
    :class:`SectorBeams` or its objective)
    (:meth:`~arraysel.physics.volume.sector.SectorPSF.build_fast`, checked on the full array and
    two random selections of ``k`` elements, seed 0), built when absent (without ``build``: None
    when absent); ``{"refused": 1, "why": ...}``-like (``refused`` present) when the fast path was
    refused."""
    from arraysel import __version__
    from arraysel.io import cache
    from arraysel.physics.volume.fast import FastPathUnavailable
    from arraysel.physics.volume.sector import SECTOR_FAST, SECTOR_FAST_LADDER

    k = objective.k
    checks = check_masks(objective.n_elements, k)
    why: list[str] = []

    def make() -> dict:
        for settings in SECTOR_FAST_LADDER:
            try:
                return objective.exact.build_fast(i, settings, check_masks=checks).state()
            except FastPathUnavailable as exc:
                why.append(str(exc))
        return {"refused": torch.tensor(1)}

    def check(state: dict) -> None:
        if "refused" not in state:
            objective.exact.fast_from_state(i, state, SECTOR_FAST)

    key = (__version__, SECTOR_FAST_VERSION, _point_key(objective.setup, i), k, repr(SECTOR_FAST_LADDER))
    if not build and cache.peek("sector-fast", key, ["unsort"]) is None \
            and cache.peek("sector-fast", key, ["refused"]) is None:
        return None
    state = dict(cache.load_or_build("sector-fast", key, make, what=f"the sector fast path of point {i}",
                                     check=check, seconds_hint=300.0))
    if "refused" in state and why:
        state["why"] = why[0]
    return state


def point_label(objective, i: int) -> str:
    """A point's label: its angles (degrees) and range (mm), e.g. ``"13,0@50mm"``."""
    u, v = objective.setup.direction_of(i)
    r = objective.setup.range_of(i)
    return f"{math.degrees(math.asin(u)):.3g},{math.degrees(math.asin(v)):.3g}@{r * 1e3:.4g}mm"
