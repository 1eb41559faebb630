"""Hostile cases, resources: a grid too large for the memory cap is refused from its sizes alone,
before anything is allocated, in one line naming the keys, the memory needed and allowed.
"""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from arraysel.errors import ParameterError
from arraysel.physics.psf import settings
from arraysel.scenes.schema import load_scene

BUILTIN = ("paper", "paper-e2e", "l11-5v", "c5-2v", "p4-2v-depths")


def test_grid_bytes_is_arithmetic_and_grows_with_the_grid():
    small, step = settings.grid_bytes(400, 400, 128, 64)
    big, big_step = settings.grid_bytes(8192, 8192, 128, 64)
    assert 0 < small < 2 ** 30 and big > 5 * 2 ** 30
    assert "window estimate" in big_step
    # every 8th row and column of 8192 x 8192, 64 elements, WINDOW_ESTIMATE_ARRAYS float64 arrays
    want = settings.HEAP_FACTOR * settings.WINDOW_ESTIMATE_ARRAYS * 8 * 1025 * 1025 * 64
    assert abs(big - want) <= 1
    most = settings.largest_grid_pixels(64, 4 * 2 ** 30)
    side = int(most ** 0.5)
    assert settings.grid_bytes(side, side, 128, 64)[0] <= 4 * 2 ** 30 * 1.01
    assert settings.grid_bytes(side + 200, side + 200, 128, 64)[0] > 4 * 2 ** 30


@pytest.mark.parametrize("name", BUILTIN)
def test_builtin_scenes_pass_under_the_default_cap(name, monkeypatch):
    monkeypatch.delenv(settings.MEMORY_GIB, raising=False)
    assert load_scene(name).psf_setups()


def test_huge_grid_is_refused_in_one_line_naming_the_keys(monkeypatch):
    monkeypatch.setenv(settings.MEMORY_GIB, "4")
    scene = load_scene({"base": "paper", "grid": {"n_x": 8192, "n_z": 8192}})   # loading is fine
    with pytest.raises(ParameterError) as err:
        scene.psf_setups()
    msg = str(err.value)
    assert "\n" not in msg and "grid.n_x" in msg and "grid.n_z" in msg and "8192 x 8192" in msg
    assert "GiB" in msg and "4.0 GiB allowed by ARRAYSEL_MEMORY_GIB" in msg and "up to about" in msg
    monkeypatch.setenv(settings.MEMORY_GIB, "1000")       # the cap is the user's to raise
    assert settings.grid_bytes(8192, 8192, 128, 64)[0] < settings.memory_limit_bytes()


def test_the_cap_decides_also_for_a_smaller_grid(monkeypatch):
    monkeypatch.setenv(settings.MEMORY_GIB, "0.25")
    with pytest.raises(ParameterError, match="grid.n_x x grid.n_z = 2048 x 2048"):
        load_scene({"base": "paper", "grid": {"n_x": 2048, "n_z": 2048}}).psf_setups()


_HUGE = textwrap.dedent("""
    import resource, sys
    from arraysel.cli.main import main
    code = main(["psf", "--scene", sys.argv[1], "--out", sys.argv[2]])
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss   # KiB on Linux
    print(code, peak, flush=True)
""")

# the same interpreter importing what the command imports, and nothing more: the baseline the
# refused command is measured against (what importing torch costs differs between machines)
_IMPORTS = textwrap.dedent("""
    import resource
    import torch
    import arraysel.cli.main, arraysel.cli.psf, arraysel.scenes
    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, flush=True)
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="ru_maxrss in KiB (Linux)")
def test_huge_grid_command_is_refused_before_allocating(tmp_path):
    """``arraysel psf`` on an 8192 x 8192 grid: exit code 2, one line, and the process never grew
    past what importing arraysel and torch takes (within 256 MiB of a process that only imports
    them, against the ~5.4 GiB the window estimate would allocate)."""
    scene = tmp_path / "huge.toml"
    scene.write_text('base = "paper"\n[grid]\nn_x = 8192\nn_z = 8192\n')
    env = {**os.environ, "ARRAYSEL_CACHE": "off"}
    env.pop(settings.MEMORY_GIB, None)
    proc = subprocess.run([sys.executable, "-c", _HUGE, str(scene), str(tmp_path / "k.npz")], capture_output=True,
                          text=True, env=env, timeout=600)
    code, peak_kib = (int(v) for v in proc.stdout.split())
    assert code == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "grid.n_x" in lines[0] and "ARRAYSEL_MEMORY_GIB" in lines[0], proc.stderr
    base = subprocess.run([sys.executable, "-c", _IMPORTS], capture_output=True, text=True, env=env, timeout=600)
    base_kib = int(base.stdout.split()[0])
    assert peak_kib < base_kib + 2 ** 18, (peak_kib, base_kib)  # within 256 MiB of the imports alone
    assert not (tmp_path / "k.npz").exists()
