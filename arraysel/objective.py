"""The objective every selection strategy is judged by.

:class:`Objective` wraps a scene's PSF model and metrics:

* :meth:`Objective.evaluate`: batched, no-grad evaluation of many masks,
  returning every Table-1 metric (chunked, so memory stays bounded);
* :meth:`Objective.mask_loss`: differentiable, scene-weighted PSF loss of soft
  element weights (the same weights are the TX apodization and the RX
  channel weights);
* :meth:`Objective.selection_loss`: the training loss of an (Ne, k) selection
  matrix (PSF terms + entropy + row terms; end-to-end terms on scenes that
  weight them, through a data term the trainer attaches).

It counts evaluated masks, gradient steps and the wall time spent inside it,
so a comparison can report every strategy's budget and overhead.
Only the terms with a non-zero weight are computed.
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch

from . import metrics as M
from .errors import NumericalError, ParameterError, SelectionError
from .psf import PSFModel
from .scene import Scene, load_scene

METRIC_NAMES = ("L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i", "L_SLR", "Mean")
PSF_WEIGHT_KEYS = ("L_PSF", "L_contrast", "L_SLR")


def masks_from_indices(selections, n_elements: int, k: int | None = None) -> np.ndarray:
    """(B, Ne) 0/1 float masks from lists of active element indices, validated.

    Raises :class:`SelectionError` naming the offending selection (its position)
    for a repeated, negative or out-of-range index, or a wrong count.
    """
    out = np.zeros((len(selections), n_elements), dtype=np.float64)
    for i, sel in enumerate(selections):
        idx = [int(v) for v in sel]
        if any(v < 0 or v >= n_elements for v in idx):
            raise SelectionError(f"selection {i}: element indices must be in [0, {n_elements - 1}], got {idx}")
        if len(set(idx)) != len(idx):
            raise SelectionError(f"selection {i}: repeated element index in {idx}")
        if k is not None and len(idx) != k:
            raise SelectionError(f"selection {i}: expected k = {k} elements, got {len(idx)}")
        if not idx:
            raise SelectionError(f"selection {i}: empty selection")
        out[i, idx] = 1.0
    return out


class Objective:
    """Batched, differentiable PSF objective of a scene (see module docstring).

    Parameters
    ----------
    scene : a :class:`~arraysel.scene.Scene` or the name/path of one.
    device : "cpu" or "cuda" (or a torch.device).
    dtype : torch.float32 (default) or torch.float64.
    chunk : masks per batch inside :meth:`evaluate`.
    """

    metric_names = METRIC_NAMES

    def __init__(self, scene: Scene | str = "paper", device="cpu", dtype=torch.float32, chunk: int = 256,
                 fast: bool = True):
        self.scene = load_scene(scene) if not isinstance(scene, Scene) else scene
        self.device = torch.device(device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ParameterError("device = 'cuda' but no CUDA device is available; use --device cpu")
        self.dtype = dtype
        self.chunk = int(chunk)
        setup = self.scene.psf_setup()
        self.setup = setup
        self.n_elements = setup.probe.n_elements
        self.k = self.scene.k
        sim = self.scene.section("simulator")
        self.psf = PSFModel(setup, dtype=dtype, device=self.device, fast=fast,
                            margin=int(sim.get("fast_margin", 8)), block=int(sim.get("fast_block", 8)))
        met = self.scene.section("metrics")
        self.metric_kw = dict(pitch=setup.pitch, wavelength=setup.wavelength,
                              r_main=float(met.get("r_main", 1.5)), r_guard=float(met.get("r_guard", 2.5)),
                              quantile=float(met.get("quantile", 0.99)))
        self.weights = self.scene.weights
        self.evaluations = 0
        self.gradient_steps = 0
        self.seconds = 0.0
        self.fallbacks = 0
        #: optional end-to-end data term: callable(kappa, P, P_soft, step) -> dict of terms
        self.data_term: Callable | None = None

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

    def reference_kernel(self) -> torch.Tensor:
        """The full-array PSF kernel (window, window)."""
        return self.psf.reference_kernel()

    def kernels(self, masks) -> torch.Tensor:
        """(B, window, window) complex PSF kernels, no grad."""
        with torch.no_grad(), self._timed():
            m = self.as_masks(masks)
            return torch.cat([self.psf.kernels(m[i:i + self.chunk]) for i in range(0, m.shape[0], self.chunk)])

    def metrics_of_kernels(self, kappa: torch.Tensor, terms=None) -> dict[str, torch.Tensor]:
        ref = self.reference_kernel().to(kappa.dtype)
        return M.psf_metrics(kappa, kappa_ref=ref, terms=terms, **self.metric_kw)

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, masks, return_kernels: bool = False) -> dict[str, np.ndarray]:
        """Every Table-1 metric of a batch of masks: {name: float64 array (B,)}.

        masks: (B, Ne) 0/1 (or weights >= 0), numpy or torch. No gradient.
        With ``return_kernels`` the dict also holds ``"kernels"`` (B, w, w) complex.
        """
        with torch.no_grad(), self._timed():
            m = self.as_masks(masks)
            ref = self.reference_kernel()
            out = {k: [] for k in METRIC_NAMES}
            kern = []
            for i in range(0, m.shape[0], self.chunk):
                k, fb = self.psf.kernels(m[i:i + self.chunk], return_info=True)
                self.fallbacks += int(fb.sum())
                met = M.psf_metrics(k, kappa_ref=ref.to(k.dtype), **self.metric_kw)
                for name in METRIC_NAMES:
                    out[name].append(met[name].double().cpu())
                if return_kernels:
                    kern.append(k.cpu())
            self.evaluations += int(m.shape[0])
        res = {name: torch.cat(v).numpy() for name, v in out.items()}
        if return_kernels:
            res["kernels"] = torch.cat(kern).numpy()
        return res

    def evaluate_indices(self, selections) -> dict[str, np.ndarray]:
        """:meth:`evaluate` for lists of active element indices (validated, k enforced)."""
        return self.evaluate(masks_from_indices(selections, self.n_elements, self.k))

    # ------------------------------------------------------------------ losses
    def psf_terms(self, weights: torch.Tensor, terms=None) -> dict[str, torch.Tensor]:
        """Differentiable PSF metrics (B,) of soft element weights (B, Ne)."""
        w = weights if weights.dim() == 2 else weights[None]
        if w.shape[-1] != self.n_elements:
            raise SelectionError(f"weights must have shape (B, {self.n_elements}), got {tuple(w.shape)}")
        kappa = self.psf.kernels(w.to(self.device, self.dtype))
        return self.metrics_of_kernels(kappa, terms=terms)

    def _psf_loss(self, weights: torch.Tensor):
        wts = {k: self.weights.get(k, 0.0) for k in PSF_WEIGHT_KEYS}
        need = [k for k, v in wts.items() if v > 0]
        terms_needed = []
        for k in need:
            terms_needed += ["L_SLR"] if k == "L_SLR" else [k]
        if not terms_needed:
            z = weights.sum(-1) * 0
            return z, {}
        terms = self.psf_terms(weights, terms=terms_needed)
        total = sum(wts[k] * terms[k] for k in need)
        return total, terms

    def mask_loss(self, weights: torch.Tensor):
        """Scene-weighted PSF loss of soft weights (B, Ne) in [0, 1]: (total (B,), terms)."""
        with self._timed():
            w = weights if weights.dim() == 2 else weights[None]
            total, terms = self._psf_loss(w)
            if not bool(torch.isfinite(total.detach()).all()):
                raise NumericalError("mask_loss is not finite (NaN/Inf) for some weights")
            self.evaluations += int(w.shape[0])
            if w.requires_grad:
                self.gradient_steps += 1
        return total, terms

    def selection_loss(self, P: torch.Tensor, P_soft: torch.Tensor, step: int = 0):
        """Training loss of a (Ne, k) selection matrix: (scalar total, terms).

        Element weights are the row sums of P (clamped to [0, 1]); L_ent and
        L_row act on P_soft; L_conv and L_rec come from :attr:`data_term`
        on scenes that weight them.
        """
        with self._timed():
            if P.dim() != 2 or P.shape[0] != self.n_elements:
                raise SelectionError(f"P must have shape ({self.n_elements}, k), got {tuple(P.shape)}")
            w = P.sum(1).clamp(0, 1)[None]
            total, terms = self._psf_loss(w)
            total = total.sum()
            terms = {k: v.sum() for k, v in terms.items()}
            if self.weights.get("L_ent", 0) > 0:
                terms["L_ent"] = M.l_ent(P_soft)
                total = total + self.weights["L_ent"] * terms["L_ent"]
            if self.weights.get("L_row", 0) > 0:
                # on P_soft, as the trainer and the toy objective: the straight-through P
                # has one-hot columns over distinct elements, so its rows never sum past 1
                terms["L_row"] = M.l_row(P_soft)
                total = total + self.weights["L_row"] * terms["L_row"]
            if self.scene.needs_data:
                if self.data_term is None:
                    raise ParameterError(f"scene {self.scene.name!r} weights L_conv/L_rec: train it with "
                                         "`arraysel train` (the data term is attached by the trainer)")
                kappa = self.psf.kernels(w)
                extra = self.data_term(kappa[0], P, P_soft, step)
                for k, v in extra.items():
                    terms[k] = v
                    total = total + self.weights.get(k, 0.0) * v
            if not bool(torch.isfinite(total.detach())):
                raise NumericalError("selection_loss is not finite (NaN/Inf)")
            self.evaluations += 1
            if P.requires_grad:
                self.gradient_steps += 1
        return total, terms

    def reset_counters(self):
        self.evaluations = 0
        self.gradient_steps = 0
        self.seconds = 0.0
        self.fallbacks = 0


_CACHE: dict = {}


def build_objective(scene="paper", device="cpu", dtype=torch.float32, **kw) -> Objective:
    """Build (or reuse, within a process) the objective of a scene."""
    sc = load_scene(scene) if not isinstance(scene, Scene) else scene
    key = (repr(sc.tree), str(device), str(dtype), tuple(sorted(kw.items())))
    obj = _CACHE.get(key)
    if obj is None:
        obj = Objective(sc, device=device, dtype=dtype, **kw)
        _CACHE[key] = obj
    obj.reset_counters()
    return obj
