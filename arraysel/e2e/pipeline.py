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
from typing import Any, Callable

import numpy as np
import torch

# the run's settings live with the trainer's; their names stay importable from here
from arraysel.e2e.config import QUICK_PROFILE, E2ESettings, _jsonable, resolve_settings, setting_names
from arraysel.errors import ParameterError, SelectionError, check_number
from arraysel.io.atomic import atomic_write_bytes
from arraysel.objective.losses import LOSS_KEYS, PSF_WEIGHT_KEYS
from arraysel.objective.metrics import METRIC_NAMES
from arraysel.objective.psf_objective import build_objective
from arraysel.selection import masks_from_indices
from arraysel.scenes.schema import Scene, load_scene

__all__ = ["E2ESettings", "resolve_settings", "setting_names", "QUICK_PROFILE", "run_training", "baseline_masks", "comparison_rows",
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
    say = log or (lambda _msg: None)
    t_start = time.perf_counter()
    sc = scene if isinstance(scene, Scene) else load_scene(scene)
    if not sc.needs_data:
        raise ParameterError(f"scene {sc.name!r} gives L_conv and L_rec weight 0: there is nothing to "
                             "train end to end (use `arraysel compare` for PSF-only selection, or a "
                             "scene based on 'paper-e2e')")
    settings = resolve_settings(sc, full=full, **overrides)
    ckpt_path = _prepare_folder(out_dir, sc, settings, dtype, resume=resume, force=force)
    objective = build_objective(sc, device=device, dtype=dtype)
    ne, k = objective.n_elements, objective.k
    run = _build_trainer(sc, settings, objective, ckpt_path, device, say)
    trainer = run.trainer
    train_seconds = _train(trainer, run.total, ckpt_path, resume, log_every, say)

    learned = _write_learned(out_dir, trainer, sc.name, ne, k, settings.train.seed)
    masks = _masks(learned, ne, k, settings.train.seed, extra_masks)
    res = objective.evaluate(masks_from_indices(list(masks.values()), ne), return_kernels=True)
    table = [{"config": name, "n_active": len(idx), **{m: float(res[m][i]) for m in METRIC_NAMES},
              "elements": " ".join(map(str, idx))} for i, (name, idx) in enumerate(masks.items())]
    _write_csv(os.path.join(out_dir, "table1.csv"), table)
    t_recon = time.perf_counter()
    recons, ft_steps = _reconstructors(run, settings, masks, say)
    recon_seconds = time.perf_counter() - t_recon
    rec_rows = _reconstruction_rows(run, settings, masks, recons, ft_steps)
    _write_csv(os.path.join(out_dir, "reconstruction.csv"), rec_rows)
    _write_history(out_dir, trainer.history)

    files = ["mask.txt", "mask.json", "table1.csv", "reconstruction.csv", "history.csv",
             "settings.json", "checkpoint.pt"]
    if figures:
        from arraysel.e2e.figures import write_figures

        files += write_figures(out_dir, trainer=trainer, masks=masks, recons=recons,
                               kernels=res["kernels"], kernel_ref=run.kappa_ref.detach().cpu().numpy(),
                               pitch=objective.setup.pitch, n_elements=ne, images=run.x_test,
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


def _prepare_folder(out_dir: str, sc: Scene, settings: E2ESettings, dtype, *, resume: bool, force: bool) -> str:
    """Check ``out_dir`` (and, resuming, the settings of its checkpoint), clear an old run's files
    with ``force``, write ``settings.json``; return the checkpoint's path."""
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
    return ckpt_path


@dataclass
class _Training:
    """What the steps after training need of its set-up."""

    trainer: Any
    fresh_reconstructor: Callable
    kappa_ref: torch.Tensor
    x_test: Any
    total: int
    ft_steps: int


def _build_trainer(sc: Scene, s: E2ESettings, objective, ckpt_path: str, device, say) -> _Training:
    """The physics (kernel and PSF terms of ``objective``), the data, the selection module and the
    trainer of a run, and the line that describes it."""
    from arraysel.e2e.data import SceneMaker, load_dataset
    from arraysel.e2e.recon import Reconstructor
    from arraysel.e2e.trainer import E2ETrainer, HardSTESelection

    ne, k = objective.n_elements, objective.k
    kappa_ref = objective.reference_kernel()
    psf_needed = [n for n in PSF_WEIGHT_KEYS if sc.weights.get(n, 0.0) > 0]

    def kernel_fn(w: torch.Tensor) -> torch.Tensor:
        return objective.psf.kernels(w[None])[0]

    def psf_terms(kappa: torch.Tensor) -> dict[str, torch.Tensor]:
        m = objective.metrics_of_kernels(kappa[None], terms=psf_needed)
        return {n: m[n][0] for n in psf_needed}

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
    return _Training(trainer, fresh_reconstructor, kappa_ref, x_test, total, ft_steps)


def _train(trainer, total: int, ckpt_path: str, resume: bool, log_every: int | None, say) -> float:
    """Train to ``total`` steps (from the checkpoint when resuming), a progress line every
    ``log_every`` steps; return the seconds it took."""
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
    return time.perf_counter() - t_train


def _write_learned(out_dir: str, trainer, scene_name: str, ne: int, k: int, seed: int) -> list[int]:
    """The learned selection, checked, written to ``mask.txt`` and ``mask.json``."""
    learned = [int(i) for i in trainer.learned_indices().tolist()]
    if len(learned) != k or len(set(learned)) != k:
        raise SelectionError(f"the learned selection has {len(set(learned))} distinct elements, not k = {k}")
    _write_text(os.path.join(out_dir, "mask.txt"),
                f"# learned selection of scene {scene_name!r} after {trainer.step} steps "
                f"(0-based element indices, k = {k} of {ne})\n" + ",".join(map(str, learned)) + "\n")
    _write_text(os.path.join(out_dir, "mask.json"),
                json.dumps({"scene": scene_name, "n_elements": ne, "k": k, "elements": learned,
                            "steps": trainer.step, "seed": seed}, indent=2) + "\n")
    return learned


def _masks(learned: list[int], ne: int, k: int, seed: int, extra_masks) -> dict[str, list[int]]:
    """The selections of Table 1: the learned one, the baselines and ``extra_masks`` (checked)."""
    masks = {"learned": learned, **baseline_masks(ne, k, seed)}
    for name, idx in (extra_masks or {}).items():
        if name in masks:
            raise ParameterError(f"extra mask name {name!r} is taken; taken: {sorted(masks)}")
        idx = sorted(int(i) for i in idx)
        if len(idx) != k or len(set(idx)) != k or not all(0 <= i < ne for i in idx):
            raise SelectionError(f"extra mask {name!r} must hold {k} distinct indices in [0, {ne}), "
                                 f"got {idx}")
        masks[name] = idx
    return masks


def _reconstructors(run: _Training, s: E2ESettings, masks: dict, say) -> tuple[dict, int]:
    """One reconstructor a selection, each fine-tuned (or, with ``recon_steps``, trained afresh)
    on the same batches; the trainer's generator and data position are restored afterwards.
    Returns them and the steps each was trained."""
    trainer, ft_steps = run.trainer, run.ft_steps
    snapshot = (trainer.generator.get_state(), trainer._perm, trainer._pos)
    recons = {}
    if s.recon_steps:
        ft_steps = s.recon_steps
        say(f"training a fresh reconstructor for each of {len(masks)} selections "
            f"({s.recon_steps} steps each, same initialisation and batches)")
    for name, idx in masks.items():
        trainer.generator.set_state(snapshot[0])
        trainer._perm, trainer._pos = snapshot[1], snapshot[2]
        if s.recon_steps:
            model = run.fresh_reconstructor()
            trainer.finetune_head(s.recon_steps, mask=idx, reconstructor=model, include_ista=True)
        else:
            model = copy.deepcopy(trainer.reconstructor)
            trainer.finetune_head(ft_steps, mask=idx, reconstructor=model)
        recons[name] = model
    trainer.generator.set_state(snapshot[0])
    trainer._perm, trainer._pos = snapshot[1], snapshot[2]
    return recons, ft_steps


def _reconstruction_rows(run: _Training, s: E2ESettings, masks: dict, recons: dict, ft_steps: int) -> list[dict]:
    """MSE / PSNR / SSIM of each selection's reconstruction and of its blurred measurement."""
    ev = run.trainer.evaluate(run.x_test, {k_: v for k_, v in masks.items() if k_ != "learned"},
                              reconstructors=recons, blurred=True, batch_size=min(64, len(run.x_test)))
    return [{"config": name, "n_active": len(masks[name]), "finetune_steps": ft_steps,
             **{key: ev[name][key] for key in ("mse", "psnr", "ssim", "mse_blurred",
                                               "psnr_blurred", "ssim_blurred")}}
            for name in masks]


def _write_history(out_dir: str, history: list[dict]) -> None:
    hist_keys = list(dict.fromkeys(key for h in history for key in h))
    _write_csv(os.path.join(out_dir, "history.csv"),
               [{"step": i + 1, **{key: h.get(key, math.nan) for key in hist_keys}}
                for i, h in enumerate(history)] or [{"step": 0}])
