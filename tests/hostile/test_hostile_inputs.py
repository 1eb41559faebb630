"""Hostile cases, malformed input and a hostile environment: element indices Python's ``int``
reads but a mask file must not hold (``6_2``, full-width digits), a byte-order mark, a reader
that closes the pipe, a first build on a busy machine, a home folder that cannot be written.

Each case asserts the exit code and the one line that says what happened, or the right number.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from arraysel.cli.main import main
from arraysel.errors import SelectionError
from arraysel.io.masks import parse_elements

AS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0
SETPRIV = shutil.which("setpriv")
GOOD = list(range(0, 64, 2))  # a toy selection (Ne = 64, k = 32)
CLI = "import sys; from arraysel.cli.main import main; sys.exit(main())"


def _evaluate(tmp_path, text: str, capsys) -> tuple[int, list[str]]:
    masks = tmp_path / "m.txt"
    masks.write_bytes(text.encode("utf-8"))
    code = main(["evaluate", "--scene", "toy", "--masks", str(masks), "--out", str(tmp_path / "o.csv"),
                 "--no-progress"])
    return code, capsys.readouterr().err.strip().splitlines()


# ------------------------------------------------------------------ item 6: integers are ASCII digits
@pytest.mark.parametrize("token", ["6_2", "\uff16\uff12", "\u0666\u0662", "62\u0663", "1e1", "0x3e", "6.0", "\u00b2"])
def test_a_mask_index_that_is_not_ascii_digits_is_refused_naming_its_line(tmp_path, capsys, token):
    """Issue 77, item 6: before, ``... 60 6_2`` (and full-width digits) was read as 62."""
    line = " ".join(map(str, GOOD[:-1])) + f" {token}\n"
    code, err = _evaluate(tmp_path, "# first line is a comment\n" + line, capsys)
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("arraysel evaluate: error: ") and ", line 2: " in err[0]
    assert f"{token!r} is not an integer element index" in err[0]
    assert not (tmp_path / "o.csv").exists()


def test_signed_ascii_indices_are_still_read_and_checked():
    assert parse_elements("+0 2 4", 8, 3) == [0, 2, 4]
    with pytest.raises(SelectionError, match=r"in \[0, 7\], got \[-1\]"):
        parse_elements("-1 2 4", 8, 3)


def test_an_elements_cell_with_underscores_is_not_a_selection():
    from arraysel.selection import Selection

    with pytest.raises(SelectionError, match="'0 6_2' is not a list of element indices"):
        Selection.from_text("0 6_2", 64)
    assert Selection.from_text("0 62", 64).indices == (0, 62)


def test_a_byte_order_mark_at_the_start_of_a_mask_file_is_read_past(tmp_path, capsys):
    """Issue 77, item 6: before, a file saved with a byte-order mark was refused with a confusing
    message ('\\ufeff0' is not an integer element index)."""
    plain = " ".join(map(str, GOOD)) + "\n"
    code, err = _evaluate(tmp_path, "\ufeff" + plain, capsys)
    assert code == 0, err
    with_bom = (tmp_path / "o.csv").read_text()
    code, err = _evaluate(tmp_path, plain, capsys)
    assert code == 0 and (tmp_path / "o.csv").read_text() == with_bom
    code, err = _evaluate(tmp_path, plain + "\ufeff" + plain, capsys)  # a mark anywhere else is refused
    assert code == 2 and len(err) == 1 and ", line 2: '\\ufeff0' is not an integer element index" in err[0]


# ------------------------------------------------------------------ item 6: a closed pipe
def test_a_reader_that_closes_the_pipe_ends_the_command_quietly():
    """Issue 77, item 6: ``arraysel list -v | head -1`` printed a BrokenPipeError traceback."""
    proc = subprocess.Popen([sys.executable, "-c", CLI, "list", "-v"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    proc.stdout.close()  # before the command writes its first line
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 141 and err.decode() == "", err.decode()


def test_head_of_the_list_gets_its_line_and_no_traceback():
    proc = subprocess.run(f"{sys.executable} -c '{CLI}' list -v | head -1", shell=True, capture_output=True,
                          text=True, timeout=120)
    assert proc.stdout.startswith("name") and proc.stdout.count("\n") == 1 and proc.stderr == "", proc.stderr


# ------------------------------------------------------------------ item 6: the first build's time notice
def test_the_first_build_notice_says_it_is_an_estimate_from_the_measured_cost(tmp_path, monkeypatch, caplog):
    """Issue 77, item 6: before, the notice said 'about 2 s' from the sizes alone (a build that
    took 48 s on a loaded machine), and did not say it was an estimate."""
    import logging

    import numpy as np

    from arraysel.io import cache

    folder = tmp_path / "c"
    monkeypatch.setenv("ARRAYSEL_CACHE", str(folder))
    earlier = folder / ("psf-" + "1" * 24)  # an earlier build here took 4 x its own estimate
    earlier.mkdir(parents=True)
    (earlier / "manifest.json").write_text(json.dumps({"format": 1, "tensors": {}, "build_seconds": 16.0,
                                                       "estimated_seconds": 4.0, "created": "2026-01-01T00:00:00Z"}))
    with caplog.at_level(logging.WARNING, logger="arraysel.io.cache"):
        state = cache.load_or_build("psf", ("k",), lambda: {"a": np.arange(3)}, what="a test basis",
                                    seconds_hint=2.0, progress=False)
    assert list(state["a"]) == [0, 1, 2]
    notice = [r.getMessage() for r in caplog.records if "building a test basis" in r.getMessage()]
    assert len(notice) == 1 and "(first run with these settings; an estimate: about 8 s)" in notice[0], notice
    manifest = json.loads((folder / cache.entry_name("psf", ("k",)) / "manifest.json").read_text())
    assert manifest["estimated_seconds"] == 2.0 and manifest["build_seconds"] >= 0  # the next build's measure


# ------------------------------------------------------------------ item 7: a home folder that cannot be written
@pytest.mark.slow
@pytest.mark.skipif(not (AS_ROOT and SETPRIV), reason="needs root and setpriv to run as another user")
def test_the_kernels_compile_for_a_user_whose_home_and_install_cannot_be_written():
    """Issue 77, item 7: before, importing the kernels failed with numba's 'cannot cache function
    ...: no locator available' for a user who could write neither the installation nor HOME."""
    tmp = tempfile.mkdtemp(prefix="arraysel-nobody-")
    try:
        home = Path(tmp, "home")
        home.mkdir(mode=0o555)
        scratch = Path(tmp, "scratch")
        scratch.mkdir()
        os.chmod(tmp, 0o755)
        os.chmod(scratch, 0o777)
        env = {**os.environ, "HOME": str(home), "TMPDIR": str(scratch)}
        env.pop("NUMBA_CACHE_DIR", None)
        code = ("import numba, numpy as np\n"
                "import arraysel.physics.pairkernels, arraysel.physics.volume.kernels\n"
                "import arraysel.objective.metric_kernels as mk\n"
                "print(numba.config.CACHE_DIR)\n")
        proc = subprocess.run([SETPRIV, "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable, "-c",
                               code], capture_output=True, text=True, env=env, timeout=600, cwd=tmp)
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert proc.stdout.strip() == str(scratch / "arraysel-numba-65534")
        assert "no locator available" not in proc.stderr
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
