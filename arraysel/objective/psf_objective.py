"""The objective every selection strategy is judged by: one objective over a scene's imagers.

:class:`Objective` is assembled from a scene's settings and imagers (:mod:`arraysel.physics.imaging`;
:func:`~arraysel.objective.imagers.scene_imagers`: one kernel per field point of a 1-D probe, the
three planes of a matrix probe's 3-D PSF, a sector scene's beam pattern) and scores their plane sets
against their full-array plane sets (:func:`~arraysel.objective.plane_metrics.plane_scorer`):

* :meth:`Objective.evaluate`: batched, no-grad evaluation of many masks, returning every Table-1
  metric (chunked, so memory stays bounded), and the figures of merit of 2-D arrays (``PSL_dB``,
  ``width_x_6dB``, ``width_y_6dB``) on a 3-D scene, the pattern's lobe metrics on a sector scene;
* :meth:`Objective.mask_loss`: differentiable, scene-weighted PSF loss of soft element weights (the
  same weights are the TX apodization and the RX channel weights);
* :meth:`Objective.selection_loss`: the training loss of an (Ne, k) selection matrix (PSF terms +
  entropy + row terms, :mod:`arraysel.objective.losses`; a scene that weights the end-to-end terms
  is trained by ``arraysel train``).

It counts evaluated masks, gradient steps and the wall time spent inside it, so a comparison can
report every strategy's budget and overhead. Only the terms with a non-zero weight are computed.

A scene with several field points (``medium.points``) has one imager per point
(``Objective.imagers``; ``Objective.psfs`` their :class:`~arraysel.physics.psf.PSFModel`);
each point's kernel is the window centred on its own peak, scored against its own full-array
reference. The headline metrics (:data:`METRIC_NAMES`) are then the aggregate
``metrics.aggregate`` chooses (the mean over the points, or the worst point),
and :meth:`Objective.evaluate` adds every metric per point, their mean and
their worst (:func:`point_metric_names`). A one-point scene returns exactly
the headline metrics (and a 3-D scene its figures of merit), as before. See ``docs/scenes.md``.

When an imager has no fast path, the objective logs once, when it is built, that
it uses the exact path, with its estimated time per mask and memory
(:meth:`Objective.exact_notice`), and the first evaluation of several masks
logs its estimated duration.
"""
from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import torch

from arraysel.objective import imagers as I
from arraysel.objective import metrics as M
from arraysel.objective import objective_losses, objective_moves
from arraysel.objective.contract import WorkerFactory, dtype_name
from arraysel.objective.plane_metrics import plane_scorer
from arraysel.objective.sector_beams import per_beam_attribute
from arraysel.objective.point_columns import AGGREGATES, aggregated, images_out, point_metric_names  # noqa: F401
from arraysel.errors import ParameterError, SelectionError
from arraysel.objective.tensors import (ReadOnlyKw, checked_masks,  # noqa: F401  (checked_masks: its former home)
                                        objective_device)
from arraysel.physics.imaging import PlaneSet
from arraysel.selection import masks_from_indices
from arraysel.scenes.scene import ObjectiveSettings
from arraysel.scenes.schema import Scene, load_scene

_log = logging.getLogger(__name__)

METRIC_NAMES = M.METRIC_NAMES
#: most masks per batch of :meth:`Objective.evaluate` on a 1-D scene (:data:`arraysel.objective.imagers.DEFAULT_CHUNK`)
DEFAULT_CHUNK = I.DEFAULT_CHUNK
_fmt_seconds = I._fmt_seconds


class _Timer:
    """Adds the wall time of a ``with`` block to ``objective.seconds``."""

    def __init__(self, objective):
        self.objective = objective

    def __enter__(self):
        self.t = time.perf_counter()

    def __exit__(self, *a):
        self.objective.seconds += time.perf_counter() - self.t


class Objective:
    """Batched, differentiable PSF objective of a scene over its imagers (see module docstring).

    Parameters
    ----------
    scene : a :class:`~arraysel.scenes.schema.Scene` or the name/path of one; or its
        :class:`~arraysel.scenes.scene.ObjectiveSettings` together with ``imagers`` (no scene:
        :meth:`assemble`).
    device : "cpu" (default) or "cuda" (or a torch.device); with ``imagers``, theirs by default.
    dtype : torch.float32 (default) or torch.float64; with ``imagers``, theirs by default.
    chunk : masks per batch inside :meth:`evaluate` (default :data:`DEFAULT_CHUNK`, 128 on a 3-D scene).
    fast : False: the exact paths only.
    imagers : the imagers to score (default :func:`~arraysel.objective.imagers.scene_imagers` of the
        scene, read with its settings).
    """

    metric_names = METRIC_NAMES
    #: "kernels" when each field point's image is one 2-D kernel (:meth:`kernels`), "planes" when the
    #: scene's image is a set of planes (:meth:`planes`, :attr:`coords`): what the imagers say, for
    #: readers of the objective (its own methods ask the imagers)
    image_kind: str | None = None

    def __init__(self, scene: Scene | ObjectiveSettings | str = "paper", device=None, dtype=None,
                 chunk: int | None = None, fast: bool = True, imagers=None):
        if isinstance(scene, ObjectiveSettings):
            if not imagers:
                raise ParameterError("Objective(settings, imagers=...): an objective assembled from its settings "
                                     "needs its imagers (arraysel.objective.imagers.scene_imagers gives a scene's)")
            self.scene, st = None, scene
        else:
            self.scene = load_scene(scene) if not isinstance(scene, Scene) else scene
            st = self.scene.objective_settings()
        if imagers is not None:
            imagers = list(imagers)
            device = imagers[0].device if device is None else device
            dtype = imagers[0].dtype if dtype is None else dtype
        self.device = objective_device("cpu" if device is None else device)
        self.dtype = torch.float32 if dtype is None else dtype
        self.fast_requested = bool(fast)
        #: the scene's settings, read once: the objective does not go back to the scene
        self.settings = st
        if imagers is None:
            imagers = I.scene_imagers(self.scene, st, dtype=self.dtype, device=self.device, fast=fast)
        #: the imagers (one per field point), :mod:`arraysel.physics.imaging`
        self.imagers = list(imagers)
        self.chunk = int(I.default_chunk(self.imagers) if chunk is None else chunk)
        self.n_elements = self.imagers[0].n_elements
        self.k = st.k
        #: the layout (ObjectiveContract's optional capability): the element grid (ny, nx) of a 2-D array
        #: on a full grid (else None) and the element centres (Ne, 3) as (x, y, z) in metres
        self.element_grid, self.element_positions = self.imagers[0].layout()
        #: the scene's constraints (:mod:`arraysel.constraints`), None without a [constraints] section
        #: (or without a scene)
        self.constraints = None if self.scene is None else self.scene.constraints()
        #: the field points (one per imager; a sector scene's, one per beam of its per-beam view;
        #: without a scene, the imagers' own)
        self.points = I.scene_points(self.scene) if self.scene is not None else [im.point for im in self.imagers]
        self.n_points = len(self.points)
        self.aggregate = st.aggregate
        first = self.imagers[0]
        self.image_kind = "kernels" if all(im.pitch is not None for im in self.imagers) else "planes"
        kw = dict(wavelength=st.wavelength, **st.metric_radii)
        #: the metrics' radii and scales (read-only: the scorers below hold them)
        self.metric_kw = ReadOnlyKw(kw if first.pitch is None else dict(pitch=first.pitch[0], **kw))
        # each imager's scoring of its plane sets against its reference, and the names it gives
        scorers = [plane_scorer(im, wavelength=st.wavelength, **st.metric_radii) for im in self.imagers]
        self._columns = scorers[0][0]
        self._scorers = [fn for _names, fn in scorers]
        #: extra result keys: every metric per point, their mean and worst (several imagers), or the
        #: figures of merit of a set of planes (the pattern's lobe metrics of a sector scene)
        self.breakdown_names = (point_metric_names(len(self.imagers)) if len(self.imagers) > 1
                                else tuple(n for n in self._columns if n not in METRIC_NAMES))
        self.weights = dict(st.weights)
        self._announced = False
        self._neigh = None
        if any(im.exact for im in self.imagers):
            _log.warning("%s", self.exact_notice())
        self.reset_counters()
        #: :meth:`mask_hessian` from the pair basis (:mod:`arraysel.objective.pair_model`) where it
        #: applies (False: always the autograd of ``mask_loss``)
        self.hessian_from_pairs = all(im.psf_model is not None for im in self.imagers)
        # what the imagers hold, under the names of the former 1-D and 3-D objectives: the 1-D points'
        # PSFModel (``psfs``, ``psf`` the first) and setups; the first imager's setup, physics model,
        # pixel positions ``{plane: (H, W, 3)}`` in metres, and why it uses its exact path (None: fast)
        self.psfs = [im.psf_model for im in self.imagers if im.psf_model is not None]
        self.psf = self.psfs[0] if self.psfs else None
        self.setups = [im.setup for im in self.imagers]
        self.setup, self.model, self.coords = first.setup, first.model, first.coords
        self.exact_reason = next((im.exact_reason for im in self.imagers if im.exact), None)
        #: the per-beam view of the scene's points (:func:`~arraysel.objective.imagers.scene_beams`: a
        #: sector scene's :class:`~arraysel.objective.sector_beams.SectorBeams`), None for others
        self.beams = None if self.scene is None else I.scene_beams(self)

    @classmethod
    def assemble(cls, settings: ObjectiveSettings, imagers, chunk: int | None = None) -> "Objective":
        """The objective assembled from ``settings`` (:class:`~arraysel.scenes.scene.ObjectiveSettings`:
        ``k``, the loss weights, the metric radii, the aggregate) and ``imagers`` (a list of
        :class:`~arraysel.physics.imaging.Imager`, on their device and dtype): it scores their plane
        sets and reads nothing else. Without a scene it has no constraints, no per-beam view and no
        worker recipe; ``Objective(scene)`` is this assembly of the scene's settings and
        :func:`~arraysel.objective.imagers.scene_imagers`."""
        return cls(settings, chunk=chunk, imagers=imagers)

    @property
    def fast(self) -> bool:
        """True when every imager has its fast path."""
        return not any(im.exact for im in self.imagers)

    # ------------------------------------------------------------------ the per-beam view (sector scenes)
    beam_metrics = per_beam_attribute("beam_metrics", "The per-beam metrics of masks on the points' PSFs")
    beam_loss = per_beam_attribute("beam_loss", "The per-beam loss of masks on the points' PSFs")
    point_images = per_beam_attribute("point_images", "A point's complex images on its surface")
    fast_point = per_beam_attribute("fast_point", "Install a point's fast model")
    fresh_random_masks = per_beam_attribute("fresh_random_masks", "Fresh random selections of k elements")
    fresh_random = per_beam_attribute("fresh_random", "How many fresh random selections are scored per beam")
    exact = per_beam_attribute("exact", "The points' PSFs on their surfaces (SectorPSF)")
    pattern = per_beam_attribute("pattern", "The two-way beam pattern over the sector")
    fast_refused = per_beam_attribute("fast_refused", "The points whose fast model was refused, with why")

    # ------------------------------------------------------------------ exact-path notice
    def estimate_seconds(self, n_masks: int = 1) -> float:
        """Estimated wall time (s) of :meth:`evaluate` on ``n_masks`` masks (every imager;
        :func:`~arraysel.objective.imagers.estimate_seconds`)."""
        return I.estimate_seconds(self.imagers, n_masks, self.chunk)

    def exact_notice(self, n_masks: int | None = None) -> str:
        """One line saying that (and why) the scene runs on the exact path, with time and memory."""
        return I.exact_notice(self.settings.name, self.imagers, self.chunk, n_masks)

    # ------------------------------------------------------------------ helpers
    def _timed(self):
        return _Timer(self)

    def as_masks(self, masks) -> torch.Tensor:
        """``masks`` (B, Ne) or (Ne,) as checked weights on the objective's device and dtype; a
        matrix scene's also (B, n_tx, Ne), a transmit aperture per transmit event."""
        return checked_masks(masks, self.n_elements, self.device, self.dtype, I.transmit_events(self.imagers))

    def _weights(self, weights: torch.Tensor) -> torch.Tensor:
        w = weights[None] if weights.dim() == 1 else weights   # (B, n_tx, Ne): one per transmit event
        if w.shape[-1] != self.n_elements:
            raise SelectionError(f"weights must have shape (B, {self.n_elements}), got {tuple(w.shape)}")
        return w.to(self.device, self.dtype)

    def _point_list(self, point):
        n = len(self.imagers)
        if point is None:
            return list(range(n))
        if not isinstance(point, int) or not 0 <= point < n:
            raise ParameterError(f"point = {point!r} is out of range; the scene has {n} field point(s)")
        return [point]

    def _kernels_only(self, what: str) -> None:
        """ParameterError unless every imager gives one 2-D kernel on a pixel grid (its ``pitch``)."""
        other = next((im for im in self.imagers if im.pitch is None), None)
        if other is not None:
            raise ParameterError(f"scene {self.settings.name!r} has planes, not a 2-D kernel on a pixel grid "
                                 f"(its imager gives {list(other.plane_names)}): use Objective.{what}")

    def _one_imager(self):
        if len(self.imagers) != 1:
            raise ParameterError(f"the scene has {len(self.imagers)} field points, each with its own kernel: "
                                 "use Objective.kernels(masks, point)")
        return self.imagers[0]

    # ------------------------------------------------------------------ images
    def reference_kernel(self, point: int | None = None) -> torch.Tensor:
        """The full-array PSF kernel: (window, window), or (P, window, window) for a several-point
        scene when ``point`` is None."""
        self._kernels_only("reference_planes")
        if point is None and len(self.imagers) == 1:
            point = 0
        if point is not None:
            return self.imagers[self._point_list(point)[0]].reference().kernel[0]
        return torch.stack([im.reference().kernel[0] for im in self.imagers])

    def kernels(self, masks, point: int | None = None) -> torch.Tensor:
        """Complex PSF kernels, no grad: (B, window, window) for one point (``point`` or a
        one-point scene), (B, P, window, window) for every point of a several-point scene."""
        self._kernels_only("planes")
        with torch.no_grad(), self._timed():
            m = self.as_masks(masks)
            one = len(self.imagers) == 1
            pts = self._point_list(0 if point is None and one else point)
            out = []
            for p in pts:
                im = self.imagers[p]
                out.append(torch.cat([im.image(m[i:i + n]).kernel for i, n in self._chunks(im, m.shape[0])]))
            return out[0] if len(pts) == 1 and (point is not None or one) else torch.stack(out, 1)

    def planes(self, weights) -> dict[str, torch.Tensor]:
        """The complex planes ``{name: (B, H, W)}`` of weights (B, Ne), differentiable (one imager)."""
        return self._one_imager().image(self._weights(torch.as_tensor(weights))).images

    def reference_planes(self) -> dict[str, torch.Tensor]:
        """The full array's planes ``{name: (1, H, W)}`` (computed once, no gradient; one imager)."""
        return self._one_imager().reference().images

    def metrics_of_kernels(self, kappa: torch.Tensor, terms=None) -> dict[str, torch.Tensor]:
        """Metrics of kernels shaped as :meth:`kernels` returns them ((B,) or (B, P) values)."""
        ref = self.reference_kernel().to(kappa.dtype)
        return M.psf_metrics(kappa, kappa_ref=ref, terms=terms, **self.metric_kw)

    def _chunks(self, imager, n: int):
        """(start, size) of the mask batches: ``chunk`` masks, fewer when the imager's memory says so."""
        step = max(1, min(self.chunk, imager.masks_per_batch()))
        return [(i, min(step, n - i)) for i in range(0, n, step)]

    def _metrics(self, p: int, planes: PlaneSet, terms=None) -> dict[str, torch.Tensor]:
        """The metrics of imager ``p``'s plane set (:func:`~arraysel.objective.plane_metrics.plane_scorer`)."""
        return self._scorers[p](planes, terms)

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, masks, return_kernels: bool = False, return_planes: bool = False,
                 receive=None) -> dict[str, np.ndarray]:
        """Every metric of a batch of masks: {name: float64 array (B,)}.

        masks: (B, Ne) 0/1 (or weights >= 0), numpy or torch. No gradient.
        With ``return_kernels`` the dict also holds ``"kernels"`` (B, w, w) complex (a 1-D scene;
        (B, P, w, w) for P points); with ``return_planes`` ``"planes"``, ``{name: complex (B, H, W)}``.
        ``receive``: separate receive masks (B, Ne), ``masks`` then the transmit aperture (a 1-D
        scene's exact path; :mod:`arraysel.objective.aperture`).
        """
        if return_kernels:
            self._kernels_only("evaluate(masks, return_planes=True)")
        with torch.no_grad(), self._timed():
            m = self.as_masks(masks)
            r = None if receive is None else self.as_masks(receive)
            if r is None and not self._announced and m.shape[0] > 1 and any(im.exact for im in self.imagers):
                self._announced = True
                _log.warning("evaluating %d masks on the exact PSF path: about %s", m.shape[0],
                             _fmt_seconds(self.estimate_seconds(int(m.shape[0]))))
            res = self._score(int(m.shape[0]), lambda im, i, n: im.image_masks(
                m[i:i + n], None if r is None else r[i:i + n]), return_kernels or return_planes)
        return self._images_out(res, return_kernels, return_planes)

    def evaluate_swaps(self, mask, out, into, return_kernels: bool = False) -> dict[str, np.ndarray]:
        """:meth:`evaluate` of the one-swap neighbours of a 0/1 selection ``mask`` (Ne,): element
        ``out[i]`` switched off and ``into[i]`` on (:class:`~arraysel.objective.contract.ScoresSwaps`;
        :func:`arraysel.objective.neighbours.evaluate_swaps` calls it): :meth:`evaluate_moves`
        with one element a move."""
        from arraysel.objective.neighbours import check_swaps

        m, a, b = check_swaps(mask, out, into)
        return self.evaluate_moves(m, a[:, None], b[:, None], return_kernels=return_kernels)

    def evaluate_moves(self, mask, out, into, return_kernels: bool = False) -> dict[str, np.ndarray]:
        """:meth:`evaluate` of the neighbours of a 0/1 selection ``mask`` (Ne,) that switch the
        elements ``out[i]`` off and ``into[i]`` on (int ``(B, m)`` each;
        :class:`~arraysel.objective.contract.ScoresMoves`;
        :func:`arraysel.objective.neighbours.evaluate_moves` calls it), counted as ``B``
        evaluations: the same values, to rounding, as scoring the neighbour masks independently.
        Each imager images the neighbours from the selection where it can
        (:meth:`~arraysel.physics.imaging.Imager.image_moves`: on a 1-D point the certificates'
        channel envelopes and the images of the neighbours are corrected from the selection's own,
        :meth:`~arraysel.physics.psf.PSFModel.swap_kernels`); on a 3-D scene's fast path each move is scored
        from the selection's planes plus its low-rank change, blocks of swaps of a few outgoing
        elements by batched products (:mod:`arraysel.objective.matrix_neighbours`). Rows of ``out``
        and ``into`` may be padded with ``-1`` (moves of different sizes in one call)."""
        return objective_moves.score_moves(self, mask, out, into, return_kernels)

    def _neighbourhood(self):
        """The neighbourhood that scores all swaps of a selection from its planes, or None
        (:func:`~arraysel.objective.imagers.neighbourhood_for`), formed once."""
        if self._neigh is None:
            self._neigh = I.neighbourhood_for(self) or False
        return self._neigh or None

    def swap_bases(self, model):
        """The neighbourhood bases kept for the field point of ``model`` (one of :attr:`psfs`;
        :func:`~arraysel.objective.objective_moves.swap_bases`)."""
        return objective_moves.swap_bases(self, model)

    def prepare_neighbourhoods(self) -> bool:
        """Form now what :meth:`evaluate_swaps` shares between selections, so that a search's first
        neighbourhoods do not pay for it; whether everything is kept
        (:func:`~arraysel.objective.objective_moves.prepare_neighbourhoods`)."""
        return objective_moves.prepare_neighbourhoods(self)

    def neighbourhood(self):
        """The :class:`~arraysel.objective.contract.Neighbourhood` a search scores neighbours with
        (:func:`~arraysel.objective.objective_moves.moves_neighbourhood`); None for a subclass
        that scores masks its own way and has no neighbourhood of its own (its neighbours are
        scored as masks)."""
        if type(self).evaluate is not Objective.evaluate:
            return None
        return objective_moves.moves_neighbourhood(self)

    def loss_model(self):
        """The :class:`~arraysel.objective.contract.LossModel` of :meth:`mask_loss`: the gradient
        by autograd, the Hessian by :meth:`mask_hessian`."""
        from arraysel.objective.contract import AutogradLossModel

        return AutogradLossModel(self.mask_loss, self.dtype, self.device, hessian=self.mask_hessian)

    def _score(self, n_masks: int, images_of, keep: bool) -> dict:
        """Every metric of ``n_masks`` selections whose plane sets ``images_of(imager, start, size)``
        gives (``(PlaneSet, fell_back)``) batch by batch (:meth:`_chunks`) on each imager; with
        ``keep``, their plane sets (on the CPU) under ``"_planes"``, one per imager."""
        per = [{k: [] for k in self._columns} for _ in self.imagers]
        kept: list = [[] for _ in self.imagers]
        for p, im in enumerate(self.imagers):
            for i, n in self._chunks(im, n_masks):
                ps, fb = images_of(im, i, n)
                self.fallbacks += int(fb.sum())
                met = self._metrics(p, ps)
                for name in self._columns:
                    per[p][name].append(met[name].double().cpu())
                if keep:
                    kept[p].append(ps.map(lambda x: x.cpu()))
        self.evaluations += int(n_masks)
        empty = torch.zeros(0, dtype=torch.float64)
        per_np = [{name: torch.cat(v) if v else empty for name, v in d.items()} for d in per]
        res = ({name: v.numpy() for name, v in per_np[0].items()} if len(self.imagers) == 1
               else aggregated(per_np, self.aggregate))
        if keep:
            res["_planes"] = [PlaneSet.cat(k) if k else None for k in kept]
        return res

    def _images_out(self, res: dict, kernels: bool, planes: bool) -> dict:
        return images_out(res, kernels, planes, self.imagers)

    def evaluate_indices(self, selections) -> dict[str, np.ndarray]:
        """:meth:`evaluate` for lists of active element indices (validated, k enforced)."""
        return self.evaluate(masks_from_indices(selections, self.n_elements, self.k))

    # ------------------------------------------------------------------ losses
    def psf_terms(self, weights: torch.Tensor, terms=None, receive=None) -> dict[str, torch.Tensor]:
        """Differentiable PSF metrics (B,) of soft element weights (B, Ne) (with ``receive``,
        separate receive weights (B, Ne): ``weights`` the transmit apodization).

        A several-point scene gives the aggregate over its points that
        ``metrics.aggregate`` chooses (the mean, or the worst point: the largest value).
        """
        w, r = self._weights(weights), None if receive is None else receive.to(self.device, self.dtype)
        return self._terms([im.image(w, r) for im in self.imagers], terms)

    def terms_of_kernels(self, kappas: list[torch.Tensor], terms=None) -> dict[str, torch.Tensor]:
        """:meth:`psf_terms` of the kernels ``kappas`` (one (B, win, win) tensor per point)."""
        return self._terms([im.wrap(k) for im, k in zip(self.imagers, kappas)], terms)

    def _terms(self, sets: list[PlaneSet], terms=None) -> dict[str, torch.Tensor]:
        per = [self._metrics(p, ps, terms) for p, ps in enumerate(sets)]
        if len(per) == 1:
            return per[0]
        # (differentiable) mean over the points, or the worst point: the largest value (lower is better)
        st = {name: torch.stack([d[name] for d in per], -1) for name in per[0]}
        return {name: v.mean(-1) if self.aggregate == "mean" else v.amax(-1) for name, v in st.items()}

    def _psf_loss(self, weights: torch.Tensor, kappas: list[torch.Tensor] | None = None, receive=None):
        """The scene-weighted PSF loss ``(total (B,), terms)`` of ``weights`` (B, Ne), from their
        kernels ``kappas`` when the caller has them (:func:`~arraysel.objective.objective_losses.psf_loss`)."""
        return objective_losses.psf_loss(self, weights, kappas, receive)

    def mask_loss(self, weights: torch.Tensor, receive=None):
        """Scene-weighted PSF loss of soft weights (B, Ne) in [0, 1]: (total (B,), terms);
        ``receive``: separate receive weights (B, Ne) (:func:`~arraysel.objective.objective_losses.mask_loss`)."""
        return objective_losses.mask_loss(self, weights, receive)

    def mask_hessian(self, mask) -> tuple[np.ndarray, np.ndarray]:
        """The gradient ``(Ne,)`` and the Hessian ``(Ne, Ne)`` (float64) of :meth:`mask_loss` at
        ``mask`` (:func:`~arraysel.objective.objective_losses.mask_hessian`)."""
        return objective_losses.mask_hessian(self, mask)

    def selection_loss(self, P: torch.Tensor, P_soft: torch.Tensor, step: int = 0):
        """Training loss of a (Ne, k) selection matrix: (scalar total, terms)
        (:func:`~arraysel.objective.objective_losses.selection_loss`)."""
        return objective_losses.selection_loss(self, P, P_soft)

    def worker_factory(self) -> "SceneObjectiveFactory | None":
        """A picklable recipe that rebuilds this objective on a worker (the scene, device, dtype
        and chunk); ``None`` for a subclass, which must give its own, and for an objective assembled
        without a scene."""
        if type(self) is not Objective or self.scene is None:
            return None
        return SceneObjectiveFactory(self.scene.to_dict(), device=str(self.device), dtype=dtype_name(self.dtype),
                                     chunk=int(self.chunk))

    def reset_counters(self):
        self.evaluations = 0
        self.gradient_steps = 0
        self.seconds = 0.0
        self.fallbacks = 0


_CACHE: dict = {}


def build_objective(scene="paper", device="cpu", dtype=torch.float32, objective_class=None, **kw) -> Objective:
    """Build (or reuse, within a process) the objective of a scene: an ``objective_class``
    (default :class:`Objective`, for every scene: 1-D, 3-D and sector scenes alike)."""
    sc = load_scene(scene) if not isinstance(scene, Scene) else scene
    cls = Objective if objective_class is None else objective_class
    key = (cls.__name__, repr(sc.tree), str(device), str(dtype), tuple(sorted(kw.items())))
    obj = _CACHE.get(key)
    if obj is None:
        obj = cls(sc, device=device, dtype=dtype, **kw)
        _CACHE[key] = obj
    obj.reset_counters()
    return obj


@dataclasses.dataclass(frozen=True)
class SceneObjectiveFactory(WorkerFactory):
    """Builds the physics objective of a scene with :func:`build_objective` (on a worker).

    Parameters
    ----------
    scene : the scene as a dictionary (``Scene.to_dict()``)
    device : ``"cpu"`` or ``"cuda"`` (on the worker)
    dtype : ``"float32"`` or ``"float64"``
    chunk : masks per batch inside ``Objective.evaluate``
    """

    scene: dict
    device: str = "cpu"
    dtype: str = "float32"
    chunk: int = DEFAULT_CHUNK

    def __hash__(self):  # the dict field is not hashable; the key is
        return hash(self.key())

    def __call__(self):
        return build_objective(load_scene(dict(self.scene)), device=self.device,
                               dtype=getattr(torch, self.dtype), chunk=self.chunk)
