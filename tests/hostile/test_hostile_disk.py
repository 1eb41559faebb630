"""Hostile cases, a full disk: during a comparison and during a cache build.

Two ways to run out of room: a small tmpfs filled with ballast (a real "No space left on
device"; needs root to mount, skipped otherwise) and ``RLIMIT_FSIZE`` in a child process (any
file past the limit fails with "File too large"; works for every user).

A comparison that meets a full disk ends with one line naming the file it could not write and
exit code 2, no traceback and no temporary file left; every file it wrote before is whole; once
there is room, ``--resume`` finishes the folder with every run once, with its trace, and the
same numbers as a comparison that never met the full disk. A cache build that cannot save its
entry says so in one warning line and returns the right numbers; the cache keeps no half entry.
"""
from __future__ import annotations

import contextlib
import os
import resource
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pandas as pd
import pytest

from scene_texts import TINY_SCENE
from support import own_plugin_manager, time_limit  # noqa: F401  (autouse fixtures)
from test_hostile_traces import whole

_bounded = time_limit(300)
AS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0
ARGS = ["--selectors", "random,uniform,greedy", "--scene", "toy", "--seeds", "0,1", "--budget-s", "20",
        "--budget-evals", "40", "--no-progress", "--no-figures", "--in-process"]
CLI = "import sys; from arraysel.cli.main import main; sys.exit(main())"
#: runs a command with RLIMIT_FSIZE = argv[1] bytes (argv: LIMIT COMMAND...)
LIMITED = ("import resource, sys; n = int(sys.argv[1]); resource.setrlimit(resource.RLIMIT_FSIZE, (n, n)); "
           "from arraysel.cli.main import main; sys.exit(main(sys.argv[2:]))")


def _cli(*argv, env=None, limit: int | None = None) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-c", CLI, *argv] if limit is None else [sys.executable, "-c", LIMITED, str(limit), *argv]
    return subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, **(env or {})}, timeout=280)


def _leftovers(folder: Path) -> list[str]:
    return [str(p) for p in folder.rglob("*") if p.name.endswith(".tmp")]


@contextlib.contextmanager
def _small_disk(kib: int):
    """A tmpfs of ``kib`` KiB, mounted for the block (skips the test where it cannot be mounted)."""
    if not AS_ROOT or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root")
    where = Path(tempfile.mkdtemp(prefix="arraysel-disk-"))
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={kib}k", "tmpfs", str(where)], capture_output=True,
                          text=True)
    if proc.returncode != 0:
        where.rmdir()
        pytest.skip(f"cannot mount a tmpfs: {proc.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)
        shutil.rmtree(where, ignore_errors=True)


def _fill(disk: Path, leave_kib: int) -> Path:
    """Ballast that leaves about ``leave_kib`` KiB of ``disk`` free."""
    free = shutil.disk_usage(disk).free
    ballast = disk / "ballast"
    with open(ballast, "wb") as fh:
        fh.write(b"\0" * max(0, free - leave_kib * 1024))
    return ballast


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> dict:
    from arraysel.cli.main import main
    from arraysel.selectors import registry

    out = tmp_path_factory.mktemp("ref") / "cmp"
    registry.reset()
    try:
        assert main(["compare", *ARGS, "--out", str(out)]) == 0
    finally:
        registry.reset()
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False)
    return {(c, str(s)): m for c, s, m in zip(runs["config"], runs["seed"], runs["Mean"])}


def _stopped_cleanly(proc, out: Path, why: str) -> None:
    assert proc.returncode == 2, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("arraysel compare: error: ") and f"{out}/" in last and why in last, last
    assert last.endswith("rerun the same command with --resume") and "Traceback" not in proc.stderr
    assert not _leftovers(out)
    if (out / "runs.csv").exists():  # whole, if written at all
        pd.read_csv(out / "runs.csv")


def _resumed_whole(out: Path, reference: dict) -> None:
    proc = _cli("compare", *ARGS, "--out", str(out), "--resume")
    assert proc.returncode == 0, proc.stderr
    whole(out)
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False)
    assert {(c, str(s)): m for c, s, m in zip(runs["config"], runs["seed"], runs["Mean"])} == reference


@pytest.mark.slow
@pytest.mark.parametrize("leave_kib", [8, 24])
def test_a_compare_that_fills_the_disk_stops_in_one_line_and_resumes_whole(reference, leave_kib):
    with _small_disk(512) as disk:
        ballast = _fill(disk, leave_kib)
        out = disk / "cmp"
        proc = _cli("compare", *ARGS, "--out", str(out))
        _stopped_cleanly(proc, out, "No space left on device")
        ballast.unlink()
        _resumed_whole(out, reference)


@pytest.mark.parametrize("limit", [1500, pytest.param(3000, marks=pytest.mark.slow)])
def test_a_compare_past_its_file_size_limit_stops_in_one_line_and_resumes_whole(tmp_path, reference, limit):
    out = tmp_path / "cmp"
    proc = _cli("compare", *ARGS, "--out", str(out), limit=limit)
    _stopped_cleanly(proc, out, "File too large")
    _resumed_whole(out, reference)


# ------------------------------------------------------------------ a cache build
def _tiny_scene(tmp_path: Path) -> tuple[Path, Path]:
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY_SCENE)
    masks = tmp_path / "m.txt"
    masks.write_text("0 2 4 6\n1 3 5 7\n0 1 2 3\n")
    return scene, masks


def _evaluate(tmp_path, cache: str, limit: int | None = None) -> tuple[subprocess.CompletedProcess, str]:
    scene, masks = _tiny_scene(tmp_path)
    out = tmp_path / f"o-{abs(hash((cache, limit)))}.csv"
    proc = _cli("evaluate", "--scene", str(scene), "--masks", str(masks), "--out", str(out), "--no-progress",
                env={"ARRAYSEL_CACHE": cache}, limit=limit)
    return proc, out.read_text() if out.exists() else ""


def _cache_warned_and_clean(proc, cache: Path) -> None:
    assert proc.returncode == 0, proc.stderr
    warned = [line for line in proc.stderr.splitlines() if "could not save" in line]
    assert len(warned) == 1 and "it will be built again next time" in warned[0], proc.stderr
    assert "Traceback" not in proc.stderr
    left = [p.name for p in cache.iterdir() if p.name.startswith(".") or not p.name.endswith(".lock")] \
        if cache.exists() else []
    assert left == [], left  # no half-written entry, no temporary folder


@pytest.mark.slow
def test_a_cache_build_on_a_full_disk_warns_once_and_gives_the_right_numbers(tmp_path):
    _, want = _evaluate(tmp_path, "off")
    with _small_disk(256) as disk:
        _fill(disk, 4)
        cache = disk / "cache"
        proc, got = _evaluate(tmp_path, str(cache))
        _cache_warned_and_clean(proc, cache)
    assert got == want


def test_a_cache_build_past_the_file_size_limit_warns_once_and_gives_the_right_numbers(tmp_path):
    _, want = _evaluate(tmp_path, "off")
    cache = tmp_path / "cache"
    proc, got = _evaluate(tmp_path, str(cache), limit=4096)
    _cache_warned_and_clean(proc, cache)
    assert got == want
    assert resource.RLIMIT_FSIZE  # (the limit applied to the child only)
