"""Settings of end-to-end training, one set: loss weights and optimisation (defaults: the paper's, the
scene schema's ``[training]`` section and :data:`arraysel.objective.losses.DEFAULT_WEIGHTS`,
their homes): the trainer's (:class:`TrainConfig`) and a run's (:class:`E2ESettings`, which holds
the trainer's; :func:`resolve_settings` reads them from a scene, the profile and overrides)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping

from arraysel.errors import ParameterError, check_choice, check_number
from arraysel.objective.losses import LOSS_KEYS, check_weights
from arraysel.scenes.schema import Scene
from arraysel.scenes.schema import training_default as _T

__all__ = ["TrainConfig", "E2ESettings", "resolve_settings", "setting_names", "QUICK_PROFILE"]


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


#: the :class:`TrainConfig` fields the pipeline sets itself, not settings: why, for the error
_PIPELINE_SETS = {"max_steps": "give 'steps' (the run's step count is derived from it)",
                  "weights": "the scene's [weights] section sets the loss weights",
                  "checkpoint_every": "the pipeline checkpoints at every progress line",
                  "progress": "the pipeline reports through log="}
#: the trainer's settings every ``settings.json`` records (``steps``: ``TrainConfig.max_steps``);
#: another :class:`TrainConfig` field is recorded when it differs from its default
_RECORDED_TRAIN_KEYS = ("batch_size", "epochs", "steps", "lr_mask", "lr_ista", "lr_head", "tau_start",
                        "tau_end", "tau_steps", "seed", "convolution", "kernel_stride", "target",
                        "noise_std", "balance", "reblur", "psf_warmup", "joint_lr_mask",
                        "warm_start_margin")


@dataclass
class E2ESettings:
    """Everything a training run depends on besides the scene's physics: ``train``, the trainer's
    settings (:class:`arraysel.e2e.config.TrainConfig`, the one home of the batch size, epochs,
    learning rates, temperature schedule, seed, data model, balance and warm-up, their defaults
    and their docs), and the pipeline's own settings below.

    ``train.max_steps`` is the run's ``steps`` (when set it overrides ``epochs``) and
    ``train.weights`` the scene's ``[weights]`` (:func:`resolve_settings`); the pipeline trains
    with a copy whose ``max_steps`` and ``tau_steps`` are the resolved counts, ``psf_warmup`` at
    most two thirds of the run and no progress bar.

    ``scatterers``: ``'points'``
    (genscat-like speckle, ``scatterers_per_pixel`` on average, placed in
    ``[depth_min, depth_max]``) or ``'image'`` (the image itself).
    ``n_train`` / ``n_test``: keep only that many images (``None``: all).
    ``finetune_steps`` (per selection, before the reconstruction metrics)
    defaults to ``finetune_epochs`` epochs, or 100 steps when that is 0.
    ``sample_selection``: the HARD-STE columns are sampled from ``p_j`` in
    training (``True``, the documented default) or taken as their arg-max
    (``False``, like the ``ste`` selector's default ``draw='argmax'``: less
    noisy, the quick profile's choice). ``random_phase``: each point scatterer gets a uniform random phase
    (:class:`arraysel.e2e.data.SceneMaker`). ``recon_steps > 0`` changes the
    evaluation protocol: instead of fine-tuning copies of the jointly trained
    reconstructor, every selection (the learned one included) gets a fresh
    reconstructor (same initialisation) trained ``recon_steps`` steps on the
    same batches, so the selections are compared under the same
    reconstruction budget. ``reblur_mode`` (``'image'`` or ``'correct'``): what
    the head sees with ``train.reblur``, :class:`arraysel.e2e.recon.Reconstructor`'s
    option of that name. ``head_init``: ``'magnitude'`` (the head's base
    starts as ``|z|``, the residual branch with ``eta = 0.1``; the full
    profile's) or ``'identity'`` (also ``eta = 0``: ``I_hat = |z|`` exactly at
    step 0; the quick profile's). Both apply to the jointly trained
    reconstructor and to every selection's own alike.
    """

    profile: str = "quick"
    dataset: str = "mnist"
    source: str = "auto"
    image_size: int = 128
    depth_min: float = 0.0
    depth_max: float = 0.15
    scatterers: str = "points"
    scatterers_per_pixel: float = 1.25
    ista_layers: int = _T("ista_layers")
    base_channels: int = 32
    finetune_steps: int | None = None
    finetune_epochs: int = _T("finetune_epochs")
    n_train: int | None = None
    n_test: int | None = None
    random_phase: bool = False
    recon_steps: int = 0
    sample_selection: bool = True
    reblur_mode: str = "image"
    head_init: str = "magnitude"
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        if isinstance(self.train, Mapping):
            self.train = TrainConfig(**self.train)
        elif not isinstance(self.train, TrainConfig):
            raise ParameterError(f"train must be a TrainConfig or a mapping of its fields, "
                                 f"got {type(self.train).__name__}")
        check_choice("profile", self.profile, ("quick", "full"))
        check_choice("dataset", self.dataset, ("mnist", "fashion"))
        check_choice("source", self.source, ("auto", "sample", "idx"))
        check_choice("scatterers", self.scatterers, ("points", "image"))
        check_number("image_size", self.image_size, lo=8, hi=4096, integer=True)
        check_number("depth_min", self.depth_min, lo=0)
        if not self.depth_max > self.depth_min:
            raise ParameterError(f"depth_max ({self.depth_max}) must be > depth_min ({self.depth_min})")
        check_number("scatterers_per_pixel", self.scatterers_per_pixel, lo=0, lo_open=True)
        if self.finetune_steps is not None:
            check_number("finetune_steps", self.finetune_steps, lo=0, integer=True)
        check_number("finetune_epochs", self.finetune_epochs, lo=0, integer=True)
        check_number("ista_layers", self.ista_layers, lo=1, integer=True)
        check_number("base_channels", self.base_channels, lo=1, integer=True)
        for name in ("n_train", "n_test"):
            if getattr(self, name) is not None:
                check_number(name, getattr(self, name), lo=1, integer=True)
        check_number("seed", self.train.seed, lo=0, integer=True)  # also the baselines' numpy seed
        check_choice("reblur_mode", self.reblur_mode, ("image", "correct"))
        check_choice("head_init", self.head_init, ("magnitude", "identity"))
        check_number("recon_steps", self.recon_steps, lo=0, integer=True)


def setting_names() -> list[str]:
    """The names :func:`resolve_settings` (``run_training(**overrides)``) takes: the pipeline's
    :class:`E2ESettings` fields, ``steps`` and the :class:`TrainConfig` fields the pipeline does
    not set itself (they go to ``train``)."""
    own = [f.name for f in dataclasses.fields(E2ESettings) if f.name != "train"]
    trainer = ["steps"] + [f.name for f in dataclasses.fields(TrainConfig) if f.name not in _PIPELINE_SETS]
    return sorted(own + trainer)


#: the quick (CPU) profile's values; see :mod:`arraysel.e2e.pipeline`
QUICK_PROFILE = dict(image_size=64, kernel_stride=2, convolution="linear", target="envelope",
                     scatterers="points", random_phase=True, noise_std=0.01, balance="initial",
                     reblur=True, batch_size=8, steps=450, psf_warmup=300, tau_steps=300,
                     base_channels=8, ista_layers=5, source="sample", lr_mask=3e-3,
                     joint_lr_mask=1e-4, lr_ista=5e-3, lr_head=1e-3, finetune_steps=25,
                     recon_steps=120, sample_selection=False, warm_start_margin=2.0,
                     reblur_mode="correct", head_init="identity")


def resolve_settings(scene: Scene, *, full: bool = False, **overrides: Any) -> E2ESettings:
    """The run's settings: the scene's ``[data]``/``[training]``, then the quick
    profile unless ``full``, then ``overrides`` (``None`` values are ignored), one flat namespace
    (:func:`setting_names`): a :class:`TrainConfig` field goes to ``train`` (``steps`` to
    ``train.max_steps``), the scene's ``[weights]`` to ``train.weights``."""
    d, t = scene.section("data"), scene.section("training")
    base: dict[str, Any] = {"profile": "full" if full else "quick"}
    for key in ("dataset", "source", "image_size", "depth_min", "depth_max"):
        if key in d:
            base[key] = d[key]
    for key in ("epochs", "batch_size", "lr_mask", "lr_ista", "lr_head", "tau_start", "tau_end",
                "tau_steps", "ista_layers"):
        if key in t:
            base[key] = t[key]
    if t.get("steps"):
        base["steps"] = t["steps"]
    if "finetune_epochs" in t:
        base["finetune_epochs"] = t["finetune_epochs"]
    if not full:
        base.update(QUICK_PROFILE)
    names = setting_names()
    for key, value in overrides.items():
        if key in _PIPELINE_SETS:
            raise ParameterError(f"training setting {key!r} is not taken here: {_PIPELINE_SETS[key]}")
        if key not in names:
            raise ParameterError(f"unknown training setting {key!r}; allowed: {names}")
        if value is not None:
            base[key] = value
            if key == "epochs" and overrides.get("steps") is None:
                base["steps"] = None  # an explicit --epochs beats the profile's step count
            if key == "finetune_steps" and overrides.get("recon_steps") is None:
                base["recon_steps"] = 0  # an explicit --finetune-steps asks for that protocol
    if base.get("steps") is not None:
        check_number("steps", base["steps"], lo=0, integer=True)
    train_names = {f.name for f in dataclasses.fields(TrainConfig)}
    train = {key: base.pop(key) for key in list(base) if key in train_names}
    train["max_steps"] = base.pop("steps", None)
    train["weights"] = {name: scene.weights.get(name, 0.0) for name in LOSS_KEYS}
    return E2ESettings(**base, train=TrainConfig(**train))


def _jsonable(settings: E2ESettings) -> dict[str, Any]:
    """``settings.json``'s ``settings``: one flat mapping, the pipeline's fields and the trainer's
    (:data:`_RECORDED_TRAIN_KEYS`, ``steps`` for ``max_steps``; any other :class:`TrainConfig`
    field when it is not its default, so that records of runs that leave it keep their keys and
    ``--resume`` still compares them; the loss weights are the scene's, recorded with it)."""
    out = {f.name: getattr(settings, f.name) for f in dataclasses.fields(E2ESettings) if f.name != "train"}
    for f in dataclasses.fields(TrainConfig):
        key = "steps" if f.name == "max_steps" else f.name
        if f.name in _PIPELINE_SETS and key != "steps":
            continue
        value = getattr(settings.train, f.name)
        if key in _RECORDED_TRAIN_KEYS or value != f.default:
            out[key] = value
    return out
