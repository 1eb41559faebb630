"""Settings of end-to-end training, one set: loss weights and optimisation (defaults: the paper's, the
scene schema's ``[training]`` section and :data:`arraysel.objective.losses.DEFAULT_WEIGHTS`,
their homes)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

from arraysel.errors import check_choice, check_number
from arraysel.objective.losses import check_weights
from arraysel.scenes.schema import training_default as _T

__all__ = ["TrainConfig"]


@dataclass
class TrainConfig:
    """The training settings (the paper's defaults; the batch size, epochs, learning rates and
    temperature schedule default to the scene schema's ``[training]`` section, their one home).

    ``weights``: the loss weights under the scene's ``[weights]`` names (``L_PSF``, ``L_conv``,
    ``L_rec``, ``L_contrast``, ``L_SLR``, ``L_ent``, ``L_row``); a name left out takes its
    default (:data:`arraysel.objective.losses.DEFAULT_WEIGHTS`), 0 switches a term off. After
    construction it is the complete, checked mapping (:func:`arraysel.objective.losses.check_weights`).

    ``max_steps`` (when set) overrides ``epochs``; an epoch is
    ``N // batch_size`` steps (the last partial batch is dropped, unless the
    data set is smaller than one batch). Checkpoints are written every
    ``checkpoint_every`` steps (0: only at the end) when a checkpoint path is
    given. ``noise_std`` adds complex Gaussian noise of that standard
    deviation to the measurements fed to the reconstructor (not to
    ``L_conv``).

    Forward model and target (defaults: the paper's circular model on the
    kernel's own grid, ``I_ref`` from the scene maker):

    * ``convolution``: ``'circular'`` (:class:`~arraysel.e2e.recon.ConvolutionOperator`
      on the kernel :func:`fit_kernel` to the scene size) or ``'linear'``
      (:class:`~arraysel.e2e.recon.LinearConvolutionOperator`: the whole
      kernel, the scene zero outside its field, nothing wraps around).
    * ``kernel_stride`` (1 to 16): the data terms use :func:`decimate_kernel` of the
      kernel (one scene pixel = ``kernel_stride`` PSF pixels); the PSF terms
      always see the full-resolution kernel.
    * ``target``: ``'scene'`` (the scene maker's ``I_ref``) or ``'envelope'``:
      ``I_ref = |kappa_ref (*) I_s| / s`` and ``I_s / s`` with ``s`` the
      per-image maximum of ``|kappa_ref (*) I_s|``, i.e. the full array's
      envelope image of the same scatterers, in [0, 1].
    * ``balance``: ``'none'`` (the weights as they are) or ``'initial'``:
      each of :data:`BALANCED_TERMS` is divided by its mean over
      ``balance_batches`` batches at the start of training (fixed
      afterwards, stored in checkpoints), :func:`balanced_total`.
    * ``reblur``: the reconstructor's head sees its ISTA estimate imaged with
      the reference kernel (``Reconstructor(..., reblur=op_ref)``), the
      natural output stage for ``target='envelope'``.
    * ``psf_warmup``: the first ``psf_warmup`` steps train the selection on
      the PSF terms alone (``L_conv``, ``L_rec`` off, the reconstructor
      untouched): the mask starts the joint phase from a PSF-only optimum
      instead of a random draw. ``joint_lr_mask`` (default ``lr_mask``) is
      the mask's learning rate after it: a lower one keeps the data terms'
      noisy gradient from pulling the selection away from it (drift).
      ``warm_start_margin > 0`` (needs a selection module with ``logits``
      drawn by arg-max, ``sample=False``): during the warm-up the trainer
      keeps the selection with the lowest weighted (balanced) PSF terms seen
      so far (the arg-max draw of a step is the deterministic selection, so
      this costs nothing), and at the end of the warm-up sets the logits to
      that selection, ``margin`` on its element in each column and 0
      elsewhere: the joint phase starts from the PSF-only optimum, and a
      selection change then needs a logit change of about ``margin``.
    """

    batch_size: int = _T("batch_size")
    epochs: int = _T("epochs")
    max_steps: int | None = None
    lr_mask: float = _T("lr_mask")
    lr_ista: float = _T("lr_ista")
    lr_head: float = _T("lr_head")
    tau_start: float = _T("tau_start")
    tau_end: float = _T("tau_end")
    tau_steps: int = _T("tau_steps")
    seed: int = 0
    checkpoint_every: int = 500
    noise_std: float = 0.0
    conv_reduction: str = "mean"
    grad_clip: float | None = None
    progress: bool = True
    convolution: str = "circular"
    kernel_stride: int = 1
    target: str = "scene"
    balance: str = "none"
    balance_batches: int = 4
    reblur: bool = False
    psf_warmup: int = 0
    joint_lr_mask: float | None = None
    warm_start_margin: float = 0.0
    weights: Mapping[str, float] | None = None

    def __post_init__(self) -> None:
        self.weights = check_weights(self.weights, name="weights")
        check_number("batch_size", self.batch_size, lo=1, integer=True)
        check_number("epochs", self.epochs, lo=0, integer=True)
        if self.max_steps is not None:
            check_number("max_steps", self.max_steps, lo=0, integer=True)
        for name in ("lr_mask", "lr_ista", "lr_head", "noise_std"):
            check_number(name, getattr(self, name), lo=0)
        check_number("tau_start", self.tau_start, lo=0, lo_open=True)
        check_number("tau_end", self.tau_end, lo=0, lo_open=True)
        check_number("tau_steps", self.tau_steps, lo=0, integer=True)
        check_number("checkpoint_every", self.checkpoint_every, lo=0, integer=True)
        check_number("seed", self.seed, integer=True)
        check_choice("conv_reduction", self.conv_reduction, ("mean", "sum"))
        check_choice("convolution", self.convolution, ("circular", "linear"))
        check_number("kernel_stride", self.kernel_stride, lo=1, hi=16, integer=True)
        check_choice("target", self.target, ("scene", "envelope"))
        check_choice("balance", self.balance, ("none", "initial"))
        check_number("balance_batches", self.balance_batches, lo=1, integer=True)
        check_number("psf_warmup", self.psf_warmup, lo=0, integer=True)
        check_number("warm_start_margin", self.warm_start_margin, lo=0)
        if self.joint_lr_mask is not None:
            check_number("joint_lr_mask", self.joint_lr_mask, lo=0)
        if self.grad_clip is not None:
            check_number("grad_clip", self.grad_clip, lo=0, lo_open=True)
