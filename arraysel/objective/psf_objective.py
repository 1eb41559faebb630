"""The objective every selection strategy is judged by.

:class:`Objective` wraps a scene's PSF model and metrics:

* :meth:`Objective.evaluate`: batched, no-grad evaluation of many masks,
  returning every Table-1 metric (chunked, so memory stays bounded);
* :meth:`Objective.mask_loss`: differentiable, scene-weighted PSF loss of soft
  element weights (the same weights are the TX apodization and the RX
  channel weights);
* :meth:`Objective.selection_loss`: the training loss of an (Ne, k) selection
  matrix (PSF terms + entropy + row terms, :mod:`arraysel.objective.losses`;
  a scene that weights the end-to-end terms is trained by ``arraysel train``).

It counts evaluated masks, gradient steps and the wall time spent inside it,
so a comparison can report every strategy's budget and overhead.
Only the terms with a non-zero weight are computed.

A scene with several field points (``medium.points``) has one
:class:`~arraysel.physics.psf.PSFModel` per point (``Objective.psfs``); each point's
kernel is the window centred on its own peak, scored against its own full-array
reference. The headline metrics (:data:`METRIC_NAMES`) are then the aggregate
``metrics.aggregate`` chooses (the mean over the points, or the worst point),
and :meth:`Objective.evaluate` adds every metric per point, their mean and
their worst (:func:`point_metric_names`). A one-point scene returns exactly
the headline metrics, as before. See ``docs/scenes.md``.

When a point has no fast path, the objective logs once, when it is built, that
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

from arraysel.objective import metrics as M
from arraysel.objective.contract import WorkerFactory, dtype_name
from arraysel.objective.losses import PSF_WEIGHT_KEYS, training_loss
from arraysel.objective.pair_model import pair_model
from arraysel.errors import NumericalError, ParameterError, SelectionError
from arraysel.objective.tensors import objective_device
from arraysel.selection import masks_from_indices
from arraysel.physics.psf import PSFModel
from arraysel.scenes.schema import Scene, load_scene

_log = logging.getLogger(__name__)

METRIC_NAMES = M.METRIC_NAMES
#: aggregates over the field points of a several-point scene
AGGREGATES = ("mean", "worst")


def point_metric_names(n_points: int) -> tuple[str, ...]:
    """Breakdown keys of a scene with ``n_points`` field points (none for one point).

    ``"<metric>@p<i>"`` for point i (in ``medium.points`` order), then
    ``"<metric>@mean"`` and ``"<metric>@worst"`` (the largest value over the
    points; every metric is lower-is-better).
    """
    if n_points <= 1:
        return ()
    names = [f"{m}@p{i}" for i in range(n_points) for m in METRIC_NAMES]
    names += [f"{m}@{a}" for a in AGGREGATES for m in METRIC_NAMES]
    return tuple(names)


def _fmt_seconds(sec: float) -> str:
    if sec < 1:
        return f"{sec * 1e3:.0f} ms"
    if sec < 120:
        return f"{sec:.1f} s"
    if sec < 7200:
        return f"{sec / 60:.1f} min"
    return f"{sec / 3600:.1f} h"


#: most masks per batch of :meth:`Objective.evaluate`; each model takes at most its
#: :meth:`~arraysel.physics.psf.operator.PSFModel.masks_per_batch` at once (a memory budget:
#: the paper scene 256, the 128-element built-in scenes about 200). Against 128 on the paper
#: scene: 1.85 against 2.18 ms a mask (six rounds of 3000 masks alternated in one process; the
#: image product on E runs 10 % faster on the larger batch) and 10.9-11.0 against 11.4-11.5 s
#: for 5000 masks whole-process, for a resident peak 0.2 GiB higher (1.40 against 1.18 GB).
#: The scores do not depend on it (the same CSV to the last digit).
DEFAULT_CHUNK = 256


class Objective:
    """Batched, differentiable PSF objective of a scene (see module docstring).

    Parameters
    ----------
    scene : a :class:`~arraysel.scenes.schema.Scene` or the name/path of one.
    device : "cpu" or "cuda" (or a torch.device).
    dtype : torch.float32 (default) or torch.float64.
    chunk : masks per batch inside :meth:`evaluate` (:data:`DEFAULT_CHUNK`).
    """

    metric_names = METRIC_NAMES

    def __init__(self, scene: Scene | str = "paper", device="cpu", dtype=torch.float32, chunk: int = DEFAULT_CHUNK,
                 fast: bool = True):
        self.scene = load_scene(scene) if not isinstance(scene, Scene) else scene
        self.device = objective_device(device)
        self.dtype = dtype
        self.chunk = int(chunk)
        self.fast_requested = bool(fast)
        #: the scene's settings, read once: the objective does not go back to the scene
        self.settings = st = self.scene.objective_settings()
        self.setups = self.scene.psf_setups()
        setup = self.setups[0]
        self.setup = setup
        self.n_elements = setup.probe.n_elements
        self.k = st.k
        #: the layout (ObjectiveContract's optional capability): a 1-D probe has no grid; its element
        #: centres (Ne, 3) as (x, y, z) in metres
        self.element_grid = None
        xe, ze, _, _ = setup.probe.element_positions()
        self.element_positions = np.stack([xe, np.zeros_like(xe), ze], axis=1)
        #: the scene's constraints (:mod:`arraysel.constraints`), None without a [constraints] section
        self.constraints = self.scene.constraints()
        #: field points (x, z) in metres, one PSF model each (``self.psfs``; ``self.psf`` is the first)
        self.points = self.scene.points()
        self.n_points = len(self.setups)
        self.aggregate = st.aggregate
        margin, block = st.fast_margin, st.fast_block
        self.psfs = [PSFModel(s, dtype=dtype, device=self.device, fast=fast, margin=margin, block=block)
                     for s in self.setups]
        self.psf = self.psfs[0]
        if self.n_points > 1:  # the points share the memory cap: each keeps its share of DAS plans
            for p in self.psfs:
                p.plan_cache_elements = max(1, p.plan_cache_limit() // self.n_points)
            for p in self.psfs:
                p.other_bytes = sum(q.plan_cache_bytes() + q.model_bytes() for q in self.psfs if q is not p)
        self._announced = False
        if any(p.basis is None for p in self.psfs):
            _log.warning("%s", self.exact_notice())
        self.metric_kw = dict(pitch=setup.pitch, wavelength=setup.wavelength, **st.metric_radii)
        #: extra result keys of a several-point scene: every metric per point, their mean and worst
        self.breakdown_names = point_metric_names(self.n_points)
        self.weights = dict(st.weights)
        self.evaluations = 0
        self.gradient_steps = 0
        self.seconds = 0.0
        self.fallbacks = 0
        #: :meth:`mask_hessian` from the pair basis (:mod:`arraysel.objective.pair_model`) where it
        #: applies (False: always the autograd of ``mask_loss``)
        self.hessian_from_pairs = True

    # ------------------------------------------------------------------ exact-path notice
    def estimate_seconds(self, n_masks: int = 1) -> float:
        """Estimated wall time (s) of :meth:`evaluate` on ``n_masks`` masks (every field point).

        Exact-path points are estimated by :meth:`PSFModel.exact_seconds_per_mask`; fast-path
        points count as free (their cost is milliseconds a mask).
        """
        total = 0.0
        for p in self.psfs:
            if p.basis is None:
                total += n_masks * p.exact_seconds_per_mask(min(self.chunk, p.masks_per_batch(), max(1, n_masks)))
                if p._ref is None:  # the full array's reference kernel comes first, once
                    total += p.exact_seconds_per_mask(1)
        return total

    def exact_notice(self, n_masks: int | None = None) -> str:
        """One line saying that (and why) the scene runs on the exact path, with time and memory."""
        slow = [i for i, p in enumerate(self.psfs) if p.basis is None]
        if not slow:
            return f"scene {self.settings.name!r}: fast PSF path on every field point"
        why = "disabled (fast=False)" if not self.fast_requested else "unavailable (its precomputation is over its cap)"
        where = "" if self.n_points == 1 else f" for {len(slow)} of {self.n_points} field points"
        per = sum(p.exact_seconds_per_mask() for p in self.psfs if p.basis is None)
        mem = max(p.exact_bytes(p.masks_per_batch()) for p in (self.psfs[i] for i in slow))
        text = (f"scene {self.settings.name!r}: PSF fast path {why}{where}; using the exact path: about "
                f"{_fmt_seconds(per)} per mask (estimated), memory up to {mem / 2 ** 30:.1f} GiB "
                f"(cap {self.psfs[slow[0]].memory_limit / 2 ** 30:.1f} GiB, ARRAYSEL_MEMORY_GIB)")
        if n_masks is not None:
            text += f"; {n_masks} mask(s): about {_fmt_seconds(self.estimate_seconds(n_masks))}"
        return text

    # ------------------------------------------------------------------ helpers
    def _timed(self):
        obj = self

        class _T:
            def __enter__(self):
                self.t = time.perf_counter()

            def __exit__(self, *a):
                obj.seconds += time.perf_counter() - self.t

        return _T()

    def as_masks(self, masks) -> torch.Tensor:
        m = masks if isinstance(masks, torch.Tensor) else torch.as_tensor(np.asarray(masks, dtype=np.float64))
        if m.dim() == 1:
            m = m[None]
        if m.dim() != 2 or m.shape[1] != self.n_elements:
            raise SelectionError(f"masks must have shape (B, {self.n_elements}), got {tuple(m.shape)}")
        m = m.to(self.device, self.dtype)
        if not bool(torch.isfinite(m).all()):
            raise SelectionError("masks contain NaN or Inf")
        if bool((m < 0).any()):
            raise SelectionError("mask weights must be >= 0")
        if bool((m.sum(1) == 0).any()):
            bad = torch.nonzero(m.sum(1) == 0).flatten().tolist()
            raise SelectionError(f"empty selection (no active element) at batch position(s) {bad}")
        return m

    def _point_list(self, point):
        if point is None:
            return list(range(self.n_points))
        if not isinstance(point, int) or not 0 <= point < self.n_points:
            raise ParameterError(f"point = {point!r} is out of range; the scene has {self.n_points} field point(s)")
        return [point]

    def reference_kernel(self, point: int | None = None) -> torch.Tensor:
        """The full-array PSF kernel: (window, window), or (P, window, window) for a several-point
        scene when ``point`` is None."""
        if point is None and self.n_points == 1:
            point = 0
        if point is not None:
            return self.psfs[self._point_list(point)[0]].reference_kernel()
        return torch.stack([p.reference_kernel() for p in self.psfs])

    def kernels(self, masks, point: int | None = None) -> torch.Tensor:
        """Complex PSF kernels, no grad: (B, window, window) for one point (``point`` or a
        one-point scene), (B, P, window, window) for every point of a several-point scene."""
        with torch.no_grad(), self._timed():
            m = self.as_masks(masks)
            pts = self._point_list(0 if point is None and self.n_points == 1 else point)
            out = []
            for p in pts:
                model = self.psfs[p]
                out.append(torch.cat([model.kernels(m[i:i + n]) for i, n in self._chunks(model, m.shape[0])]))
            return out[0] if len(pts) == 1 and (point is not None or self.n_points == 1) else torch.stack(out, 1)

    def metrics_of_kernels(self, kappa: torch.Tensor, terms=None) -> dict[str, torch.Tensor]:
        """Metrics of kernels shaped as :meth:`kernels` returns them ((B,) or (B, P) values)."""
        ref = self.reference_kernel().to(kappa.dtype)
        return M.psf_metrics(kappa, kappa_ref=ref, terms=terms, **self.metric_kw)

    def _chunks(self, model: PSFModel, n: int):
        """(start, size) of the mask batches: ``chunk`` masks, fewer when the exact path's memory says so."""
        step = max(1, min(self.chunk, model.masks_per_batch()))
        return [(i, min(step, n - i)) for i in range(0, n, step)]

    def _aggregate(self, per_point: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, worst) over points of per-point values [(B,), ...]; worst = largest (lower is better)."""
        st = torch.stack(per_point, -1)
        return st.mean(-1), st.amax(-1)

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, masks, return_kernels: bool = False, receive=None) -> dict[str, np.ndarray]:
        """Every Table-1 metric of a batch of masks: {name: float64 array (B,)}.

        masks: (B, Ne) 0/1 (or weights >= 0), numpy or torch. No gradient.
        With ``return_kernels`` the dict also holds ``"kernels"`` (B, w, w) complex.
        ``receive``: separate receive masks (B, Ne), ``masks`` then the transmit aperture
        (exact path; :mod:`arraysel.objective.aperture`).
        """
        if receive is not None:
            return self._evaluate_apertures(masks, receive, return_kernels)
        with torch.no_grad(), self._timed():
            m = self.as_masks(masks)
            if not self._announced and m.shape[0] > 1 and any(p.basis is None for p in self.psfs):
                self._announced = True
                _log.warning("evaluating %d masks on the exact PSF path: about %s", m.shape[0],
                             _fmt_seconds(self.estimate_seconds(int(m.shape[0]))))
            res = self._score(int(m.shape[0]), lambda model, i, n: model.kernels(m[i:i + n], return_info=True),
                              return_kernels)
        return res

    def _evaluate_apertures(self, masks, receive, return_kernels: bool) -> dict[str, np.ndarray]:
        with torch.no_grad(), self._timed():
            m, r = self.as_masks(masks), self.as_masks(receive)
            return self._score(int(m.shape[0]), lambda model, i, n: model.kernels(
                m[i:i + n], return_info=True, receive=r[i:i + n]), return_kernels)

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
        :func:`arraysel.objective.neighbours.evaluate_moves` calls it). The same values, to
        rounding, as scoring the neighbour masks independently, and counted as as many
        evaluations; the certificates' channel envelopes and the images of the neighbours are
        corrected from the selection's own (:meth:`~arraysel.physics.psf.PSFModel.swap_kernels`),
        a neighbour they do not settle goes on to the refinement and the exact path as in
        :meth:`evaluate`. Rows of ``out`` and ``into`` may be padded with ``-1`` (moves of
        different sizes in one call)."""
        from arraysel.objective.neighbours import check_moves, move_masks

        m, a, b = check_moves(mask, out, into)
        if type(self).evaluate is not Objective.evaluate:
            # a subclass that scores masks its own way (MatrixObjective): its evaluate of the masks
            return self.evaluate(move_masks(m, a, b))
        if m.size != self.n_elements:
            raise SelectionError(f"mask must have shape ({self.n_elements},), got ({m.size},)")
        if not m.any():
            raise SelectionError("empty selection (no active element): mask")
        with torch.no_grad(), self._timed():
            base = self.as_masks(m[None])[0]
            return self._score(int(a.shape[0]), lambda model, i, n: model.swap_kernels(base, a[i:i + n], b[i:i + n],
                                                                                         return_info=True,
                                                                                         bases=self.swap_bases(model)),
                               return_kernels)

    def swap_bases(self, model: PSFModel):
        """The neighbourhood bases kept for the field point of ``model`` (one of :attr:`psfs`;
        :class:`~arraysel.objective.swapbases.SwapBases`): the state a search's neighbourhoods
        share, kept here, not in the physics."""
        from arraysel.objective.swapbases import SwapBases

        kept = self.__dict__.setdefault("_swap_bases", {})
        if id(model) not in kept:
            kept[id(model)] = SwapBases()
        return kept[id(model)]

    def prepare_neighbourhoods(self) -> bool:
        """Form now the pair-image rows :meth:`evaluate_swaps` gathers (each field point's basis,
        :meth:`~arraysel.physics.psf.basis.PairBasis.fill_pair_rows`; a few seconds and
        ``k``-independent memory: 0.32 GiB on the paper scene, 1.3 GiB for 128 elements), so that
        a search's first neighbourhoods do not pay for them. Returns whether every basis keeps
        all its rows (False: beyond the memory cap, each neighbourhood forms the rows it needs)."""
        done = True
        for model in self.psfs:
            basis = getattr(model, "basis", None)
            if basis is not None:
                done = basis.fill_pair_rows() and done
        return done

    def neighbourhood(self):
        """The :class:`~arraysel.objective.contract.Neighbourhood` a search scores neighbours with:
        :meth:`evaluate_moves`, prepared by :meth:`prepare_neighbourhoods`; None for a subclass
        that scores masks its own way and has no neighbourhood of its own (its neighbours are
        scored as masks)."""
        from arraysel.objective.contract import MovesNeighbourhood

        if type(self).evaluate is not Objective.evaluate:
            return None
        return MovesNeighbourhood(self.evaluate_moves, self.prepare_neighbourhoods)

    def loss_model(self):
        """The :class:`~arraysel.objective.contract.LossModel` of :meth:`mask_loss`: the gradient
        by autograd, the Hessian by :meth:`mask_hessian`."""
        from arraysel.objective.contract import AutogradLossModel

        return AutogradLossModel(self.mask_loss, self.dtype, self.device, hessian=self.mask_hessian)

    def _score(self, n_masks: int, kernels_of, return_kernels: bool) -> dict[str, np.ndarray]:
        """Every metric of ``n_masks`` selections whose kernels ``kernels_of(model, start, size)``
        gives (``(kernels, fell_back)``) batch by batch (:meth:`_chunks`) on each field point."""
        per = [{k: [] for k in METRIC_NAMES} for _ in self.psfs]
        kern: list = [[] for _ in self.psfs]
        for p, model in enumerate(self.psfs):
            ref = model.reference_kernel()
            for i, n in self._chunks(model, n_masks):
                k, fb = kernels_of(model, i, n)
                self.fallbacks += int(fb.sum())
                met = M.psf_metrics(k, kappa_ref=ref.to(k.dtype), **self.metric_kw)
                for name in METRIC_NAMES:
                    per[p][name].append(met[name].double().cpu())
                if return_kernels:
                    kern[p].append(k.cpu())
        self.evaluations += int(n_masks)
        empty = torch.zeros(0, dtype=torch.float64)
        per_np = [{name: torch.cat(v) if v else empty for name, v in d.items()} for d in per]
        if self.n_points == 1:
            res = {name: v.numpy() for name, v in per_np[0].items()}
        else:
            res = {}
            for name in METRIC_NAMES:
                mean, worst = self._aggregate([d[name] for d in per_np])
                res[name] = (mean if self.aggregate == "mean" else worst).numpy()
                for p, d in enumerate(per_np):
                    res[f"{name}@p{p}"] = d[name].numpy()
                res[f"{name}@mean"] = mean.numpy()
                res[f"{name}@worst"] = worst.numpy()
        if return_kernels:
            w = self.setup.window
            ks = [torch.cat(v).numpy() if v else np.zeros((0, w, w), np.complex64) for v in kern]
            res["kernels"] = ks[0] if self.n_points == 1 else np.stack(ks, 1)
        return res

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
        w = weights if weights.dim() == 2 else weights[None]
        if w.shape[-1] != self.n_elements:
            raise SelectionError(f"weights must have shape (B, {self.n_elements}), got {tuple(w.shape)}")
        w = w.to(self.device, self.dtype)
        r = None if receive is None else receive.to(self.device, self.dtype)
        return self.terms_of_kernels([model.kernels(w, receive=r) for model in self.psfs], terms)

    def terms_of_kernels(self, kappas: list[torch.Tensor], terms=None) -> dict[str, torch.Tensor]:
        """:meth:`psf_terms` of the kernels ``kappas`` (one (B, win, win) tensor per point)."""
        per = []
        for model, kappa in zip(self.psfs, kappas):
            ref = model.reference_kernel().to(kappa.dtype)
            per.append(M.psf_metrics(kappa, kappa_ref=ref, terms=terms, **self.metric_kw))
        if len(per) == 1:
            return per[0]
        out = {}
        for name in per[0]:
            mean, worst = self._aggregate([d[name] for d in per])
            out[name] = mean if self.aggregate == "mean" else worst
        return out

    def _psf_loss(self, weights: torch.Tensor, kappas: list[torch.Tensor] | None = None, receive=None):
        """The scene-weighted PSF loss ``(total (B,), terms)`` of ``weights`` (B, Ne), from their
        kernels ``kappas`` (one tensor per point) when the caller has them."""
        wts = {k: self.weights.get(k, 0.0) for k in PSF_WEIGHT_KEYS}
        need = [k for k, v in wts.items() if v > 0]
        if not need:
            z = weights.sum(-1) * 0
            return z, {}
        if receive is not None:
            return training_loss(self.psf_terms(weights, terms=need, receive=receive), wts)
        terms = self.psf_terms(weights, terms=need) if kappas is None else self.terms_of_kernels(kappas, need)
        return training_loss(terms, wts)

    def mask_loss(self, weights: torch.Tensor, receive=None):
        """Scene-weighted PSF loss of soft weights (B, Ne) in [0, 1]: (total (B,), terms);
        ``receive``: separate receive weights (B, Ne)."""
        with self._timed():
            w = weights if weights.dim() == 2 else weights[None]
            total, terms = self._psf_loss(w) if receive is None else self._psf_loss(w, receive=receive)
            if not bool(torch.isfinite(total.detach()).all()):
                raise NumericalError("mask_loss is not finite (NaN/Inf) for some weights")
            self.evaluations += int(w.shape[0])
            if w.requires_grad:
                self.gradient_steps += 1
        return total, terms

    def mask_hessian(self, mask) -> tuple[np.ndarray, np.ndarray]:
        """The gradient ``(Ne,)`` and the Hessian ``(Ne, Ne)`` (float64) of :meth:`mask_loss` at
        ``mask`` (weights ``(Ne,)``): the loss's quadratic model, by which swap descents with
        ``model = quadratic`` rank swaps: from the pair basis where it applies
        (:func:`~arraysel.objective.pair_model.pair_model`, :attr:`hessian_from_pairs`), else one
        forward pass and ``Ne`` Hessian-vector products in one batched backward pass; the same
        values to rounding. Counted as ``Ne`` evaluations and one gradient step."""
        n = self.n_elements
        with self._timed():
            fast = pair_model(self, mask) if self.hessian_from_pairs else None
            if fast is not None:
                _total, g, H = fast
            else:
                w = torch.as_tensor(np.asarray(mask, dtype=np.float64), dtype=self.dtype,
                                    device=self.device).reshape(1, n).requires_grad_(True)
                total, _terms = self._psf_loss(w)
                (g,) = torch.autograd.grad(total.sum(), w, create_graph=True)
                eye = torch.eye(n, dtype=self.dtype, device=self.device)[:, None, :]
                (H,) = torch.autograd.grad(g, w, eye, is_grads_batched=True)
                g = g.detach()[0].double().cpu().numpy()
                H = H.detach()[:, 0, :].double().cpu().numpy()
            if not (np.isfinite(g).all() and np.isfinite(H).all()):
                raise NumericalError("mask_hessian is not finite (NaN/Inf) for this selection")
            self.evaluations += n
            self.gradient_steps += 1
        return g, H

    def selection_loss(self, P: torch.Tensor, P_soft: torch.Tensor, step: int = 0):
        """Training loss of a (Ne, k) selection matrix: (scalar total, terms).

        Element weights are the row sums of P (clamped to [0, 1]); L_ent and
        L_row act on P_soft (:mod:`arraysel.objective.losses`). A scene that
        weights L_conv or L_rec is trained end to end (``arraysel train``), not here.
        """
        with self._timed():
            if P.dim() != 2 or P.shape[0] != self.n_elements:
                raise SelectionError(f"P must have shape ({self.n_elements}, k), got {tuple(P.shape)}")
            w = P.sum(1).clamp(0, 1)[None]
            psf = self._psf_loss(w)[1]
            total, terms = training_loss({k: v.sum() for k, v in psf.items()}, self.weights, P_soft=P_soft)
            if self.settings.needs_data:
                raise ParameterError(f"scene {self.settings.name!r} weights L_conv/L_rec: train it with "
                                     "`arraysel train` (end-to-end training computes those terms)")
            if not bool(torch.isfinite(total.detach())):
                raise NumericalError("selection_loss is not finite (NaN/Inf)")
            self.evaluations += 1
            if P.requires_grad:
                self.gradient_steps += 1
        return total, terms

    def worker_factory(self) -> "SceneObjectiveFactory | None":
        """A picklable recipe that rebuilds this objective on a worker (the scene, device, dtype
        and chunk); ``None`` for a subclass, which must give its own."""
        if type(self) is not Objective:
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
    (default :class:`Objective`; :func:`arraysel.objective.build.build_objective` picks the
    3-D scenes' :class:`~arraysel.objective.matrix_objective.MatrixObjective`)."""
    sc = load_scene(scene) if not isinstance(scene, Scene) else scene
    cls = Objective if objective_class is None else objective_class
    if (sc.is_volume or sc.is_sector) and cls is Objective:
        raise ParameterError(f"scene {sc.name!r} is a 3-D scene: build it with arraysel.build_objective "
                             "(arraysel.objective.build), which gives its MatrixObjective or SectorObjective")
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
