"""How the command behaves for a user: exit codes and completion in --help, notices through logging
(-q silences them), progress bars only on a terminal, selectors whose package is missing refused
before anything runs."""
from __future__ import annotations

import importlib.util
import logging
import os
import subprocess
import sys

import pytest

from arraysel.cli.main import EXIT_CODES, configure_logging, main


def _help(argv, capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 0
    return capsys.readouterr().out


def test_help_lists_the_exit_codes_and_completion(capsys):
    text = _help(["--help"], capsys)
    assert "exit codes:" in text and "arraysel completion bash|zsh|tcsh" in text
    for code, _ in EXIT_CODES:
        assert f"\n  {code:<4d} " in text
    assert {c for c, _ in EXIT_CODES} >= {0, 1, 2, 130}


def test_report_help_prints_percent_signs_once(capsys):
    text = _help(["report", "--help"], capsys)
    assert "%%" not in text and "93.8 %" in text


@pytest.mark.parametrize("shell, marker", [("bash", "-F _shtab_arraysel arraysel"),
                                           ("zsh", "#compdef arraysel")])
def test_completion_scripts_know_every_command(shell, marker, capsys):
    pytest.importorskip("shtab")
    assert main(["completion", shell]) == 0
    script = capsys.readouterr().out
    assert marker in script
    for command in ("compare", "report", "evaluate", "scenes", "completion"):
        assert command in script


def _no_module(monkeypatch, name: str) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n == name else real(n, *a))


def test_a_selector_whose_package_is_missing_is_marked_and_refused_before_the_run(monkeypatch, tmp_path, capsys):
    _no_module(monkeypatch, "nevergrad")
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("nevergrad "))
    assert "NOT-INSTALLED" in row and "needs nevergrad: pip install 'arraysel[nevergrad]'" in out
    assert "NOT-INSTALLED" not in next(line for line in out.splitlines() if line.startswith("random "))
    folder = tmp_path / "cmp"
    assert main(["compare", "--scene", "toy", "--selectors", "random,nevergrad", "--budget-evals", "5",
                 "--seeds", "0", "--out", str(folder)]) == 2
    err = capsys.readouterr().err
    assert err == ("arraysel compare: error: selector 'nevergrad' needs nevergrad, which is not installed; "
                   "install it with: pip install 'arraysel[nevergrad]'\n")
    assert not folder.exists()                                  # nothing ran, nothing written
    import arraysel as asel
    from arraysel.errors import ParameterError

    with pytest.raises(ParameterError, match=r"pip install 'arraysel\[nevergrad\]'"):
        asel.compare("toy", ["nevergrad"], budget_s=None, budget_evals=5, out_dir=tmp_path / "api")


def test_quiet_silences_the_caches_notices(monkeypatch, tmp_path, capsys):
    import torch

    from arraysel.io import cache

    monkeypatch.setenv("ARRAYSEL_CACHE", str(tmp_path / "cache"))
    try:
        for quiet, key in ((0, "a"), (1, "b")):
            configure_logging(quiet=quiet)
            cache.load_or_build("t", (key,), lambda: {"x": torch.arange(3)}, what="a test entry")
            err = capsys.readouterr().err
            assert ("arraysel: building a test entry (first run with these settings)" in err) == (not quiet), err
    finally:
        configure_logging()
        logging.getLogger("arraysel").handlers.clear()


def test_a_redirected_log_gets_no_progress_frames(tmp_path):
    """stderr to a file (not a terminal): no tqdm bar, so no carriage-return frames in the log."""
    log = tmp_path / "log.txt"
    with open(log, "w") as fh:
        proc = subprocess.run([sys.executable, "-m", "arraysel", "compare", "--scene", "toy", "--selectors",
                               "random,uniform", "--budget-evals", "20", "--seeds", "0,1", "--in-process",
                               "--no-figures", "--out", str(tmp_path / "cmp")], cwd=tmp_path, stdout=subprocess.PIPE,
                              stderr=fh, text=True, timeout=300,
                              env={**os.environ, "ARRAYSEL_CACHE": str(tmp_path / "cache")})
    assert proc.returncode == 0, log.read_text()
    text = log.read_text()
    assert "\r" not in text and "%|" not in text, text


def test_the_announced_build_time_follows_the_measured_cost(monkeypatch, tmp_path, caplog):
    """The first build announces the model's estimate; it saves its measured time, and the next
    build's estimate is scaled by measured / estimated (here 0.3 s against 0.1 s: x3)."""
    import time

    import torch

    from arraysel.io import cache

    folder = tmp_path / "cache"
    monkeypatch.setenv("ARRAYSEL_CACHE", str(folder))

    def slow():
        time.sleep(0.3)
        return {"x": torch.arange(3)}

    with caplog.at_level(logging.WARNING, logger="arraysel"):
        cache.load_or_build("t", ("a",), slow, what="entry a", seconds_hint=0.1)
        assert cache.build_seconds_estimate(str(folder), 10.0) == pytest.approx(30.0, rel=0.5)
        cache.load_or_build("t", ("b",), slow, what="entry b", seconds_hint=10.0)
    notices = [r.getMessage() for r in caplog.records if "building entry" in r.getMessage()]
    assert "about 0 s" in notices[0] and "about 3" in notices[1], notices   # 10 s x (0.3 / 0.1)
    entries = [e for e in cache.list_entries(str(folder)) if e["kind"] == "entry"]
    assert all(e["build_seconds"] >= 0.3 for e in entries)
    assert cache.build_seconds_estimate(str(folder), 1.0) <= 4.0            # at most 4 x the model's
    assert cache.build_seconds_estimate(str(tmp_path / "empty"), 7.0) == 7.0
