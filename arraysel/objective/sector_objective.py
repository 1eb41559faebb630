"""The objective of a sector scene (``docs/sector.md``): search on the two-way beam pattern over the
steered sector, score on the points' exact PSFs, per beam.

:class:`SectorObjective` follows the objective contract (``evaluate``, ``mask_loss``,
``selection_loss``, counters, a worker recipe). Its ``evaluate`` and losses run on the cheap,
differentiable beam pattern (:class:`~arraysel.physics.beampattern.BeamPattern` over the sector,
scored by :class:`~arraysel.objective.beam_objective.BeamPatternScorer`'s lobe rule), with the
Table-1 names read on the pattern:

* ``L_SLR_q``: ``10^(PSL/20)``, the worst beam's peak side lobe, as an amplitude ratio;
* ``L_SLR_i``: ``10^(ISLR/10)``, the sector's mean integrated side-lobe ratio;
* ``L_contrast``: the mean side-lobe power over the mean main-lobe power (each beam's view
  weighted by the share of the sector's beams that see it);
* ``L_PSF``: the scale-invariant MSE of the amplitude pattern against the full array's (its main
  lobe's width and shape); ``L_SLR`` and ``Mean`` as in Table 1.

The pattern's ``PSL_dB``, ``ISLR_dB`` and -6 dB widths in u and v go into each row as
``bp_PSL_dB``, ``bp_ISLR_dB``, ``bp_width_u_6dB``, ``bp_width_v_6dB``.

:meth:`SectorObjective.beam_metrics` scores selections the way a designer reads them: each point's
exact PSF on its surface over the sector (:class:`~arraysel.physics.volume.sector.SectorPSF`) and
its per-beam lobe metrics (:func:`~arraysel.objective.lobes.lobe_metrics`: its main lobe from its
own PSF, ``PSL_dB`` outside it, ``ISLR_dB``, ``GLL_dB`` on the grating lobes that the selection's
lattice predicts around the point, the -6 dB widths in x and y in metres).
"""
from __future__ import annotations

import hashlib
import math

import numpy as np
import torch

from arraysel.errors import NumericalError, ParameterError, SelectionError, check_number
from arraysel.objective.tensors import objective_device
from arraysel.objective.lobes import lobe_metrics, main_lobe_regions
from arraysel.objective.metrics import METRIC_NAMES
from arraysel.objective.beam_objective import BeamPatternScorer
from arraysel.objective.contract import dtype_name
from arraysel.objective.psf_objective import Objective, SceneObjectiveFactory, build_objective
from arraysel.scenes.schema import Scene, load_scene

__all__ = ["SectorObjective", "SectorObjectiveFactory", "BEAM_COLUMNS", "SEARCH_COLUMNS"]

#: the per-beam metrics of :meth:`SectorObjective.beam_metrics`, per point
BEAM_COLUMNS = ("PSL_dB", "ISLR_dB", "GLL_dB", "width_x_6dB", "width_y_6dB")
#: the beam pattern's metrics in each row of a comparison
SEARCH_COLUMNS = ("bp_PSL_dB", "bp_ISLR_dB", "bp_width_u_6dB", "bp_width_v_6dB")
_NAME = "pattern"
_TINY = 1e-30


class SectorObjective(Objective):
    """Batched, differentiable objective of a sector scene (see the module docstring).

    Parameters: scene (a sector :class:`~arraysel.scenes.schema.Scene` or its name/path), device,
    dtype, chunk (masks per batch of :meth:`evaluate`; the exact scoring of :meth:`beam_metrics`
    runs one selection at a time).
    """

    metric_names = METRIC_NAMES

    def __init__(self, scene: Scene | str = "matrix-1024-sector", device="cpu", dtype=torch.float32,
                 chunk: int = 64, fast: bool = True):
        from arraysel.physics.beampattern import BeamPattern

        self.scene = load_scene(scene) if not isinstance(scene, Scene) else scene
        if not self.scene.is_sector:
            raise ParameterError(f"scene {self.scene.name!r} has no [sector] section: it is not a sector scene")
        self.device = objective_device(device)
        self.dtype, self.chunk = dtype, int(chunk)
        self.settings = st = self.scene.objective_settings()
        self.setup = self.scene.sector_setup()
        #: the scene's constraints (:mod:`arraysel.constraints`), None without a [constraints] section
        self.constraints = self.scene.constraints()
        probe = self.setup.probe
        self.n_elements, self.k = probe.n_elements, st.k
        self.element_grid = probe.layout_grid
        self.element_positions = probe.element_positions()
        self.points = list(self.setup.points)
        self.n_points = len(self.points)
        geo = self.scene.sector_geometry()
        self.pattern = BeamPattern.from_probe(probe, self.scene.acquisition(), sector_deg=geo["half_angles"],
                                              n_freq=int(self.scene.value("sector", "n_freq")), dtype=dtype,
                                              device=self.device)
        self.scorer = BeamPatternScorer(self.pattern)
        self.fresh_random = int(self.scene.value("sector", "fresh_random"))
        self.breakdown_names = SEARCH_COLUMNS
        self.weights = dict(st.weights)
        self.fast_requested, self.exact_reason = False, None
        #: whether the per-beam scoring may use the points' fast models; the points refused, with why
        self.fast_exact, self.fast_refused = bool(fast), {}
        #: the fewest selections a call must score to build a point's fast model that is not cached
        self.fast_min_masks = 64
        self._mirrors = None
        self._ref_amp = None
        self._exact = None
        self._segments: dict = {}
        self.evaluations = self.gradient_steps = self.fallbacks = 0
        self.seconds = 0.0
        self._announced = True
        self.hessian_from_pairs = False

    # ------------------------------------------------------------------ the search's terms
    def estimate_seconds(self, n_masks: int = 1) -> float:
        return n_masks * 0.005

    def exact_notice(self, n_masks: int | None = None) -> str:
        return f"scene {self.settings.name!r}: search on the sector's two-way beam pattern"

    def _reference_amplitude(self) -> torch.Tensor:
        if self._ref_amp is None:
            with torch.no_grad():
                full = torch.ones(1, self.n_elements, dtype=self.dtype, device=self.device)
                self._ref_amp = self.pattern.pattern(full)[0].clamp(min=0).sqrt()
        return self._ref_amp

    def psf_terms(self, weights: torch.Tensor, terms=None, receive=None) -> dict[str, torch.Tensor]:
        """The search's terms (B,) of soft element weights (B, Ne) on the beam pattern (module
        docstring), differentiable in the weights; the ``bp_`` metrics without gradient."""
        w = weights if weights.dim() == 2 else weights[None]
        if w.shape[-1] != self.n_elements:
            raise SelectionError(f"weights must have shape (B, {self.n_elements}), got {tuple(w.shape)}")
        w = w.to(self.device, self.dtype)
        p = self.pattern
        img = p.pattern(w, None if receive is None else receive.to(self.device, self.dtype))  # (B, Hv, Hu)
        planes, coords = {_NAME: img}, {_NAME: p.coords}
        reg = main_lobe_regions({_NAME: img.detach()}, coords, target=(0.0, 0.0, 0.0), rule=self.scorer.rule,
                                power=True, frame="uv")
        m = lobe_metrics(planes, coords, target=(0.0, 0.0, 0.0), rule=self.scorer.rule, regions=reg,
                         weights={_NAME: p.mean_weight}, peak_weights={_NAME: p.peak_weight}, power=True,
                         frame="uv", terms=("PSL_dB", "ISLR_dB", "width_u_6dB", "width_v_6dB"))
        main = reg.main[_NAME].to(img.dtype)
        wt = p.mean_weight.to(img.dtype)
        side = (1 - main) * wt
        inner = main * wt
        contrast = ((img * side).sum((1, 2)) / side.sum((1, 2)).clamp(min=_TINY)) / (
            (img * inner).sum((1, 2)) / inner.sum((1, 2)).clamp(min=_TINY)).clamp(min=_TINY)
        amp = (img.clamp(min=0) + _TINY).sqrt()
        ref = self._reference_amplitude().to(img.dtype)
        a_ref = (amp * ref * wt).sum((1, 2)) / (amp * amp * wt).sum((1, 2)).clamp(min=_TINY)
        l_psf = ((a_ref[:, None, None] * amp - ref) ** 2 * wt).sum((1, 2)) / (ref * ref * wt).sum()
        q = 10.0 ** (m["PSL_dB"] / 20.0)
        i = 10.0 ** (m["ISLR_dB"] / 10.0)
        out = {"L_PSF": l_psf, "L_contrast": contrast, "L_SLR_q": q, "L_SLR_i": i, "L_SLR": (q + i) / 2,
               "Mean": (l_psf + contrast + q + i) / 4}
        out.update({f"bp_{k}": v.detach() for k, v in m.items()})
        if terms is not None:
            out = {k: out[k] for k in terms}
        return out

    def evaluate(self, masks, receive=None) -> dict[str, np.ndarray]:
        """Every Table-1 term and ``bp_`` metric of a batch of masks on the beam pattern:
        ``{name: float64 (B,)}``. No gradient. ``receive``: separate receive masks (B, Ne)."""
        with torch.no_grad(), self._timed():
            m = self.as_masks(masks)
            r = None if receive is None else self.as_masks(receive)
            parts = [self.psf_terms(m[i:i + self.chunk], receive=None if r is None else r[i:i + self.chunk])
                     for i in range(0, m.shape[0], self.chunk)]
            self.evaluations += int(m.shape[0])
        return {k: torch.cat([p[k] for p in parts]).double().cpu().numpy() for k in (*METRIC_NAMES, *SEARCH_COLUMNS)}

    def kernels(self, masks, point=None):
        raise ParameterError("a sector scene has surfaces, not a 2-D kernel: use SectorObjective.beam_metrics")

    def reference_kernel(self, point=None):
        raise ParameterError("a sector scene has surfaces, not a 2-D kernel: use SectorObjective.beam_metrics")

    def prepare_neighbourhoods(self) -> bool:
        return True

    def evaluate_moves(self, mask, out, into, return_kernels: bool = False) -> dict[str, np.ndarray]:
        """:meth:`evaluate` of the neighbour masks (the beam pattern has no cheaper neighbourhood)."""
        from arraysel.objective.neighbours import move_masks

        return self.evaluate(move_masks(mask, out, into))

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
        from arraysel.physics.volume.sector import MirroredModel, xy_mirrors

        if self._mirrors is None:
            self._mirrors = xy_mirrors(self.setup)
        perm, pairs = self._mirrors
        j = pairs.get(int(i))
        if j is not None and j < int(i) and self.fast_point(j, build=build):
            # the x-y mirror of an earlier point: its model, the weights permuted, the image transposed
            psf.install_fast(i, MirroredModel(psf._fast[j], perm))
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
        weights (B, Ne), ``masks`` then the transmit apodization. ``base`` (Ne,): a selection each
        mask differs from in a few elements (a local search's moves: the fast path's receive sums
        then come from it, :meth:`~arraysel.physics.volume.fast.MatrixFastPSF.image`)."""
        from arraysel.physics.volume.sector import SURFACE

        m = self.as_masks(masks) if not isinstance(masks, torch.Tensor) else masks
        m = m.to(self.device, self.dtype)
        r = None
        if receive is not None:
            r = self.as_masks(receive) if not isinstance(receive, torch.Tensor) else receive
            r = r.to(self.device, self.dtype)
        fast = not exact and self.fast_point(i, build=m.shape[0] >= self.fast_min_masks)
        step = max(1, self.chunk) if fast else 1
        bw = None if base is None else torch.as_tensor(np.asarray(base)).reshape(-1).to(self.device, self.dtype)
        parts = [self.exact.surfaces(m[b:b + step], i, exact=not fast,
                                     receive=None if r is None else r[b:b + step], base=bw)[SURFACE]
                 for b in range(0, m.shape[0], step)]
        img = torch.cat(parts)
        if not bool(torch.isfinite(img).all()):
            raise NumericalError(f"the PSF of point {i} is not finite")
        return img

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
        separate receive masks (B, Ne) (grating lobes then from the lattice of both apertures' elements);
        ``base``: as :meth:`point_images`."""
        from arraysel.physics.volume.sector import SURFACE

        m = self.as_masks(masks)
        r = None if receive is None else self.as_masks(receive)
        both = m if r is None else torch.maximum(m, r)
        pts = list(range(self.n_points)) if points is None else [int(p) for p in points]
        out = {k: np.zeros((m.shape[0], len(pts))) for k in BEAM_COLUMNS}
        step = max(1, self.chunk)
        with torch.no_grad():
            for j, i in enumerate(pts):
                coords = self.exact.coords[i]
                for b0 in range(0, m.shape[0], step):
                    mb = m[b0:b0 + step]
                    rb = None if r is None else r[b0:b0 + step]
                    surf = {SURFACE: self.point_images(mb, i, exact=exact, receive=rb, base=base)}
                    res = lobe_metrics(surf, coords, target=self.points[i],
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

    def worker_factory(self) -> "SectorObjectiveFactory | None":
        if type(self) is not SectorObjective:
            return None
        return SectorObjectiveFactory(self.scene.to_dict(), device=str(self.device), dtype=dtype_name(self.dtype),
                                      chunk=int(self.chunk))


#: the version of the cached sector fast-path tensors (bumped when their meaning changes)
SECTOR_FAST_VERSION = 1


def _point_key(setup, i: int) -> tuple:
    """A cache key of point ``i`` of a :class:`~arraysel.physics.volume.sector.SectorSetup`: its
    point setup, the delays by digest and the grid of directions."""
    ps = setup.point_setup(i)
    d = np.ascontiguousarray(ps.delays, dtype=np.float64)
    uv = np.concatenate([setup.u, setup.v]).astype(np.float64)
    fields = (ps.probe, ps.acq, ps.scatterer, ps.reflectivity, ps.iq_bandwidth, ps.options)
    return (repr(fields), d.shape, hashlib.sha256(d.tobytes()).hexdigest(), hashlib.sha256(uv.tobytes()).hexdigest())


def sector_fast_state(objective: SectorObjective, i: int, build: bool = True) -> dict | None:
    """The cached fast-path tensors of point ``i`` of a sector objective's scene
    (:meth:`~arraysel.physics.volume.sector.SectorPSF.build_fast`, checked on the full array and
    two random selections of ``k`` elements, seed 0), built when absent (without ``build``: None
    when absent); ``{"refused": 1, "why": ...}``-like (``refused`` present) when the fast path was
    refused."""
    from arraysel import __version__
    from arraysel.io import cache
    from arraysel.physics.volume.fast import FastPathUnavailable
    from arraysel.physics.volume.sector import SECTOR_FAST, SECTOR_FAST_LADDER

    from arraysel.objective.imagers import check_masks

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


class SectorObjectiveFactory(SceneObjectiveFactory):
    """Builds the :class:`SectorObjective` of a sector scene on a worker."""

    def __hash__(self):
        return hash(self.key())

    def __call__(self):
        return build_objective(load_scene(dict(self.scene)), device=self.device, dtype=getattr(torch, self.dtype),
                               chunk=self.chunk, objective_class=SectorObjective)
