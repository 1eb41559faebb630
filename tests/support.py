"""Fixtures several test modules share (imported by name; pytest finds tests/ through its conftest).

* :func:`time_limit` -- an autouse fixture that fails, instead of hanging, a test that runs longer
  than its limit: ``_bounded = time_limit(120)`` in a module;
* :func:`own_plugin_manager` -- a process-wide plugin manager of the built-ins only (no installed
  entry points, no disable list from the environment), restored afterwards:
  ``from support import own_plugin_manager`` in a module, with ``pytestmark`` or autouse as it needs;
* :data:`PLAIN` -- the swap engine's settings for tests of its mechanics.
"""
from __future__ import annotations

import signal

import pytest

from arraysel.selectors.swapsettings import SwapSettings

#: the swap engine with one plain descent (no race, no shifts, the linear model, a full scan, restarts
#: off), not ``swap``'s defaults: the tests of the engine's mechanics were written against it
PLAIN = SwapSettings(guide=0.5, scan=1.0, restart_after=0, fresh="random", race=1, race_quota=500,
                     race_chirps=256, shift=0, shift_scan=4096, model="linear", gradient="exact")


def time_limit(seconds: int):
    """An autouse fixture: SIGALRM after ``seconds`` raises TimeoutError in the test."""
    @pytest.fixture(autouse=True)
    def _bounded():
        def stop(signum, frame):
            raise TimeoutError(f"test took more than {seconds} s")
        old = signal.signal(signal.SIGALRM, stop)
        signal.alarm(seconds)
        yield
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    return _bounded


@pytest.fixture(autouse=True)
def own_plugin_manager(monkeypatch):
    """A process-wide plugin manager of the built-ins only, restored afterwards (autouse where
    imported)."""
    from arraysel.selectors import registry

    monkeypatch.delenv(registry.DISABLE_ENV, raising=False)
    registry.reset()
    registry._PM = registry.build_plugin_manager(load_entrypoints=False)
    try:
        yield
    finally:
        registry.reset()



def ioh_dat_rows(folder) -> dict:
    """``{(algorithm, run number): rows of its .dat block}`` of an IOHprofiler folder, from the files."""
    import json
    from pathlib import Path

    out = {}
    for js in Path(folder).glob("*/IOHprofiler_*.json"):
        meta = json.loads(js.read_text())
        scen = meta["scenarios"][0]
        blocks = (js.parent / scen["path"]).read_text().split("evaluations raw_y seconds\n")[1:]
        assert len(blocks) == len(scen["runs"]), js
        for number, block in enumerate(blocks, 1):
            out[(meta["algorithm"]["name"], number)] = len(block.strip().splitlines())
    return out


def ioh_read(folder) -> dict:
    """``{(algorithm, run number): data rows}`` as the installed iohinspector reads the IOHprofiler
    folder (a file it refuses, or a warning it gives, raises AssertionError naming the folder)."""
    import warnings

    import iohinspector

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            manager = iohinspector.DataManager()
            manager.add_folder(str(folder))
            overview = manager.overview
            data = manager.load(monotonic=False) if len(overview) else None
        except Exception as exc:  # noqa: BLE001 - whatever the reader says is the failure
            raise AssertionError(f"iohinspector cannot load {folder}: {type(exc).__name__}: {exc}") from None
    counts = {}
    if data is not None:
        rows = data.group_by("data_id").len()
        counts = dict(zip(rows["data_id"].to_list(), rows["len"].to_list()))
    return {(a, r): counts.get(d, 0) for a, r, d in zip(overview["algorithm_name"].to_list(),
                                                       overview["run_id"].to_list(), overview["data_id"].to_list())}


def ioh_folders_load(root) -> int:
    """Load every IOHprofiler folder (``ioh/`` of a comparison) under ``root`` with the installed
    ``iohinspector``: it must read every run the files hold, each with all the rows of its
    ``.dat`` block (AssertionError naming the folder otherwise). Returns the folders loaded (0
    without iohinspector)."""
    from pathlib import Path

    folders = sorted({p.parent.parent for p in Path(root).rglob("IOHprofiler_*.json")
                      if p.parent.parent.name == "ioh"})
    if not folders:
        return 0
    try:
        import iohinspector  # noqa: F401
    except ImportError:  # pragma: no cover - a test dependency
        return 0
    for folder in folders:
        want, got = ioh_dat_rows(folder), ioh_read(folder)
        assert got == want, f"iohinspector reads {folder} as {got}, its files hold {want}"
    return len(folders)
