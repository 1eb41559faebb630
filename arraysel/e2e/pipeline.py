"""End-to-end training on a scene: the library side of ``arraysel train``.

:func:`run_training` builds the scene's PSF objective, turns images of the
scene's data set into scatterer maps, trains a HARD-STE selection jointly
with the unrolled-ISTA reconstructor (:class:`arraysel.e2e.trainer.E2ETrainer`),
and writes to ``out_dir``:

* ``mask.txt`` (the learned selection, 0-based indices, one line, readable by
  ``arraysel evaluate --masks``) and ``mask.json``;
* ``table1.csv``: Table-1 metrics (:meth:`arraysel.objective.psf_objective.Objective.evaluate`)
  of the learned, uniform, random and full selections;
* ``reconstruction.csv``: MSE / PSNR / SSIM on held-out images for the same
  selections, each with a copy of the trained reconstructor whose head is
  fine-tuned for ``finetune_steps`` steps on that selection, and the same
  metrics of the blurred measurement ``|Y|`` (``*_blurred`` columns);
* ``comparison.csv`` (also printed): per selection Table-1 ``Mean``,
  ``L_PSF``, PSNR / SSIM of the reconstruction and of ``|Y|``, and whether
  the learned selection beats it on Mean, PSNR and SSIM;
* ``history.csv`` (loss terms per step), ``settings.json`` (everything the
  run depends on), ``checkpoint.pt`` (resumable);
* figures (PNG): ``fig_mask.png``, ``fig_psf.png`` (learned and reference PSF
  in dB, 40 dB range, lateral and axial profiles), ``fig_images.png`` (ground
  truth, blurred, reconstructions), ``fig_loss.png``.

Two profiles. ``full=True`` takes the scene's ``[data]`` and ``[training]``
sections as they are (the paper: 128 x 128 images, batch 64, 100 epochs).
The default *quick* profile (:data:`QUICK_PROFILE`) is sized for a CPU: 64 x 64 images, batch 8,
300 PSF-only warm-up steps then 150 joint ones, head widths 8/16/32, the bundled data sample, the
temperature decay over the warm-up, and learning rates raised (mask 3e-3, 1e-4 after the
warm-up; ISTA 5e-3, head 1e-3) so the selection moves within a few hundred steps. Any value can
be overridden (``overrides=``, or the command's flags). The settings are one set
(:class:`E2ESettings`): the trainer's are its ``train``, a :class:`arraysel.e2e.config.TrainConfig`.

Files are written atomically. Nothing here is imported by the PSF objective:
the ``paper`` scene builds no network and loads no data set.
"""
from __future__ import annotations

import copy
import csv
import dataclasses
import io
import json
import math
import os
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np
import torch

from arraysel.e2e.config import TrainConfig
from arraysel.errors import ParameterError, SelectionError, check_choice, check_number
from arraysel.io.atomic import atomic_write_bytes
from arraysel.objective.losses import LOSS_KEYS, PSF_WEIGHT_KEYS
from arraysel.objective.metrics import METRIC_NAMES
from arraysel.objective.psf_objective import build_objective
from arraysel.selection import masks_from_indices
from arraysel.scenes.schema import Scene, load_scene
from arraysel.scenes.schema import training_default as _T

__all__ = ["E2ESettings", "resolve_settings", "setting_names", "run_training", "baseline_masks", "comparison_rows",
           "format_comparison", "OUTPUT_FILES", "HELD_FILES", "check_out_folder"]

#: the files a finished run leaves in its output folder
OUTPUT_FILES = ("mask.txt", "mask.json", "table1.csv", "reconstruction.csv", "comparison.csv",
                "history.csv",
                "settings.json", "checkpoint.pt", "fig_mask.png", "fig_psf.png", "fig_images.png",
                "fig_loss.png")

#: files that show a folder holds a training (refused without resume or force)
HELD_FILES = ("checkpoint.pt", "mask.txt", "mask.json", "table1.csv", "comparison.csv")


def check_out_folder(out_dir: str, *, resume: bool = False, force: bool = False) -> None:
    """Refuse, before any work, an output folder that cannot take a training's files (a file in its
    place, an output that is a device, FIFO or folder) or that holds a training (:data:`HELD_FILES`)
    without ``resume`` (needs its ``checkpoint.pt``) or ``force``."""
    from arraysel.io.outputs import check_outputs, check_result_folder, folder_files

    check_outputs(folder_files("--out", out_dir, OUTPUT_FILES), folders=[("--out", out_dir)])
    check_result_folder(out_dir, "--out", held=HELD_FILES, what="a training", resume=resume, force=force,
                        resume_needs="checkpoint.pt")


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


#: the quick (CPU) profile's values; see the module docstring
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


def baseline_masks(n_elements: int, k: int, seed: int = 0) -> dict[str, list[int]]:
    """The paper's baselines (``docs/paper-scene.md``): ``uniform`` (``i * Ne // k``: every second element for
    k = Ne/2), ``random`` (one random k-subset from ``seed``), ``full`` (all)."""
    rng = np.random.default_rng(seed)
    return {"uniform": [i * n_elements // k for i in range(k)],
            "random": sorted(int(i) for i in rng.choice(n_elements, size=k, replace=False)),
            "full": list(range(n_elements))}


# ---------------------------------------------------------------------------
# output helpers
# ---------------------------------------------------------------------------

def _write_text(path: str, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def _write_csv(path: str, rows: list[dict[str, Any]]) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: (f"{v:.8g}" if isinstance(v, float) else v) for k, v in r.items()})
    _write_text(path, buf.getvalue())


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


def comparison_rows(table: list[dict[str, Any]], rec_rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per selection: Table-1 ``Mean`` and ``L_PSF``, held-out PSNR / SSIM of the
    reconstruction and of the blurred measurement, and whether the learned selection beats
    it on all three of Mean, PSNR and SSIM (``learned_wins``; empty on the learned row)."""
    t1 = {r["config"]: r for r in table}
    rec = {r["config"]: r for r in rec_rows}
    le = (t1["learned"]["Mean"], rec["learned"]["psnr"], rec["learned"]["ssim"])
    rows = []
    for name in rec:
        mean, ps, ss = t1[name]["Mean"], rec[name]["psnr"], rec[name]["ssim"]
        wins = "" if name == "learned" else ("yes" if le[0] < mean and le[1] > ps and le[2] > ss else "no")
        rows.append({"config": name, "Mean": float(mean), "L_PSF": float(t1[name]["L_PSF"]),
                     "psnr": float(ps), "ssim": float(ss), "psnr_blurred": float(rec[name]["psnr_blurred"]),
                     "ssim_blurred": float(rec[name]["ssim_blurred"]), "learned_wins": wins})
    return rows


def format_comparison(rows: list[dict[str, Any]]) -> list[str]:
    """The comparison as printed lines (a fixed-width table)."""
    out = [f"{'selection':>12s} {'Mean':>8s} {'L_PSF':>8s} {'PSNR dB':>8s} {'SSIM':>6s} "
           f"{'|Y| PSNR':>9s} {'|Y| SSIM':>9s}  learned better on all three"]
    for r in rows:
        out.append(f"{r['config']:>12s} {r['Mean']:8.4f} {r['L_PSF']:8.4f} {r['psnr']:8.2f} "
                   f"{r['ssim']:6.3f} {r['psnr_blurred']:9.2f} {r['ssim_blurred']:9.3f}  {r['learned_wins']}")
    return out


# ---------------------------------------------------------------------------
# the run
# ---------------------------------------------------------------------------

def _print(msg: str) -> None:
    print(msg, flush=True)


def run_training(scene: Scene | str | dict = "paper-e2e", *, out_dir: str = "results/train",
                 full: bool = False, device: str = "cpu", dtype: torch.dtype = torch.float32,
                 resume: bool = False, force: bool = False, figures: bool = True,
                 log: Callable[[str], None] | None = _print,
                 log_every: int | None = None, threads: int | None = None,
                 extra_masks: dict[str, list[int]] | None = None, **overrides: Any) -> dict[str, Any]:
    """Train an end-to-end selection on ``scene`` and write the outputs to ``out_dir``.

    ``overrides``: any setting :func:`resolve_settings` takes (:func:`setting_names`: ``dataset``,
    ``epochs``, ``steps``, ``seed``, ``image_size``, ...; ``None`` means "not given").
    With ``resume=True`` a checkpoint in ``out_dir`` written with the same
    settings is continued (a different setting raises ``ParameterError``).
    A folder that already holds a training (:data:`HELD_FILES`: a checkpoint,
    a learned mask or its tables) is refused unless ``resume`` or ``force``
    (which replaces it: its old output files are removed first), as
    ``arraysel compare`` does with its folder.
    ``threads``: torch intra-op threads for the run (restored afterwards);
    default 1 for the quick profile on a CPU (its tensors are small, and
    thread synchronisation then costs more than it gains: about 10x on a
    busy 2-core machine), torch's own setting otherwise.
    ``extra_masks``: more selections (name -> k indices) scored and
    reconstructed like the baselines (e.g. the ``ste`` selector's result).
    ``log`` receives the progress lines (``None``: silent). Returns a
    summary: ``learned`` (indices), ``table1`` and ``reconstruction`` (lists
    of row dicts), ``steps``, ``seconds``, ``files``.
    """
    if threads is None and not full and torch.device(device).type == "cpu":
        threads = 1
    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(check_number("threads", threads, lo=1, integer=True))
    try:
        return _run(scene, out_dir=out_dir, full=full, device=device, dtype=dtype, resume=resume,
                    force=force, figures=figures, log=log, log_every=log_every, extra_masks=extra_masks,
                    overrides=overrides)
    finally:
        torch.set_num_threads(old_threads)


def _run(scene, *, out_dir, full, device, dtype, resume, force, figures, log, log_every, extra_masks,
         overrides):
    from arraysel.e2e.data import SceneMaker, load_dataset
    from arraysel.e2e.recon import Reconstructor
    from arraysel.e2e.trainer import E2ETrainer, HardSTESelection

    say = log or (lambda _msg: None)
    t_start = time.perf_counter()
    sc = scene if isinstance(scene, Scene) else load_scene(scene)
    if not sc.needs_data:
        raise ParameterError(f"scene {sc.name!r} gives L_conv and L_rec weight 0: there is nothing to "
                             "train end to end (use `arraysel compare` for PSF-only selection, or a "
                             "scene based on 'paper-e2e')")
    settings = resolve_settings(sc, full=full, **overrides)
    check_out_folder(out_dir, resume=resume, force=force)
    if force:
        for name in OUTPUT_FILES:  # the old run's files, nothing else
            try:
                os.unlink(os.path.join(out_dir, name))
            except FileNotFoundError:
                pass
    os.makedirs(out_dir, exist_ok=True)
    ckpt_path = os.path.join(out_dir, "checkpoint.pt")
    record = {"scene": sc.to_dict(), "settings": _jsonable(settings), "dtype": str(dtype)}
    settings_path = os.path.join(out_dir, "settings.json")
    if resume and os.path.isfile(ckpt_path) and os.path.isfile(settings_path):
        with open(settings_path) as fh:
            old = json.load(fh)
        diff = sorted(k for k in set(old.get("settings", {})) | set(record["settings"])
                      if old.get("settings", {}).get(k) != record["settings"].get(k))
        if old.get("scene") != record["scene"]:
            diff.insert(0, "scene")
        if diff:
            raise ParameterError(f"--resume: the checkpoint in {out_dir} was written with other settings "
                                 f"({', '.join(diff)}); rerun with the same options or without --resume")
    _write_text(settings_path, json.dumps(record, indent=2, default=str) + "\n")

    # physics ------------------------------------------------------------------
    objective = build_objective(sc, device=device, dtype=dtype)
    ne, k = objective.n_elements, objective.k
    kappa_ref = objective.reference_kernel()
    wts = sc.weights
    psf_needed = [n for n in PSF_WEIGHT_KEYS if wts.get(n, 0.0) > 0]

    def kernel_fn(w: torch.Tensor) -> torch.Tensor:
        return objective.psf.kernels(w[None])[0]

    def psf_terms(kappa: torch.Tensor) -> dict[str, torch.Tensor]:
        m = objective.metrics_of_kernels(kappa[None], terms=psf_needed)
        return {n: m[n][0] for n in psf_needed}

    # data ---------------------------------------------------------------------
    s = settings
    x_train, _ = load_dataset(s.dataset, "train", source=s.source, limit=s.n_train)
    x_test, _ = load_dataset(s.dataset, "test", source=s.source, limit=s.n_test)
    n = s.image_size
    scene_fn = SceneMaker(n=n, mode=s.scatterers, depth_range=(s.depth_min, s.depth_max),
                          n_scatterers=max(1, round(s.scatterers_per_pixel * n * n)),
                          random_phase=s.random_phase)
    tc = s.train
    steps_per_epoch = max(1, len(x_train) // tc.batch_size)
    total = tc.max_steps if tc.max_steps is not None else tc.epochs * steps_per_epoch
    # the PSF-only warm-up takes at most two thirds of the run (a short run still trains jointly)
    psf_warmup = min(tc.psf_warmup, 2 * total // 3)
    tau_steps = min(tc.tau_steps, psf_warmup) if psf_warmup else tc.tau_steps
    ft_steps = s.finetune_steps
    if ft_steps is None:
        ft_steps = s.finetune_epochs * steps_per_epoch or 100
    config = dataclasses.replace(tc, max_steps=total, tau_steps=tau_steps, psf_warmup=psf_warmup,
                                 warm_start_margin=tc.warm_start_margin if psf_warmup else 0.0,
                                 checkpoint_every=0, progress=False)
    selection = HardSTESelection(ne, k, generator=torch.Generator().manual_seed(tc.seed),
                                 sample=s.sample_selection)

    def fresh_reconstructor() -> Reconstructor:
        # the same initialisation for the jointly trained model and every selection's own
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(tc.seed)
            model = Reconstructor(s.ista_layers, base_channels=s.base_channels,
                                  reblur_mode=s.reblur_mode)
        if s.head_init == "identity":
            model.init_identity_head()
        elif tc.reblur:
            model.init_magnitude_base()
        return model

    trainer = E2ETrainer(selection, kernel_fn, kappa_ref, x_train, psf_terms_fn=psf_terms,
                         config=config, n_layers=s.ista_layers,
                         reconstructor=fresh_reconstructor(),
                         base_channels=s.base_channels, scene_fn=scene_fn, checkpoint_path=ckpt_path,
                         device=device, image_size=n)
    pix = objective.setup.pitch * tc.kernel_stride
    say(f"arraysel train: scene {sc.name!r} ({s.profile} profile), Ne = {ne}, k = {k}, "
        f"{s.dataset} ({len(x_train)} train / {len(x_test)} test images, {n}x{n} px of "
        f"{pix * 1e6:.1f} um = {n * pix * 1e3:.2f} mm, {s.scatterers}, {tc.convolution} convolution, "
        f"target {tc.target}, noise {tc.noise_std:g}, balance {tc.balance}), "
        f"batch {tc.batch_size}, {total} steps, device {device}")

    # training -----------------------------------------------------------------
    if resume and os.path.isfile(ckpt_path):
        trainer.load_checkpoint(ckpt_path)
        say(f"resumed from {ckpt_path} at step {trainer.step}")
    elif os.path.isfile(ckpt_path):
        say(f"starting from step 0 (an existing {ckpt_path} is overwritten; use --resume to continue it)")
    every = log_every or max(1, min(500, total // 25))
    t_train = time.perf_counter()
    step0 = trainer.step
    while trainer.step < total:
        stop = min(total, (trainer.step // every + 1) * every)
        trainer.train(stop)  # saves the checkpoint at ``stop``
        rec = trainer.history[-1]
        rate = (time.perf_counter() - t_train) / max(1, trainer.step - step0)
        terms = " ".join(f"{key}={rec[key]:.4g}" for key in ("total", *LOSS_KEYS)
                         if key in rec)
        say(f"step {trainer.step:>6d}/{total}  tau={rec['tau']:.3f}  {terms}  ({rate:.2f} s/step)")
    train_seconds = time.perf_counter() - t_train

    # the learned selection ----------------------------------------------------
    learned = [int(i) for i in trainer.learned_indices().tolist()]
    if len(learned) != k or len(set(learned)) != k:
        raise SelectionError(f"the learned selection has {len(set(learned))} distinct elements, not k = {k}")
    _write_text(os.path.join(out_dir, "mask.txt"),
                f"# learned selection of scene {sc.name!r} after {trainer.step} steps "
                f"(0-based element indices, k = {k} of {ne})\n" + ",".join(map(str, learned)) + "\n")
    _write_text(os.path.join(out_dir, "mask.json"),
                json.dumps({"scene": sc.name, "n_elements": ne, "k": k, "elements": learned,
                            "steps": trainer.step, "seed": tc.seed}, indent=2) + "\n")

    # Table 1 ------------------------------------------------------------------
    masks = {"learned": learned, **baseline_masks(ne, k, tc.seed)}
    for name, idx in (extra_masks or {}).items():
        if name in masks:
            raise ParameterError(f"extra mask name {name!r} is taken; taken: {sorted(masks)}")
        idx = sorted(int(i) for i in idx)
        if len(idx) != k or len(set(idx)) != k or not all(0 <= i < ne for i in idx):
            raise SelectionError(f"extra mask {name!r} must hold {k} distinct indices in [0, {ne}), "
                                 f"got {idx}")
        masks[name] = idx
    res = objective.evaluate(masks_from_indices(list(masks.values()), ne), return_kernels=True)
    table = [{"config": name, "n_active": len(idx), **{m: float(res[m][i]) for m in METRIC_NAMES},
              "elements": " ".join(map(str, idx))} for i, (name, idx) in enumerate(masks.items())]
    _write_csv(os.path.join(out_dir, "table1.csv"), table)

    # reconstruction: one fine-tuned copy of the head per selection, same batches for each
    snapshot = (trainer.generator.get_state(), trainer._perm, trainer._pos)
    recons = {}
    t_recon = time.perf_counter()
    if s.recon_steps:
        ft_steps = s.recon_steps
        say(f"training a fresh reconstructor for each of {len(masks)} selections "
            f"({s.recon_steps} steps each, same initialisation and batches)")
    for name, idx in masks.items():
        trainer.generator.set_state(snapshot[0])
        trainer._perm, trainer._pos = snapshot[1], snapshot[2]
        if s.recon_steps:
            model = fresh_reconstructor()
            trainer.finetune_head(s.recon_steps, mask=idx, reconstructor=model, include_ista=True)
        else:
            model = copy.deepcopy(trainer.reconstructor)
            trainer.finetune_head(ft_steps, mask=idx, reconstructor=model)
        recons[name] = model
    recon_seconds = time.perf_counter() - t_recon
    trainer.generator.set_state(snapshot[0])
    trainer._perm, trainer._pos = snapshot[1], snapshot[2]
    ev = trainer.evaluate(x_test, {k_: v for k_, v in masks.items() if k_ != "learned"},
                          reconstructors=recons, blurred=True, batch_size=min(64, len(x_test)))
    rec_rows = [{"config": name, "n_active": len(masks[name]), "finetune_steps": ft_steps,
                 **{key: ev[name][key] for key in ("mse", "psnr", "ssim", "mse_blurred",
                                                   "psnr_blurred", "ssim_blurred")}}
                for name in masks]
    _write_csv(os.path.join(out_dir, "reconstruction.csv"), rec_rows)
    hist_keys = list(dict.fromkeys(key for h in trainer.history for key in h))
    _write_csv(os.path.join(out_dir, "history.csv"),
               [{"step": i + 1, **{key: h.get(key, math.nan) for key in hist_keys}}
                for i, h in enumerate(trainer.history)] or [{"step": 0}])

    files = ["mask.txt", "mask.json", "table1.csv", "reconstruction.csv", "history.csv",
             "settings.json", "checkpoint.pt"]
    if figures:
        from arraysel.e2e.figures import write_figures

        files += write_figures(out_dir, trainer=trainer, masks=masks, recons=recons,
                               kernels=res["kernels"], kernel_ref=kappa_ref.detach().cpu().numpy(),
                               pitch=objective.setup.pitch, n_elements=ne, images=x_test,
                               table=table, reconstruction=rec_rows)
    comparison = comparison_rows(table, rec_rows)
    _write_csv(os.path.join(out_dir, "comparison.csv"), comparison)
    files.insert(4, "comparison.csv")
    seconds = time.perf_counter() - t_start
    for line in format_comparison(comparison):
        say(line)
    say(f"learned elements: {','.join(map(str, learned))}")
    say(f"done in {seconds:.0f} s (training {train_seconds:.0f} s, reconstructors "
        f"{recon_seconds:.0f} s); wrote {out_dir}/: {', '.join(files)}")
    return {"learned": learned, "table1": table, "reconstruction": rec_rows, "steps": trainer.step,
            "seconds": seconds, "train_seconds": train_seconds, "recon_seconds": recon_seconds,
            "files": files,
            "settings": settings, "history": trainer.history}
