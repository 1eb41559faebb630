"""End-to-end training of an element selection with the reconstruction network (``docs/training.md``).

The physics enters through one callable, ``kernel_fn(weights) -> kappa``:
``weights`` is an ``(Ne,)`` float tensor (1 for an active element, 0 for an
inactive one in the forward pass, with straight-through gradients) and
``kappa`` the ``(n, n)`` complex PSF kernel, differentiable in ``weights``.

Selection protocol
------------------
A *selection module* is an ``nn.Module`` called as
``selection(tau, generator) -> (P, P_soft)``, both ``(Ne, k)``: ``P`` is the
hard 0/1 selection matrix carrying the straight-through gradient and
``P_soft`` the column-wise softmax probabilities. In ``eval()`` mode it must
be deterministic (it then gives the learned selection). Element ``i`` is
active when row ``i`` of ``P`` sums to 1; the trainer passes
``weights = P.sum(1)`` to ``kernel_fn``. :class:`HardSTESelection` is the
HARD-STE module of the paper (:mod:`arraysel.e2e.hardste`). The settings are in
:mod:`arraysel.e2e.config`, the kernel resampling in :mod:`arraysel.e2e.kernels`, the
learned selection's evaluation (fine-tuning, held-out metrics) in :mod:`arraysel.e2e.evaluation`;
this module keeps the trainer and re-exports those names.

Loss (``docs/metrics.md``)
--------------------------
``total = w L_PSF + w L_conv + w L_rec + w L_contrast + w L_SLR + w L_ent + w L_row`` with the
weights of ``config.weights`` (the scene's names; default 10, 1, 10, 10, 10, 1, 10), assembled by
:func:`arraysel.objective.losses.training_loss`, the function every objective uses. A term whose
weight is 0 is not computed. ``L_PSF``, ``L_contrast``, ``L_SLR`` come from
``psf_terms_fn(kappa) -> dict`` (keys ``'L_PSF'``, ``'L_contrast'`` and ``'L_SLR'``, or
``'L_SLR_q'`` and ``'L_SLR_i'`` whose mean is taken); the others come from
:mod:`arraysel.objective.losses`:

* ``L_conv`` (:func:`~arraysel.objective.losses.l_conv`): squared difference of
  ``Y_c = kappa (*) I_s`` and ``Y_ref = kappa_ref (*) I_s``. ``conv_reduction='mean'``
  (default) averages ``|Y_c - Y_ref|^2`` over pixels and batch, like
  ``L_rec``; ``'sum'`` takes the per-image squared norm ``||Y_c - Y_ref||^2``
  averaged over the batch (``n^2`` times larger).
* ``L_rec = mean((I_hat - I_ref)^2)`` over pixels and batch (:func:`~arraysel.objective.losses.l_rec`).
* ``L_ent``, ``L_row``: on ``P_soft`` (:func:`~arraysel.objective.losses.l_ent`,
  :func:`~arraysel.objective.losses.l_row`; the hard ``P`` drawn without replacement never
  repeats an element, so the row penalty on it would be identically zero).

Image size
----------
The scenes are ``image_size x image_size`` (default: the kernel's size). When
it differs from the kernel window, the data terms use the kernel cropped
around its centre pixel (or zero-padded around it), :func:`fit_kernel`; the
PSF terms always see the whole kernel.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import os
from pathlib import Path
from typing import Any, Callable, Mapping

import torch
import torch.nn as nn
from tqdm.auto import tqdm

from arraysel.e2e.config import TrainConfig
from arraysel.e2e.data import SceneMaker
# the learned selection's evaluation lives in its own module; its names stay importable from here
from arraysel.e2e.evaluation import E2EEvaluation, as_images, blurred_image, mask_to_weights
from arraysel.e2e.hardste import HardSTESelection, tau_schedule
from arraysel.e2e.kernels import decimate_kernel, fit_kernel
from arraysel.e2e.recon import ConvolutionOperator, LinearConvolutionOperator, Reconstructor
from arraysel.errors import NumericalError, ParameterError, check_number
from arraysel.io.atomic import AtomicFile
from arraysel.objective.losses import (DATA_WEIGHT_KEYS, PSF_WEIGHT_KEYS, l_conv, l_ent, l_rec, l_row,
                                       training_loss)

__all__ = ["tau_schedule", "HardSTESelection", "TrainConfig", "E2ETrainer",
           "train_e2e", "mask_to_weights", "entropy_loss", "row_loss", "fit_kernel", "decimate_kernel",
           "balanced_total", "BALANCED_TERMS", "blurred_image"]

log = logging.getLogger(__name__)

KernelFn = Callable[[torch.Tensor], torch.Tensor]
#: the terms ``balance='initial'`` divides by their value at the start (``L_ent`` and ``L_row``
#: are regularisers of the selection matrix, ``L_row`` is ~0 at the start: left as they are)
BALANCED_TERMS = PSF_WEIGHT_KEYS + DATA_WEIGHT_KEYS
CHECKPOINT_FORMAT = "arraysel-e2e-1"


#: ``L_ent`` (mean column entropy of ``P_soft``): :func:`arraysel.objective.losses.l_ent`
entropy_loss = l_ent
#: ``L_row`` (``sum_i relu(sum_j p_ij - 1)^2``): :func:`arraysel.objective.losses.l_row`
row_loss = l_row


def balanced_total(terms: Mapping[str, torch.Tensor], weights: Mapping[str, float],
                   scales: Mapping[str, float] | None = None) -> torch.Tensor:
    """``sum_t w_t L_t / s_t`` over the terms given (``s_t = 1`` for a term not in ``scales``):
    :func:`arraysel.objective.losses.training_loss` with ``scales``.

    With ``scales`` the values of the terms at the start of training
    (``balance='initial'``), every balanced term enters with its weight at
    step 0, whatever its physical scale: ``L_rec`` of images in [0, 1] and
    ``L_contrast`` of a PSF differ by three orders of magnitude, and without
    this the larger one decides the selection alone.
    """
    return training_loss({t: v for t, v in terms.items() if t != "total"}, weights, scales=scales)[0]


# ---------------------------------------------------------------------------
# Trainer
# ---------------------------------------------------------------------------

class E2ETrainer(E2EEvaluation):
    """Joint training of a selection module and a :class:`~arraysel.e2e.recon.Reconstructor`.

    Parameters
    ----------
    selection : selection module (see the module docstring), e.g. :class:`HardSTESelection`.
    kernel_fn : ``weights (Ne,) -> kappa (n, n) complex``, differentiable.
    kernel_ref : ``(n, n)`` complex reference kernel (all elements active).
    train_images : ``(N, 1, H, W)`` float tensor in ``[0, 1]`` (or ``(images, labels)``).
    psf_terms_fn : ``kappa -> {'L_PSF', 'L_contrast', 'L_SLR' (or 'L_SLR_q', 'L_SLR_i')}``;
        needed when any of those weights is non-zero.
    config : :class:`TrainConfig` or a mapping of its fields (the loss weights among them).
    reconstructor : default ``Reconstructor(n_layers, base_channels=base_channels)``,
        initialised from ``config.seed`` (the global RNG is left untouched).
    scene_fn : ``(images, generator) -> (I_s, I_ref)``; default
        ``SceneMaker(n=image_size, mode='image')`` (see :class:`arraysel.e2e.data.SceneMaker`).
    image_size : side of the scenes (default: the kernel's); the data terms use
        :func:`fit_kernel` of the kernel when it differs.
    checkpoint_path : file for checkpoints (``None``: no checkpoints).
    device : where the models and batches live (``'cpu'``, ``'cuda'``, ...).

    Randomness comes from one ``torch.Generator`` (on the CPU) seeded with
    ``config.seed``: data order, selection sampling, scene generation and
    noise. A checkpoint stores it, so a resumed run continues identically.
    """

    def __init__(self, selection: nn.Module, kernel_fn: KernelFn, kernel_ref: torch.Tensor,
                 train_images: Any, *, psf_terms_fn: Callable[[torch.Tensor], Mapping[str, torch.Tensor]] | None = None,
                 config: TrainConfig | Mapping[str, Any] | None = None,
                 reconstructor: nn.Module | None = None, n_layers: int = 8, base_channels: int = 32,
                 scene_fn: Callable | None = None, checkpoint_path: str | os.PathLike | None = None,
                 device: str | torch.device = "cpu", image_size: int | None = None):
        self.device = torch.device(device)
        self.config = config if isinstance(config, TrainConfig) else TrainConfig(**(config or {}))
        if any(self.weights[t] > 0 for t in PSF_WEIGHT_KEYS) and psf_terms_fn is None:
            raise ParameterError("psf_terms_fn is required while any of the weights L_PSF, L_contrast, "
                                 "L_SLR is non-zero (set them to 0 to train without PSF terms)")
        self.psf_terms_fn = psf_terms_fn
        self.kernel_fn = kernel_fn
        kernel_ref = torch.as_tensor(kernel_ref)
        if kernel_ref.ndim != 2 or kernel_ref.shape[0] != kernel_ref.shape[1]:
            raise ParameterError(f"kernel_ref must be (n, n), got {tuple(kernel_ref.shape)}")
        self.kernel_ref = kernel_ref.to(self.device)
        self.n = kernel_ref.shape[-1]
        self.image_size = self.n if image_size is None else check_number("image_size", image_size,
                                                                         lo=1, integer=True)
        self.images = as_images(train_images)
        self.selection = selection.to(self.device)
        if reconstructor is None:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(self.config.seed)
                reconstructor = Reconstructor(n_layers, base_channels=base_channels)
            if self.config.reblur:
                reconstructor.init_magnitude_base()
        self.reconstructor = reconstructor.to(self.device)
        self.scene_fn = scene_fn if scene_fn is not None else SceneMaker(n=self.image_size, mode="image")
        self.checkpoint_path = Path(checkpoint_path) if checkpoint_path is not None else None
        self.generator = torch.Generator().manual_seed(self.config.seed)
        self.optimizer = torch.optim.Adam(self._param_groups())
        self.step = 0
        self.history: list[dict[str, float]] = []
        self._perm: torch.Tensor | None = None
        self._pos = 0
        self.term_scales: dict[str, float] = {}
        self._ref_op: ConvolutionOperator | None = None
        self.warm_best: tuple[float, list[int]] | None = None
        if self.config.warm_start_margin > 0 and self.config.psf_warmup > 0 and (
                not hasattr(self.selection, "logits") or getattr(self.selection, "sample", True)):
            raise ParameterError("warm_start_margin > 0 needs a selection module with logits drawn "
                                 "by arg-max (HardSTESelection(..., sample=False))")

    @property
    def weights(self) -> Mapping[str, float]:
        """The loss weights, ``config.weights`` (the scene's names)."""
        return self.config.weights

    # -- set-up helpers -----------------------------------------------------
    def _param_groups(self) -> list[dict]:
        c, r = self.config, self.reconstructor
        groups = [{"params": list(self.selection.parameters()), "lr": c.lr_mask, "name": "mask"}]
        if hasattr(r, "ista") and hasattr(r, "head"):
            groups.append({"params": list(r.ista.parameters()), "lr": c.lr_ista, "name": "ista"})
            groups.append({"params": list(r.head.parameters()), "lr": c.lr_head, "name": "head"})
        else:  # a custom reconstructor without the two parts: everything at the head rate
            groups.append({"params": list(r.parameters()), "lr": c.lr_head, "name": "head"})
        return groups

    @property
    def steps_per_epoch(self) -> int:
        return max(1, len(self.images) // self.config.batch_size)

    @property
    def total_steps(self) -> int:
        c = self.config
        return c.max_steps if c.max_steps is not None else c.epochs * self.steps_per_epoch

    def tau(self, step: int | None = None) -> float:
        c = self.config
        return tau_schedule(self.step if step is None else step, c.tau_start, c.tau_end, c.tau_steps)

    def _next_batch(self) -> torch.Tensor:
        n, bs = len(self.images), self.config.batch_size
        if n <= bs:
            self._perm = torch.randperm(n, generator=self.generator)
            return self.images[self._perm]
        if self._perm is None or self._pos + bs > n:
            self._perm = torch.randperm(n, generator=self.generator)
            self._pos = 0
        idx = self._perm[self._pos:self._pos + bs]
        self._pos += bs
        return self.images[idx]

    def _noise(self, y: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        s = self.config.noise_std
        if s == 0:
            return y
        real = torch.float64 if y.dtype == torch.complex128 else torch.float32
        nz = torch.complex(torch.randn(y.shape, generator=generator, dtype=real),
                           torch.randn(y.shape, generator=generator, dtype=real))
        return y + (s / math.sqrt(2)) * nz.to(y.device)

    def _kernel(self, weights: torch.Tensor) -> torch.Tensor:
        kappa = self.kernel_fn(weights)
        if not isinstance(kappa, torch.Tensor) or kappa.shape != self.kernel_ref.shape:
            shape = tuple(kappa.shape) if isinstance(kappa, torch.Tensor) else type(kappa).__name__
            raise ParameterError(f"kernel_fn returned {shape}; expected {tuple(self.kernel_ref.shape)}")
        return kappa

    def operator(self, kappa: torch.Tensor) -> ConvolutionOperator:
        """The forward model of a kernel on the scene grid: :func:`decimate_kernel` by
        ``kernel_stride``, then circular (:func:`fit_kernel` to ``image_size``) or linear."""
        kappa = decimate_kernel(kappa, self.config.kernel_stride)
        if self.config.convolution == "linear":
            return LinearConvolutionOperator(kappa, self.image_size)
        return ConvolutionOperator(fit_kernel(kappa, self.image_size))

    def reference_operator(self) -> ConvolutionOperator:
        """:meth:`operator` of the reference kernel (cached)."""
        if self._ref_op is None:
            self._ref_op = self.operator(self.kernel_ref)
        return self._ref_op

    def scenes(self, images: torch.Tensor, generator: torch.Generator
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(I_s, I_ref)`` of a batch: the scene maker's, or with ``target='envelope'``
        the full array's envelope image as the target (see :class:`TrainConfig`)."""
        i_s, i_ref = self.scene_fn(images.to(self.device), generator)
        if self.config.target == "envelope":
            with torch.no_grad():
                env = self.reference_operator().A(i_s).abs()
                s = env.flatten(1).amax(1).clamp_min(torch.finfo(env.dtype).tiny)
                s = s.view(-1, *([1] * (env.dim() - 1)))
            i_s, i_ref = i_s / s.to(i_s.dtype), env / s
        return i_s, i_ref

    def reconstruct(self, model: nn.Module, y: torch.Tensor, op: ConvolutionOperator) -> torch.Tensor:
        """``model(y, op)``, with ``reblur=`` the reference operator when ``config.reblur``."""
        if self.config.reblur:
            return model(y, op, reblur=self.reference_operator())
        return model(y, op)

    @torch.no_grad()
    def calibrate_balance(self) -> dict[str, float]:
        """Set :attr:`term_scales` for ``balance='initial'``: the mean of each of
        :data:`BALANCED_TERMS` over ``balance_batches`` batches drawn with a
        generator seeded ``config.seed + 2`` (the training stream is untouched),
        the selection at the starting temperature. Returns the scales."""
        gen = torch.Generator().manual_seed(self.config.seed + 2)
        n, bs = len(self.images), self.config.batch_size
        acc: dict[str, float] = {}
        was = self.selection.training, self.reconstructor.training
        self.selection.train()
        self.reconstructor.eval()
        try:
            for _ in range(self.config.balance_batches):
                idx = torch.randperm(n, generator=gen)[:bs]
                terms = self.loss_terms(self.images[idx], self.tau(0), gen)
                for t in BALANCED_TERMS:
                    if t in terms:
                        acc[t] = acc.get(t, 0.0) + float(terms[t]) / self.config.balance_batches
        finally:
            self.selection.train(was[0])
            self.reconstructor.train(was[1])
        tiny = 1e-12
        self.term_scales = {t: max(v, tiny) for t, v in acc.items()}
        return dict(self.term_scales)

    # -- loss ---------------------------------------------------------------
    def loss_terms(self, images: torch.Tensor, tau: float, generator: torch.Generator | None = None,
                   *, psf_only: bool = False) -> dict[str, torch.Tensor]:
        """All non-zero-weight terms (the scene's names) and their weighted sum ``'total'``
        (:func:`arraysel.objective.losses.training_loss`, balanced with ``balance='initial'``)
        for one batch; ``psf_only``: without the data terms (the PSF-only warm-up)."""
        gen = self.generator if generator is None else generator
        w = dict(self.weights)
        if psf_only:
            w.update({t: 0.0 for t in DATA_WEIGHT_KEYS})
        if not any(w.values()):
            raise ParameterError("every loss weight is 0: nothing to train")
        i_s, i_ref = self.scenes(images, gen)
        P, p_soft = self.selection(tau, gen)
        kappa = self._kernel(P.sum(1))
        terms: dict[str, torch.Tensor] = {}
        if any(w[t] > 0 for t in PSF_WEIGHT_KEYS):
            got = dict(self.psf_terms_fn(kappa))
            if "L_SLR" not in got and "L_SLR_q" in got and "L_SLR_i" in got:
                got["L_SLR"] = (got["L_SLR_q"] + got["L_SLR_i"]) / 2
            for t in PSF_WEIGHT_KEYS:
                if w[t] > 0:
                    if t not in got:
                        raise ParameterError(f"psf_terms_fn returned keys {sorted(got)}; "
                                             f"'{t}' is needed (weight {w[t]})")
                    terms[t] = got[t]
        if w["L_conv"] > 0 or w["L_rec"] > 0:
            op = self.operator(kappa)
            y_c = op.A(i_s)
            if w["L_conv"] > 0:
                terms["L_conv"] = l_conv(y_c, self.reference_operator().A(i_s),
                                         reduction=self.config.conv_reduction)
            if w["L_rec"] > 0:
                i_hat = self.reconstruct(self.reconstructor, self._noise(y_c, gen), op)
                terms["L_rec"] = l_rec(i_hat, i_ref.to(i_hat.dtype))
        total, terms = training_loss(terms, w, P_soft=p_soft, scales=self.term_scales)
        terms["total"] = total
        return terms

    # -- training -----------------------------------------------------------
    @torch.no_grad()
    def _warm_start(self, indices: list[int]) -> None:
        """Logits = ``warm_start_margin`` on ``indices[j]`` in column ``j``, 0 elsewhere; the
        mask's Adam state is reset (its moments belong to the old logits)."""
        logits = self.selection.logits
        logits.zero_()
        for j, e in enumerate(sorted(indices)):
            logits[e, j] = self.config.warm_start_margin
        self.optimizer.state.pop(logits, None)
        log.info("step %d: warm start from the best PSF-only selection (score %.4g): %s",
                 self.step, self.warm_best[0], sorted(indices))

    def _set_mask_lr(self, lr: float) -> None:
        for g in self.optimizer.param_groups:
            if g.get("name") == "mask":
                g["lr"] = lr

    def train_step(self) -> dict[str, float]:
        """One optimisation step on the next batch; returns the loss terms as floats."""
        self.selection.train()
        self.reconstructor.train()
        tau = self.tau()
        warm = self.step < self.config.psf_warmup
        self._set_mask_lr(self.config.lr_mask if warm or self.config.joint_lr_mask is None
                          else self.config.joint_lr_mask)
        # the PSF-only phase: the data terms are switched off for this step
        terms = self.loss_terms(self._next_batch(), tau, psf_only=warm)
        total = terms["total"]
        if not torch.isfinite(total):
            raise NumericalError(f"step {self.step}: loss is {float(total)} "
                                 f"({ {k: float(v) for k, v in terms.items()} })")
        if warm and self.config.warm_start_margin > 0:
            psf = {t: terms[t].detach() for t in PSF_WEIGHT_KEYS if t in terms}
            score = float(training_loss(psf, self.weights, scales=self.term_scales)[0])
            if self.warm_best is None or score < self.warm_best[0]:
                self.warm_best = (score, self.selection.indices(tau).tolist())
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        if self.config.grad_clip is not None:
            params = [p for g in self.optimizer.param_groups for p in g["params"]]
            torch.nn.utils.clip_grad_norm_(params, self.config.grad_clip)
        self.optimizer.step()
        self.step += 1
        if warm and self.step == self.config.psf_warmup and self.warm_best is not None:
            self._warm_start(self.warm_best[1])
        rec = {k: float(v.detach()) for k, v in terms.items()}
        rec["tau"] = tau
        self.history.append(rec)
        return rec

    def train(self, max_steps: int | None = None, *, resume: bool = False) -> list[dict[str, float]]:
        """Train until ``max_steps`` steps in all (default ``total_steps``).

        With ``resume=True`` the checkpoint at ``checkpoint_path``, if present,
        is loaded first (step, models, optimiser, RNG and data order) and
        training goes on from its step. Returns the history (one dict of loss
        terms per step, since step 0).
        """
        if resume:
            if self.checkpoint_path is None:
                raise ParameterError("resume=True needs a checkpoint_path")
            if self.checkpoint_path.is_file():
                self.load_checkpoint(self.checkpoint_path)
                log.info("resumed from %s at step %d", self.checkpoint_path, self.step)
            else:
                log.info("no checkpoint at %s: starting from step 0", self.checkpoint_path)
        target = self.total_steps if max_steps is None else check_number("max_steps", max_steps,
                                                                         lo=0, integer=True)
        if self.config.balance == "initial" and not self.term_scales and self.step < target:
            self.calibrate_balance()
        every = self.config.checkpoint_every
        bar = tqdm(total=target, initial=min(self.step, target), desc="e2e",
                   disable=None if self.config.progress else True, dynamic_ncols=True)  # a terminal only
        try:
            while self.step < target:
                rec = self.train_step()
                bar.update(1)
                bar.set_postfix({k: f"{v:.3g}" for k, v in rec.items()}, refresh=False)
                if self.checkpoint_path is not None and every and self.step % every == 0:
                    self.save_checkpoint()
        finally:
            bar.close()
        if self.checkpoint_path is not None:
            self.save_checkpoint()
        return self.history

    # -- checkpoints --------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {
            "format": CHECKPOINT_FORMAT,
            "step": self.step,
            "selection": self.selection.state_dict(),
            "reconstructor": self.reconstructor.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "perm": self._perm,
            "pos": self._pos,
            "history": self.history,
            "config": dataclasses.asdict(self.config),
            "weights": dict(self.weights),
            "term_scales": dict(self.term_scales),
            "warm_best": None if self.warm_best is None else [self.warm_best[0], list(self.warm_best[1])],
        }

    def save_checkpoint(self, path: str | os.PathLike | None = None) -> Path:
        """Write a checkpoint atomically (temporary file in the same folder, then ``os.replace``)."""
        path = Path(path) if path is not None else self.checkpoint_path
        if path is None:
            raise ParameterError("no checkpoint path given")
        path.parent.mkdir(parents=True, exist_ok=True)
        with AtomicFile(path) as fh:  # arraysel.io.atomic: the one writer (mode from the umask)
            torch.save(self.state_dict(), fh.fh)
            fh.fh.flush()
            os.fsync(fh.fh.fileno())
            fh.commit()
        return path

    def load_checkpoint(self, path: str | os.PathLike | None = None) -> None:
        """Restore a checkpoint written by :meth:`save_checkpoint` (``torch.load(weights_only=True)``)."""
        path = Path(path) if path is not None else self.checkpoint_path
        if path is None or not Path(path).is_file():
            raise ParameterError(f"checkpoint {path} not found")
        state = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
            raise ParameterError(f"{path} is not an arraysel end-to-end checkpoint")
        if state["weights"] != dict(self.weights):
            log.warning("checkpoint %s was trained with loss weights %s; now %s", path,
                        state["weights"], dict(self.weights))
        self.selection.load_state_dict(state["selection"])
        self.reconstructor.load_state_dict(state["reconstructor"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        self._perm = state["perm"]
        self._pos = int(state["pos"])
        self.step = int(state["step"])
        self.history = list(state["history"])
        self.term_scales = {str(k): float(v) for k, v in state.get("term_scales", {}).items()}
        wb = state.get("warm_best")
        self.warm_best = None if wb is None else (float(wb[0]), [int(i) for i in wb[1]])



def train_e2e(selection: nn.Module, kernel_fn: KernelFn, kernel_ref: torch.Tensor, train_images: Any,
              *, max_steps: int | None = None, resume: bool = False, **kwargs: Any) -> E2ETrainer:
    """Build an :class:`E2ETrainer` (``kwargs`` as its constructor's) and train it; returns the trainer."""
    trainer = E2ETrainer(selection, kernel_fn, kernel_ref, train_images, **kwargs)
    trainer.train(max_steps, resume=resume)
    return trainer
