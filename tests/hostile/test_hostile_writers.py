"""Hostile cases, killed writers: a writer killed with SIGKILL leaves its temporary file (nothing
can remove it then); the next writer to the same target removes it, and never a live writer's.

Each case kills a real child process with SIGKILL, asserts the leftover is named with the dead
writer's pid, and that the next run removes it, keeps a live writer's, and writes the right
content.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from arraysel.io import atomic
from scene_texts import TINY_SCENE

_WRITER = textwrap.dedent("""
    import sys, time
    from arraysel.io.atomic import AtomicFile

    f = AtomicFile(sys.argv[1])
    f.write(b"x" * 1_000_000)
    f.fh.flush()
    print(f.tmp, flush=True)
    time.sleep(120)
""")


def _writer(target: Path) -> tuple[subprocess.Popen, Path]:
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(target)], stdout=subprocess.PIPE, text=True)
    tmp = Path(proc.stdout.readline().strip())
    assert tmp.is_file(), tmp
    return proc, tmp


def _stop(proc: subprocess.Popen) -> None:
    proc.kill()
    proc.wait()
    proc.stdout.close()


def test_temporaries_are_named_with_the_writers_pid_and_host(tmp_path):
    with atomic.AtomicFile(tmp_path / "r.csv") as f:
        name = os.path.basename(f.tmp)
        assert name.startswith(f".r.csv.{atomic.writer_tag()}.") and name.endswith(".tmp")
        f.commit()


def test_next_writer_removes_a_killed_writers_leftover_but_not_a_live_ones(tmp_path):
    target = tmp_path / "kernels.npz"
    dead, dead_tmp = _writer(target)
    live, live_tmp = _writer(target)
    try:
        os.kill(dead.pid, signal.SIGKILL)
        dead.wait()
        assert dead.returncode == -signal.SIGKILL
        assert f".{dead.pid}-" in dead_tmp.name and dead_tmp.is_file()     # the leftover, named
        other_host = tmp_path / f".kernels.npz.{dead.pid}-000000.abcdefgh.tmp"  # another host's
        other_host.write_bytes(b"y")
        foreign = tmp_path / ".kernels.npz.mine.tmp"                          # not a writer's name
        foreign.write_bytes(b"z")
        atomic.atomic_savez(target, a=np.arange(3))
        assert not dead_tmp.exists()
        assert live_tmp.is_file() and other_host.is_file() and foreign.is_file()
        assert np.array_equal(np.load(target)["a"], np.arange(3))
    finally:
        _stop(dead)
        _stop(live)
    atomic.atomic_write_bytes(target, b"again")     # the live writer is gone now: its file goes
    assert not live_tmp.exists() and other_host.is_file() and foreign.is_file()




@pytest.mark.slow
def test_killed_evaluate_psf_out_leftovers_are_removed_by_the_next_run(tmp_path, monkeypatch):
    """``arraysel evaluate --psf-out`` killed with SIGKILL mid-run leaves its two temporary files;
    the next evaluate to the same targets removes them and writes complete results."""
    from arraysel.cli.main import main
    from arraysel.objective import psf_objective

    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY_SCENE)
    rng = np.random.default_rng(0)
    many = np.sort(np.argsort(rng.random((20_000, 8)), axis=1)[:, :4], axis=1)
    (tmp_path / "many.txt").write_text("\n".join(" ".join(map(str, r)) for r in many.tolist()) + "\n")
    out, kernels = tmp_path / "o.csv", tmp_path / "k.npz"
    proc = subprocess.Popen([sys.executable, "-c", "import sys; from arraysel.cli.main import main; "
                             "sys.exit(main())", "evaluate", "--scene", str(scene), "--masks",
                             str(tmp_path / "many.txt"), "--out", str(out), "--psf-out", str(kernels),
                             "--no-progress"], env=os.environ.copy(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300  # a guard against a hang, not a speed figure
        leftovers = []
        while time.monotonic() < deadline and proc.poll() is None:
            leftovers = sorted(p for p in os.listdir(tmp_path) if p.endswith(".tmp"))
            if len(leftovers) == 2 and os.path.getsize(tmp_path / leftovers[0]) > 0:
                break
            time.sleep(0.05)
        assert proc.poll() is None, f"evaluate ended before it could be killed: {proc.stderr.read()}"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    assert {p.split(".")[2] for p in leftovers} == {"csv", "npz"}, leftovers
    assert all(f".{proc.pid}-" in p for p in leftovers), leftovers
    assert not out.exists() and not kernels.exists()          # nothing half-written in place

    few = many[:5]
    (tmp_path / "few.txt").write_text("\n".join(" ".join(map(str, r)) for r in few.tolist()) + "\n")
    monkeypatch.setattr(psf_objective, "_CACHE", {})
    assert main(["evaluate", "--scene", str(scene), "--masks", str(tmp_path / "few.txt"), "--out", str(out),
                 "--psf-out", str(kernels), "--no-progress"]) == 0
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]
    assert np.load(kernels)["psf"].shape == (5, 16, 16)
    assert len(out.read_text().splitlines()) == 6
