"""End-to-end training on a physics scene (arraysel.e2e.pipeline, `arraysel train`), on a tiny scene."""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys

import pytest
import torch

from arraysel.cli.main import main as cli_main
from arraysel.scenes.schema import load_scene

TINY = {"base": "paper-e2e", "name": "tiny-e2e",
        "probe": {"n_elements": 16}, "selection": {"k": 8},
        "grid": {"n_x": 64, "n_z": 64, "window": 32}, "simulator": {"fast_margin": 4}}
TINY_TOML = """base = "paper-e2e"
name = "tiny-e2e"
[probe]
n_elements = 16
[selection]
k = 8
[grid]
n_x = 64
n_z = 64
window = 32
[simulator]
fast_margin = 4
"""
NE, K = 16, 8


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def tiny():
    from arraysel.objective.psf_objective import build_objective

    scene = load_scene(TINY)
    return scene, build_objective(scene)


def make_trainer(objective, images, image_size=16, **cfg):
    from arraysel.e2e.data import SceneMaker
    from arraysel.e2e.trainer import E2ETrainer, HardSTESelection

    def kernel_fn(w):
        return objective.psf.kernels(w[None])[0]

    def psf_terms(kappa):
        return {"L_PSF": objective.metrics_of_kernels(kappa[None], terms=["L_PSF"])["L_PSF"][0]}

    config = dict(batch_size=4, max_steps=1, progress=False, seed=0, checkpoint_every=0,
                  weights=dict(L_contrast=0, L_SLR=0))
    config.update(cfg)
    return E2ETrainer(HardSTESelection(NE, K, generator=torch.Generator().manual_seed(0)), kernel_fn,
                      objective.reference_kernel(), images, psf_terms_fn=psf_terms,
                      config=config, n_layers=2, base_channels=4,
                      scene_fn=SceneMaker(n=image_size, mode="image"), image_size=image_size)


@pytest.fixture(scope="module")
def images():
    from arraysel.e2e.data import load_dataset

    return load_dataset("mnist", "train", source="sample", limit=8)[0]


def test_gradients_reach_selection_logits_through_the_simulator(tiny, images):
    _, obj = tiny
    t = make_trainer(obj, images)
    terms = t.loss_terms(images[:4], tau=3.0)
    terms["total"].backward()
    g = t.selection.logits.grad
    assert g is not None and torch.isfinite(g).all() and float(g.abs().sum()) > 0
    # the physics part alone (L_PSF through the PSF model) also reaches the logits
    t.selection.logits.grad = None
    t.loss_terms(images[:4], tau=3.0)["L_PSF"].backward()
    assert float(t.selection.logits.grad.abs().sum()) > 0


def test_one_step_decreases_the_loss_on_a_fixed_batch(tiny, images):
    _, obj = tiny
    t = make_trainer(obj, images, lr_mask=1e-3, lr_ista=1e-3, lr_head=1e-3)
    batch = images[:4]
    t.selection.eval()  # deterministic selection: the same P before and after the step

    def loss():
        return t.loss_terms(batch, tau=1.2, generator=torch.Generator().manual_seed(0))["total"]

    before = loss()
    t.optimizer.zero_grad()
    before.backward()
    t.optimizer.step()
    with torch.no_grad():
        after = loss()
    assert float(after) < float(before.detach())


def test_learned_selection_has_k_distinct_elements(tiny, images):
    _, obj = tiny
    t = make_trainer(obj, images, max_steps=2)
    t.train()
    idx = t.learned_indices().tolist()
    assert len(idx) == K == len(set(idx)) and all(0 <= i < NE for i in idx)


def test_kernel_is_cropped_to_the_image_size(tiny):
    from arraysel.e2e.trainer import fit_kernel

    _, obj = tiny
    ref = obj.reference_kernel()
    assert ref.shape == (32, 32)
    crop = fit_kernel(ref, 16)
    assert crop.shape == (16, 16) and crop[8, 8] == ref[16, 16]
    pad = fit_kernel(ref, 40)
    assert pad.shape == (40, 40) and pad[20, 20] == ref[16, 16]
    assert torch.isclose(pad.abs().pow(2).sum(), ref.abs().pow(2).sum())


def test_settings_profiles():
    from arraysel.e2e.pipeline import resolve_settings

    scene = load_scene("paper-e2e")
    full = resolve_settings(scene, full=True)
    t = full.train
    assert (full.image_size, t.batch_size, t.epochs, t.max_steps) == (128, 64, 100, None)
    assert (t.lr_mask, t.lr_ista, t.lr_head, t.tau_steps, full.ista_layers) == (1e-4, 5e-4, 1e-4, 1500, 8)
    quick = resolve_settings(scene)
    assert quick.image_size <= 64 and quick.train.max_steps is not None and quick.source == "sample"
    assert resolve_settings(scene, epochs=2).train.max_steps is None
    assert resolve_settings(scene, dataset="fashion", seed=3).dataset == "fashion"


#: the keys of ``settings.json``'s ``settings`` (a resumed run compares them with the old file's)
RECORDED_SETTINGS = {
    "profile", "dataset", "source", "image_size", "depth_min", "depth_max", "scatterers",
    "scatterers_per_pixel", "batch_size", "epochs", "steps", "lr_mask", "lr_ista", "lr_head",
    "tau_start", "tau_end", "tau_steps", "ista_layers", "base_channels", "finetune_steps",
    "finetune_epochs", "n_train", "n_test", "seed", "convolution", "kernel_stride", "target",
    "random_phase", "noise_std", "balance", "reblur", "psf_warmup", "joint_lr_mask", "recon_steps",
    "sample_selection", "warm_start_margin", "reblur_mode", "head_init"}


def test_settings_route_the_trainers_names_to_its_config_and_keep_their_record():
    from arraysel.e2e.pipeline import QUICK_PROFILE, _jsonable, resolve_settings
    from arraysel.errors import ParameterError
    from arraysel.objective.losses import LOSS_KEYS

    scene = load_scene("paper-e2e")
    s = resolve_settings(scene, seed=3, steps=7, noise_std=0.02, image_size=32)
    assert (s.train.seed, s.train.max_steps, s.train.noise_std, s.image_size) == (3, 7, 0.02, 32)
    assert s.train.weights == {key: scene.weights.get(key, 0.0) for key in LOSS_KEYS}  # the scene's
    assert s.train.weights["L_rec"] == scene.weights["L_rec"] > 0
    record = _jsonable(s)
    assert set(record) == RECORDED_SETTINGS  # the keys files of earlier versions hold
    assert (record["steps"], record["seed"], record["kernel_stride"]) == (7, 3, QUICK_PROFILE["kernel_stride"])
    json.dumps(record)
    clipped = _jsonable(resolve_settings(scene, grad_clip=1.0, balance_batches=2))
    assert set(clipped) - RECORDED_SETTINGS == {"grad_clip", "balance_batches"}
    assert resolve_settings(scene, grad_clip=1.0).train.grad_clip == 1.0
    with pytest.raises(ParameterError, match="'steps'"):
        resolve_settings(scene, max_steps=3)
    with pytest.raises(ParameterError, match=r"\[weights\]"):
        resolve_settings(scene, weights={"L_rec": 1.0})
    with pytest.raises(ParameterError, match="unknown training setting 'lr'"):
        resolve_settings(scene, lr=1e-3)
    with pytest.raises(ParameterError, match="steps = -1"):
        resolve_settings(scene, steps=-1)
    with pytest.raises(ParameterError, match="kernel_stride = 17"):
        resolve_settings(scene, kernel_stride=17)
    with pytest.raises(ParameterError, match="seed = -1"):
        resolve_settings(scene, seed=-1)


def test_paper_scene_is_refused():
    from arraysel.e2e.pipeline import run_training
    from arraysel.errors import ParameterError

    with pytest.raises(ParameterError, match="nothing to train"):
        run_training("paper", out_dir="/nonexistent/never-written")


def test_cli_runs_end_to_end_and_resumes(tmp_path, capsys):
    scene_file = tmp_path / "tiny.toml"
    scene_file.write_text(TINY_TOML)
    out = tmp_path / "run"
    argv = ["train", "--scene", str(scene_file), "--steps", "3", "--batch-size", "2",
            "--image-size", "16", "--channels", "4", "--finetune-steps", "1", "--n-test", "4",
            "--out", str(out)]
    assert cli_main(argv) == 0
    printed = capsys.readouterr().out
    assert "step      3/3" in printed and "rec=" in printed and "PSNR" in printed
    from arraysel.e2e.pipeline import OUTPUT_FILES
    for name in OUTPUT_FILES:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert not [p for p in os.listdir(out) if p.endswith(".tmp")]
    sel = [int(v) for v in (out / "mask.txt").read_text().splitlines()[-1].split(",")]
    assert len(sel) == K == len(set(sel))
    assert json.loads((out / "mask.json").read_text())["elements"] == sel
    with open(out / "table1.csv") as fh:
        table = list(csv.DictReader(fh))
    assert [r["config"] for r in table] == ["learned", "uniform", "random", "full"]
    assert float(table[3]["L_PSF"]) < 1e-6
    with open(out / "reconstruction.csv") as fh:
        rec = list(csv.DictReader(fh))
    assert [r["config"] for r in rec] == ["learned", "uniform", "random", "full"]
    for r in rec:
        for key in ("mse", "psnr", "ssim", "psnr_blurred", "ssim_blurred"):
            assert r[key] not in ("", "nan")
    for png in ("fig_mask.png", "fig_psf.png", "fig_images.png", "fig_loss.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # resume: 2 more steps continue from the checkpoint; other settings are refused
    assert cli_main(argv[:4] + ["5"] + argv[5:] + ["--resume", "--no-figures"]) == 2  # steps differ
    assert "other settings" in capsys.readouterr().err


def test_resume_continues_the_checkpoint(tmp_path):
    from arraysel.e2e.pipeline import run_training

    kw = dict(out_dir=str(tmp_path), steps=2, batch_size=2, image_size=16, base_channels=4,
              finetune_steps=0, n_test=2, figures=False, log=None, ista_layers=2)
    first = run_training(load_scene(TINY), **kw)
    again = run_training(load_scene(TINY), resume=True, **kw)
    assert again["steps"] == first["steps"] == 2
    assert again["history"] == first["history"]  # nothing retrained: the checkpoint is complete
    assert again["learned"] == first["learned"]


def test_paper_scene_needs_no_network_and_no_data(paper_objective):
    """Building and evaluating the `paper` objective imports none of the training modules."""
    code = (
        "import sys\n"
        "from arraysel.cli.main import build_parser\n"
        "build_parser()\n"
        "from arraysel.objective.psf_objective import build_objective\n"
        "obj = build_objective('paper')\n"
        "res = obj.evaluate([[1.0, 0.0] * 32])\n"
        "assert res['L_PSF'][0] > 0\n"
        "bad = [m for m in ('arraysel.e2e.recon', 'arraysel.e2e.data', 'arraysel.e2e.trainer', 'arraysel.e2e.pipeline')"
        " if m in sys.modules]\n"
        "print('IMPORTED', bad)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "IMPORTED []" in out.stdout


def test_figure_functions_return_figures_and_leave_the_backend_alone(tmp_path):
    import matplotlib
    from matplotlib.figure import Figure

    from arraysel.e2e import figures

    backend = matplotlib.get_backend()
    masks = {"learned": [0, 2, 5], "uniform": [0, 3, 6], "full": list(range(8))}
    fig = figures.fig_mask(masks, 8)
    assert isinstance(fig, Figure)
    assert fig.axes[0].get_yticklabels()[0].get_text().startswith("learned")
    assert isinstance(figures.fig_loss([{"total": 1.0, "L_PSF": 0.5, "tau": 6.0},
                                        {"total": 0.5, "L_rec": 0.1, "tau": 5.0}]), Figure)
    figures.save_figure(fig, str(tmp_path / "m.png"))
    assert (tmp_path / "m.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert matplotlib.get_backend() == backend
    with open(figures.__file__) as fh:
        assert "matplotlib.use(" not in fh.read()
