"""Hostile cases, output targets: every command refuses, before any work, outputs that are not
regular files (a device, a FIFO, a folder), outputs that are one of its inputs or each other
(by path, symbolic link or hard link), and ``train`` a folder holding a training; the atomic
writers refuse to replace a non-regular file as a last guard.

Each case asserts the exit code (2), one message line naming the option, and that nothing was
replaced (the device is still a device, the input keeps its bytes).
"""
from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from arraysel.cli.main import main
from arraysel.errors import ParameterError
from arraysel.io import atomic

AS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0
TOY_MASK = " ".join(map(str, range(0, 64, 2))) + "\n"


def _device(path: Path) -> Path:
    """A character device at ``path``: a null device made with mknod (root), else a symbolic link
    to /dev/null (which a user other than root cannot replace anyway)."""
    if AS_ROOT:
        os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    else:
        os.symlink("/dev/null", path)
    return path


def _is_device(path: Path) -> bool:
    return stat.S_ISCHR(os.stat(path).st_mode)


def _refused(capsys, argv, option: str) -> str:
    """Run ``arraysel ARGV`` (in this process), assert it is refused in one line naming ``option``."""
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"arraysel {argv[0]}: error:"), err
    assert option in lines[0], lines[0]
    return lines[0]


@pytest.fixture(autouse=True)
def no_heavy_work(monkeypatch):
    """A refusal must come before any objective is built or any training starts."""
    from arraysel.cli import compare as cmp
    from arraysel.e2e import pipeline
    from arraysel.objective import psf_objective

    def fail(*_a, **_k):
        raise AssertionError("heavy work started before the outputs were checked")

    monkeypatch.setattr(cmp, "build_objective", fail)
    monkeypatch.setattr(psf_objective, "build_objective", fail)
    monkeypatch.setattr(pipeline, "build_objective", fail)
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")


@pytest.fixture
def masks(tmp_path) -> Path:
    m = tmp_path / "m.txt"
    m.write_text(TOY_MASK)
    return m


# ------------------------------------------------------------------ devices, FIFOs, folders
def _fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


def _folder(path: Path) -> Path:
    path.mkdir()
    return path


MAKE = {"device": _device, "fifo": _fifo, "folder": _folder}
IS = {"device": stat.S_ISCHR, "fifo": stat.S_ISFIFO, "folder": stat.S_ISDIR}
WORD = {"device": "character device", "fifo": "FIFO", "folder": "folder"}


@pytest.mark.parametrize("kind", ["device", "fifo", "folder"])
@pytest.mark.parametrize("command", ["psf --out", "psf --plot", "evaluate --out", "evaluate --psf-out"])
def test_non_regular_file_targets_are_refused(tmp_path, capsys, masks, kind, command):
    name, option = command.split()
    if option == "--plot":  # the PNG written next to --out is the target
        target = MAKE[kind](tmp_path / "k.png")
        argv = ["psf", "--out", str(tmp_path / "k.npz"), "--plot"]
    else:
        target = MAKE[kind](tmp_path / ("t.npz" if option != "--out" or name == "psf" else "t.csv"))
        if name == "psf":
            argv = ["psf", "--out", str(target)]
        elif option == "--out":
            argv = ["evaluate", "--scene", "toy", "--masks", str(masks), "--out", str(target)]
        else:
            argv = ["evaluate", "--scene", "paper", "--masks", str(masks), "--out", str(tmp_path / "o.csv"),
                    "--psf-out", str(target)]
    line = _refused(capsys, argv, option)
    assert WORD[kind] in line
    assert IS[kind](os.stat(target).st_mode)
    assert not (tmp_path / "o.csv").exists() and not (tmp_path / "k.npz").exists()


def test_dev_null_itself_is_refused_and_kept(capsys, masks):
    """``--out /dev/null`` (the system's): refused before anything is written; a user other than
    root could not replace it anyway, root would have (the case this guards)."""
    before = os.stat("/dev/null")
    _refused(capsys, ["evaluate", "--scene", "toy", "--masks", str(masks), "--out", "/dev/null"], "--out")
    after = os.stat("/dev/null")
    assert stat.S_ISCHR(after.st_mode) and (after.st_ino, after.st_rdev) == (before.st_ino, before.st_rdev)


@pytest.mark.parametrize("kind", ["device", "fifo", "file"])
def test_compare_and_train_refuse_non_regular_targets_in_their_folder(tmp_path, capsys, kind):
    folder = tmp_path / "out"
    folder.mkdir()
    if kind == "device":
        _device(folder / "table1.csv")
    elif kind == "fifo":
        _fifo(folder / "table1.csv")
    else:  # a file where the folder should be
        folder.rmdir()
        folder.write_text("my file\n")
    line = _refused(capsys, ["compare", "--selectors", "uniform", "--scene", "toy", "--out", str(folder),
                             "--no-figures", "--no-progress", "--budget-evals", "2"], "--out")
    assert ("table1.csv" in line) if kind != "file" else ("not a folder" in line)
    line = _refused(capsys, ["train", "--out", str(folder), "--steps", "1"], "--out")
    assert ("table1.csv" in line) if kind != "file" else ("not a folder" in line)
    if kind == "file":
        assert folder.read_text() == "my file\n"
    else:
        assert not stat.S_ISREG(os.stat(folder / "table1.csv").st_mode)


def test_compare_and_train_refuse_a_device_as_their_folder(tmp_path, capsys):
    dev = _device(tmp_path / "dev")
    _refused(capsys, ["compare", "--selectors", "uniform", "--scene", "toy", "--out", str(dev),
                      "--budget-evals", "2"], "--out")
    _refused(capsys, ["train", "--out", str(dev)], "--out")
    assert _is_device(dev)


# ------------------------------------------------------------------ outputs that are inputs
def _alias(kind: str, target: Path, where: Path) -> Path:
    if kind == "same":
        return target
    if kind == "relative":
        return Path(os.path.relpath(target))
    if kind == "symlink":
        os.symlink(target, where / "link.csv")
        return where / "link.csv"
    if kind == "hardlink":
        os.link(target, where / "hard.csv")
        return where / "hard.csv"
    if kind == "folder-link":  # the same file through a linked folder
        os.symlink(target.parent, where / "alias")
        return where / "alias" / target.name
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["same", "relative", "symlink", "hardlink", "folder-link"])
def test_evaluate_out_that_is_the_masks_file_is_refused(tmp_path, capsys, masks, kind, monkeypatch):
    monkeypatch.chdir(tmp_path)
    other = tmp_path / "elsewhere"
    other.mkdir()
    out = _alias(kind, masks, other)
    line = _refused(capsys, ["evaluate", "--scene", "toy", "--masks", str(masks), "--out", str(out)], "--out")
    assert "--masks" in line and "must not replace an input" in line
    assert masks.read_text() == TOY_MASK


@pytest.mark.parametrize("kind", ["same", "symlink", "hardlink", "folder-link"])
def test_evaluate_out_and_psf_out_the_same_file_is_refused(tmp_path, capsys, masks, kind):
    kernels = tmp_path / "x.npz"
    kernels.write_bytes(b"kernels of an earlier run")
    other = tmp_path / "elsewhere"
    other.mkdir()
    out = _alias(kind, kernels, other)
    line = _refused(capsys, ["evaluate", "--scene", "paper", "--masks", str(masks), "--out", str(out),
                             "--psf-out", str(kernels)], "--psf-out")
    assert "same file as --out" in line
    assert kernels.read_bytes() == b"kernels of an earlier run"


def test_scene_file_among_the_outputs_is_refused(tmp_path, capsys):
    """``psf --plot`` writes <out>.png: a scene file of that name is an input it would replace."""
    scene = tmp_path / "k.png"
    scene.write_text('base = "paper"\n')
    line = _refused(capsys, ["psf", "--scene", str(scene), "--out", str(tmp_path / "k.npz"), "--plot"], "--plot")
    assert "--scene" in line and scene.read_text() == 'base = "paper"\n'


def test_compare_plugin_file_among_its_results_is_refused(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    plugin = out / "runs.csv"
    plugin.write_text("# my plugin, oddly named\n")
    line = _refused(capsys, ["compare", "--selectors", "uniform", "--scene", "toy", "--out", str(out),
                             "--plugin", str(plugin), "--budget-evals", "2"], "--out (runs.csv)")
    assert "--plugin" in line and plugin.read_text() == "# my plugin, oddly named\n"


# ------------------------------------------------------------------ train into a finished folder
def _finished_training(folder: Path) -> dict:
    folder.mkdir(exist_ok=True)
    files = {"checkpoint.pt": b"\x80\x02 a week of training", "mask.txt": b"0,2,4\n", "mask.json": b"{}",
             "table1.csv": b"config,Mean\n", "settings.json": b"{}"}
    for name, data in files.items():
        (folder / name).write_bytes(data)
    return files


def _unchanged(folder: Path, files: dict) -> bool:
    return all((folder / n).read_bytes() == d for n, d in files.items())


def test_train_refuses_a_folder_holding_a_training(tmp_path, capsys):
    folder = tmp_path / "run"
    files = _finished_training(folder)
    line = _refused(capsys, ["train", "--out", str(folder), "--steps", "2"], "--out")
    assert "already holds a training" in line and "--resume" in line and "--force" in line
    _refused(capsys, ["train", "--out", str(folder), "--resume", "--force"], "--resume and --force")
    (folder / "checkpoint.pt").unlink()
    del files["checkpoint.pt"]
    line = _refused(capsys, ["train", "--out", str(folder), "--resume"], "--resume")
    assert "no checkpoint.pt" in line
    assert _unchanged(folder, files)


def test_train_api_refuses_a_folder_holding_a_training(tmp_path):
    from arraysel.e2e.pipeline import run_training

    folder = tmp_path / "run"
    files = _finished_training(folder)
    with pytest.raises(ParameterError, match="already holds a training"):
        run_training("paper-e2e", out_dir=str(folder), steps=1, log=None)
    assert _unchanged(folder, files)


# ------------------------------------------------------------------ the writers' own guard
@pytest.mark.parametrize("kind", ["device", "fifo", "folder"])
def test_atomic_writers_never_replace_a_non_regular_file(tmp_path, kind):
    target = MAKE[kind](tmp_path / "t.bin")
    with pytest.raises((ParameterError, IsADirectoryError), match="not a regular file|directory"):
        atomic.atomic_write_bytes(target, b"data")
    with pytest.raises((ParameterError, IsADirectoryError)):
        with atomic.StreamingNpz(target) as npz:
            npz.add("a", [1, 2, 3])
            npz.commit()
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]
    assert IS[kind](os.stat(target).st_mode)


def test_a_target_made_a_fifo_while_being_written_is_not_replaced(tmp_path):
    target = tmp_path / "rows.csv"
    with atomic.AtomicFile(target) as f:
        f.write(b"a,b\n")
        os.mkfifo(target)                    # someone puts a FIFO there meanwhile
        with pytest.raises(ParameterError, match="FIFO"):
            f.commit()
    assert stat.S_ISFIFO(os.stat(target).st_mode)
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


def test_a_symlink_target_is_replaced_not_followed(tmp_path):
    """The documented contract for links: the writer replaces the link with the new file, and the
    file it pointed to keeps its content."""
    real = tmp_path / "real.csv"
    real.write_text("old\n")
    link = tmp_path / "link.csv"
    os.symlink(real, link)
    atomic.atomic_write_text(link, "new\n")
    assert not link.is_symlink() and link.read_text() == "new\n" and real.read_text() == "old\n"


def test_train_force_replaces_the_old_training(tmp_path, monkeypatch):
    """``force`` removes the old run's files (and only those) before training again."""
    from arraysel.e2e import pipeline

    monkeypatch.undo()  # this one trains for real (two steps of a 16-element scene)
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    folder = tmp_path / "run"
    files = _finished_training(folder)
    (folder / "my_notes.txt").write_text("kept\n")
    scene = {"base": "paper-e2e", "name": "tiny-e2e", "probe": {"n_elements": 16}, "selection": {"k": 8},
             "grid": {"n_x": 64, "n_z": 64, "window": 32}, "simulator": {"fast_margin": 4}}
    kw = dict(out_dir=str(folder), steps=2, batch_size=2, image_size=16, base_channels=4, finetune_steps=0,
              n_test=2, figures=False, log=None, ista_layers=2, recon_steps=0)
    res = pipeline.run_training(scene, force=True, **kw)
    assert res["steps"] == 2 and (folder / "my_notes.txt").read_text() == "kept\n"
    assert (folder / "checkpoint.pt").read_bytes() != files["checkpoint.pt"]
    assert [int(v) for v in (folder / "mask.txt").read_text().splitlines()[-1].split(",")] == res["learned"]
    with pytest.raises(ParameterError, match="already holds a training"):
        pipeline.run_training(scene, **kw)
