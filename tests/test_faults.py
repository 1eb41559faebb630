"""Fault suite (issue 16): damaged caches, killed writers, concurrent builders, misuse of compare
and evaluate, bad inputs, unwritable outputs and file modes.

Everything runs on small states, tiny PSF scenes or the toy objective, with the cache in a
temporary folder (``ARRAYSEL_CACHE``), so the shared cache is never touched.
"""
from __future__ import annotations

import logging
import os
import signal
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from arraysel.io import atomic

from arraysel.io import cache
from scene_texts import TINY_SCENE

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def cache_folder(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv("ARRAYSEL_CACHE", str(folder))
    monkeypatch.delenv("ARRAYSEL_CACHE_VERIFY", raising=False)
    return folder


def _state(seed=0, n=300_000):
    g = torch.Generator().manual_seed(seed)
    return {"V": torch.randn(n, generator=g), "meta": torch.tensor([3, 4, 5]), "scalar": torch.tensor(2.5),
            "empty": torch.zeros(0, 7), "c": torch.randn(5, 3, dtype=torch.complex64, generator=g)}


def _same(a: dict, b: dict) -> bool:
    return set(a) == set(b) and all(torch.equal(a[k], b[k]) for k in a)


def _counting_builder(seed=0):
    calls = []

    def build():
        calls.append(1)
        return _state(seed)
    return build, calls


def _entry(folder: Path) -> Path:
    entries = [p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")]
    assert len(entries) == 1, entries
    return entries[0]


def _mapped_file(t: torch.Tensor) -> str | None:
    """The file whose memory map holds the tensor's data (Linux /proc/self/maps), else None."""
    addr = t.data_ptr()
    with open("/proc/self/maps") as fh:
        for line in fh:
            parts = line.split()
            lo, hi = (int(v, 16) for v in parts[0].split("-"))
            if lo <= addr < hi:
                return parts[5] if len(parts) > 5 else None
    return None


def _flip_bit(path: Path, offset: int, bit: int = 3) -> None:
    with open(path, "r+b") as fh:
        fh.seek(offset)
        b = fh.read(1)[0]
        fh.seek(offset)
        fh.write(bytes([b ^ (1 << bit)]))


# ---------------------------------------------------------------------------
# cache: format, integrity, atomicity, concurrency
# ---------------------------------------------------------------------------

def test_cache_roundtrip_is_memory_mapped_and_follows_the_umask(cache_folder, capsys, caplog):
    build, calls = _counting_builder()
    with caplog.at_level(logging.WARNING, logger="arraysel.io.cache"):  # the announcement is a log record
        first = cache.load_or_build("t", ("k", 1), build, what="a test state", size_hint=3_000_000,
                                    seconds_hint=20, progress=True)
    (note,) = [r.getMessage() for r in caplog.records if "building" in r.getMessage()]
    assert "building a test state" in note and f"cached in {cache_folder} (about 3.0 MB)" in note
    assert "an estimate: about 20 s" in note and "/~20 s" in capsys.readouterr().err  # the announcement, the bar
    second = cache.load_or_build("t", ("k", 1), build, what="a test state")
    assert calls == [1] and _same(first, _state()) and _same(second, _state())
    entry = _entry(cache_folder)
    assert entry.name == cache.entry_name("t", ("k", 1))
    # loaded tensors are views of the files (copy-on-write maps), not copies
    assert _mapped_file(second["V"]) == str(entry / "V.npy")
    want = 0o666 & ~atomic._umask()
    for f in entry.iterdir():
        assert stat.S_IMODE(f.stat().st_mode) == want, f
    assert not [p for p in cache_folder.iterdir() if p.name.endswith(".tmp")]


def test_cache_build_hands_out_the_saved_files_not_the_built_tensors(cache_folder):
    """A process that builds several entries holds none of them in its own memory: the build's
    tensors are swapped for the saved entry's memory maps (the same values a later run loads)."""
    build, calls = _counting_builder()
    first = cache.load_or_build("t", ("m",), build)
    entry = _entry(cache_folder)
    assert calls == [1] and _same(first, _state())
    assert _mapped_file(first["V"]) == str(entry / "V.npy")


def _announcement(record) -> bool:
    """The notice a build gives before it starts (a log record, not a problem)."""
    return "(first run with these settings" in record.getMessage()


def test_cache_bit_flip_is_reported_and_rebuilt(cache_folder, caplog):
    build, calls = _counting_builder()
    cache.load_or_build("t", ("k",), build)
    entry = _entry(cache_folder)
    _flip_bit(entry / "V.npy", 600_001)
    with caplog.at_level(logging.WARNING, logger="arraysel.io.cache"):
        again = cache.load_or_build("t", ("k",), build)
    assert calls == [1, 1] and _same(again, _state())
    msgs = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and not _announcement(r)]
    assert len(msgs) == 1 and "damaged" in msgs[0] and "checksum mismatch" in msgs[0] and "'V'" in msgs[0]
    assert _same(cache.load_state(str(entry)), _state())  # the entry was repaired
    assert calls == [1, 1]


def test_cache_entries_carry_crc32_and_older_sha256_entries_still_load(cache_folder, caplog):
    """New entries carry the CRC-32 of every block (the bytes of each file, checked here with
    zlib); an entry whose manifest carries SHA-256 digests (written by earlier versions) loads,
    verified with them, and a flipped bit in it is still reported and rebuilt."""
    import hashlib
    import json
    import zlib

    build, calls = _counting_builder()
    cache.load_or_build("t", ("k",), build)
    entry = _entry(cache_folder)
    manifest = json.loads((entry / "manifest.json").read_text())
    for info in manifest["tensors"].values():
        data = (entry / info["file"]).read_bytes()
        blocks = [data[i:i + manifest["block"]] for i in range(0, max(1, len(data)), manifest["block"])]
        assert "sha256" not in info and info["crc32"] == [f"{zlib.crc32(b):08x}" for b in blocks]
        # rewrite the manifest as an earlier version did
        info["sha256"] = [hashlib.sha256(b).hexdigest() for b in blocks]
        del info["crc32"]
    (entry / "manifest.json").write_text(json.dumps(manifest))
    assert _same(cache.load_or_build("t", ("k",), build), _state()) and calls == [1]
    _flip_bit(entry / "V.npy", 600_001)
    with caplog.at_level(logging.WARNING, logger="arraysel.io.cache"):
        again = cache.load_or_build("t", ("k",), build)
    assert calls == [1, 1] and _same(again, _state())
    assert sum("checksum mismatch" in r.getMessage() for r in caplog.records) == 1
    rebuilt = json.loads((entry / "manifest.json").read_text())
    assert all("crc32" in info for info in rebuilt["tensors"].values())


@pytest.mark.parametrize("damage", ["truncate", "manifest", "missing", "header", "garbage-manifest"])
def test_cache_partial_or_altered_entry_is_rebuilt(cache_folder, caplog, damage):
    build, calls = _counting_builder()
    cache.load_or_build("t", ("k",), build)
    entry = _entry(cache_folder)
    if damage == "truncate":
        with open(entry / "V.npy", "r+b") as fh:
            fh.truncate(1000)
    elif damage == "manifest":
        (entry / "manifest.json").unlink()
    elif damage == "missing":
        (entry / "meta.npy").unlink()
    elif damage == "header":
        np.save(entry / "meta.npy", np.array([3, 4, 5], dtype=np.int32))  # same values, other dtype
    else:
        (entry / "manifest.json").write_bytes(b"\xff\xfe not json")
    with caplog.at_level(logging.WARNING, logger="arraysel.io.cache"):
        again = cache.load_or_build("t", ("k",), build)
    assert calls == [1, 1] and _same(again, _state())
    assert sum("damaged" in r.getMessage() for r in caplog.records) == 1
    assert _same(cache.load_state(str(_entry(cache_folder))), _state())


def test_cache_size_mode_skips_hashing_but_catches_truncation(cache_folder, monkeypatch):
    build, _ = _counting_builder()
    cache.load_or_build("t", ("k",), build)
    entry = _entry(cache_folder)
    _flip_bit(entry / "V.npy", 900_000)
    monkeypatch.setenv("ARRAYSEL_CACHE_VERIFY", "size")
    cache.load_state(str(entry))  # documented: a flipped bit passes the size check
    monkeypatch.setenv("ARRAYSEL_CACHE_VERIFY", "full")
    with pytest.raises(cache.DamagedEntry, match="checksum mismatch"):
        cache.load_state(str(entry))
    monkeypatch.setenv("ARRAYSEL_CACHE_VERIFY", "bogus")
    with pytest.raises(Exception, match="ARRAYSEL_CACHE_VERIFY"):
        cache.verify_mode()


def test_cache_full_check_is_recorded_and_a_changed_file_is_hashed_again(cache_folder, monkeypatch):
    """A full check of files changed long enough before it is recorded in the entry
    (``checked.json``); a later load of the unchanged files skips the hashing, and a file written
    since (a flipped bit) is hashed again and caught. Files changed just before the check (within
    ``SETTLED_NS``: coarse file times) are not recorded, and the entry stays the cache's."""
    from arraysel.io import cachefiles

    build, _ = _counting_builder()
    cache.load_or_build("t", ("k",), build)
    entry = _entry(cache_folder)
    hashed = []
    real = cachefiles._verify_blocks
    monkeypatch.setattr(cachefiles, "_verify_blocks", lambda *a: (hashed.append(1), real(*a))[1])
    cache.load_state(str(entry))  # just written: checked, not recorded
    assert len(hashed) == 1 and not (entry / cachefiles.CHECKED).exists()
    monkeypatch.setattr(cachefiles, "SETTLED_NS", 50_000_000)
    time.sleep(0.1)
    cache.load_state(str(entry))  # hashed, recorded
    assert len(hashed) == 2 and (entry / cachefiles.CHECKED).exists()
    assert cache.classify(str(cache_folder), entry.name)["owner"] == "cache"
    assert _same(cache.load_state(str(entry)), _state()) and len(hashed) == 2  # not hashed again
    _flip_bit(entry / "V.npy", 600_001)
    with pytest.raises(cache.DamagedEntry, match="checksum mismatch"):
        cache.load_state(str(entry))
    assert len(hashed) == 3


_KILL_SCRIPT = textwrap.dedent("""
    import os, signal, sys
    import numpy as np
    import torch
    from arraysel.io import cache

    real = np.lib.format.write_array
    count = [0]

    def dying(fp, arr, **kw):
        count[0] += 1
        if count[0] == 2:  # killed in the middle of the second tensor
            fp.write(b"x" * 1000)
            os.kill(os.getpid(), signal.SIGKILL)
        return real(fp, arr, **kw)

    np.lib.format.write_array = dying
    state = {"a": torch.arange(100_000), "b": torch.ones(100_000), "c": torch.zeros(3)}
    cache.load_or_build("t", ("k",), lambda: state)
""")


def test_cache_kill_during_save_leaves_no_entry_and_the_next_run_cleans_up(cache_folder):
    proc = subprocess.run([sys.executable, "-c", _KILL_SCRIPT], capture_output=True, text=True,
                          env={**os.environ, "ARRAYSEL_CACHE": str(cache_folder)}, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    names = [p.name for p in cache_folder.iterdir()]
    assert not [n for n in names if not n.startswith(".") and not n.endswith(".lock")], names  # no entry
    assert [n for n in names if n.endswith(".tmp")], names  # the killed writer's leftover
    build, calls = _counting_builder()
    cache.load_or_build("t", ("k",), build)
    names = sorted(p.name for p in cache_folder.iterdir())
    assert calls == [1] and not [n for n in names if n.endswith(".tmp")], names
    assert [n for n in names if not n.endswith(".lock")] == [cache.entry_name("t", ("k",))]


_BUILDER_SCRIPT = textwrap.dedent("""
    import sys, time
    import torch
    from arraysel.io import cache

    def build():
        with open(sys.argv[1], "a") as fh:
            fh.write("built\\n")
        time.sleep(2.0)
        return {"x": torch.arange(1000) * 3}

    st = cache.load_or_build("t", ("shared",), build, what="the shared state")
    assert torch.equal(st["x"], torch.arange(1000) * 3)
    print("ok")
""")


def test_cache_concurrent_builders_wait_on_the_lock(cache_folder, tmp_path):
    log = tmp_path / "builds.txt"
    env = {**os.environ, "ARRAYSEL_CACHE": str(cache_folder)}
    procs = [subprocess.Popen([sys.executable, "-c", _BUILDER_SCRIPT, str(log)], env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE) for _ in range(2)]
    outs = [p.communicate(timeout=180) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    assert log.read_text().count("built") == 1  # one built, the other waited and loaded
    assert any("waiting for another process" in err for _, err in outs)


def test_cache_off_and_location(monkeypatch, tmp_path):
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    assert cache.cache_dir() is None
    build, calls = _counting_builder()
    cache.load_or_build("t", ("k",), build)
    cache.load_or_build("t", ("k",), build)
    assert calls == [1, 1]
    monkeypatch.delenv("ARRAYSEL_CACHE")
    from platformdirs import user_cache_dir
    assert cache.cache_dir() == user_cache_dir("arraysel", appauthor=False)


def test_cache_command_path_info_clear(cache_folder):
    from arraysel.cli.main import main

    cache.load_or_build("t", ("k",), _counting_builder()[0])
    stale = cache.entry_name("t", ("stale",))
    (cache_folder / f".{stale}.999999999.0123abcd.tmp").mkdir()  # a writer that is gone
    (cache_folder / f"{cache.entry_name('psf-basis', ('old',))}.pt").write_bytes(b"old format")
    out = subprocess.run([sys.executable, "-m", "arraysel.cli.main", "cache", "info"], capture_output=True,
                         text=True, env=os.environ.copy())
    assert out.returncode == 0, out.stderr
    assert str(cache_folder) in out.stdout and "ok" in out.stdout
    assert "leftover" in out.stdout and "older cache format" in out.stdout
    assert main(["cache", "path"]) == 0
    assert main(["cache", "clear"]) == 0
    assert list(cache_folder.iterdir()) == []


def test_psf_basis_goes_through_the_checked_cache(cache_folder, caplog):
    """The PSF model stores its basis in the new cache; a bit flip in the stored basis is caught,
    reported and repaired, and the kernels stay the exact path's."""
    from arraysel.physics.probes import Acquisition, get_probe
    from arraysel.physics.psf import PSFModel, PSFSetup

    probe = get_probe("P4-2v", fc=3.5e6, n_elements=8)
    acq = Acquisition.for_probe(probe)
    pixel = acq.c / acq.fs
    setup = PSFSetup(probe=probe, acq=acq, tilts=(0.0,), n_x=32, n_z=32, pixel=pixel, z_offset=0, window=16,
                     scatterer=(0.0, 16 * pixel))
    w = torch.tensor([[1, 0, 1, 1, 0, 1, 0, 1.0]])
    first = PSFModel(setup, margin=2, block=4)
    k1 = first.kernels(w)
    entry = _entry(cache_folder)
    assert entry.name.startswith("psf-basis-")
    biggest = max((p for p in entry.iterdir() if p.suffix == ".npy"), key=lambda p: p.stat().st_size)
    _flip_bit(biggest, biggest.stat().st_size - 7, bit=6)
    with caplog.at_level(logging.WARNING, logger="arraysel.io.cache"):
        second = PSFModel(setup, margin=2, block=4)
    assert sum("damaged" in r.getMessage() for r in caplog.records) == 1
    k2 = second.kernels(w)
    exact = PSFModel(setup, margin=2, block=4, fast=False).kernels(w)
    assert torch.allclose(k1, k2) and torch.allclose(k2, exact, atol=5e-3)


# ---------------------------------------------------------------------------
# file modes and atomic writers
# ---------------------------------------------------------------------------

def test_atomic_writers_follow_the_umask(tmp_path):
    from arraysel.io import masks as maskio
    from arraysel.report import tables as reporting

    old = os.umask(0o022)
    try:
        atomic.atomic_write_text(tmp_path / "a.txt", "x")
        maskio.atomic_write_bytes(str(tmp_path / "b.csv"), b"x")
        maskio.atomic_savez(str(tmp_path / "c.npz"), a=np.zeros(2))
        reporting.write_json(tmp_path / "d.json", {"a": 1})
        with atomic.AtomicFile(tmp_path / "e.csv") as f:
            f.write(b"x")
            f.commit()
        for name in ("a.txt", "b.csv", "c.npz", "d.json", "e.csv"):
            assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o644, name
        os.umask(0o077)
        atomic.atomic_write_text(tmp_path / "private.txt", "x")
        assert stat.S_IMODE((tmp_path / "private.txt").stat().st_mode) == 0o600
    finally:
        os.umask(old)


def test_atomic_file_discards_on_error(tmp_path):
    target = tmp_path / "rows.csv"
    target.write_text("old\n")
    with pytest.raises(RuntimeError):
        with atomic.AtomicFile(target) as f:
            f.write(b"half")
            raise RuntimeError("boom")
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["rows.csv"]


# ---------------------------------------------------------------------------
# compare: isolation, resume, finished folders, budgets
# ---------------------------------------------------------------------------

_BAD_PLUGINS = textwrap.dedent("""
    import os, sys, time
    from arraysel.selectors.hookspecs import hookimpl
    from arraysel.selectors.contract import Selector, indices_to_mask


    class _Base(Selector):
        options = {}
        deterministic = True

        def batch_size(self, n_elements, k):
            return 1


    class Hangs(_Base):
        name = "hangs"
        description = "ignores its budget and sleeps"

        def select(self, objective, k, seed):
            time.sleep(600)
            return list(range(k))


    class Exits(_Base):
        name = "exits"
        description = "calls sys.exit(0)"

        def select(self, objective, k, seed):
            sys.exit(0)


    class Dies(_Base):
        name = "dies"
        description = "kills its own process"

        def select(self, objective, k, seed):
            os._exit(3)


    class Overspends(_Base):
        name = "overspends"
        description = "evaluates far more masks than its budget"

        def select(self, objective, k, seed):
            for _ in range(50):  # past the budgeted view, on the objective it wraps
                objective._inner.evaluate(indices_to_mask(list(range(k)), objective.n_elements)[None])
            return list(range(k))


    class Fine(_Base):
        name = "fine"
        description = "the first k elements"

        def select(self, objective, k, seed):
            return list(range(k))


    @hookimpl
    def arraysel_register_selectors(register):
        for cls in (Hangs, Exits, Dies, Overspends, Fine):
            register(cls)
""")


@pytest.fixture(scope="module")
def _bad_plugin_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("plugins") / "bad_plugins.py"
    path.write_text(_BAD_PLUGINS)
    return str(path)


@pytest.fixture(autouse=True)
def _own_plugin_manager(monkeypatch):
    """A process-wide plugin manager of the built-ins only, restored afterwards."""
    from arraysel.selectors import registry

    monkeypatch.delenv(registry.DISABLE_ENV, raising=False)
    registry.reset()
    registry._PM = registry.build_plugin_manager(load_entrypoints=False)
    try:
        yield
    finally:
        registry.reset()


@pytest.fixture
def bad_plugins(_bad_plugin_file):
    return _bad_plugin_file


def _compare(out, selectors, *extra, budget_s="1", evals="10"):
    from arraysel.cli.main import main

    return main(["compare", "--selectors", selectors, "--scene", "toy", "--budget-s", budget_s,
                 "--budget-evals", evals, "--out", str(out), "--no-progress", "--no-figures", *extra])


def test_compare_isolates_hanging_exiting_dying_and_overspending_selectors(tmp_path, bad_plugins, capsys):
    import pandas as pd

    out = tmp_path / "cmp"
    t0 = time.monotonic()
    code = _compare(out, "hangs,exits,dies,overspends,fine", "--plugin", bad_plugins, "--grace-s", "1")
    took = time.monotonic() - t0
    err = capsys.readouterr().err
    assert code == 1 and "4 run(s) failed" in err
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False).set_index("config")
    assert "stopped after" in runs.loc["hangs", "error"] and "budget was 1 s" in runs.loc["hangs", "error"]
    assert "(exit code 0) without a result" in runs.loc["exits", "error"]
    assert "exit code 3" in runs.loc["dies", "error"]
    assert "BudgetExceededError" in runs.loc["overspends", "error"]
    assert runs.loc["fine", "error"] == "" and runs.loc["full", "error"] == ""
    meta = __import__("json").loads((out / "run.json").read_text())
    assert meta["status"] == "finished" and meta["error_rows"] == 4
    assert took < 120, took  # the hang cost its budget plus the grace period, not 600 s


def test_compare_refuses_a_finished_folder_without_force(tmp_path, bad_plugins, capsys):
    import pandas as pd

    out = tmp_path / "cmp"
    assert _compare(out, "fine", "--plugin", bad_plugins, "--in-process") == 0
    before = (out / "runs.csv").read_bytes()
    (out / "masks.png").write_bytes(b"stale figure")
    assert _compare(out, "fine", "--plugin", bad_plugins, "--in-process") == 2
    err = capsys.readouterr().err
    assert "already holds the results" in err and "--force" in err and len(err.strip().splitlines()) == 1
    assert (out / "runs.csv").read_bytes() == before  # untouched
    assert _compare(out, "fine", "--plugin", bad_plugins, "--in-process", "--force") == 0
    assert not (out / "masks.png").exists()  # stale figures went with the old results
    assert list(pd.read_csv(out / "runs.csv")["config"]) == ["full", "fine"]
    assert _compare(out, "fine", "--plugin", bad_plugins, "--resume", "--force") == 2


@pytest.mark.parametrize("change, field", [
    (["--budget-s", "2"], "budget"),
    (["--budget-evals", "11"], "budget"),
    (["--dtype", "float64"], "dtype"),
])
def test_compare_resume_refuses_a_different_setup(tmp_path, bad_plugins, capsys, change, field):
    out = tmp_path / "cmp"
    assert _compare(out, "fine", "--plugin", bad_plugins, "--in-process") == 0
    capsys.readouterr()
    args = ["--plugin", bad_plugins, "--in-process", "--resume"]
    budget_s = change[1] if change[0] == "--budget-s" else "1"
    evals = change[1] if change[0] == "--budget-evals" else "10"
    extra = change if change[0] == "--dtype" else []
    assert _compare(out, "fine", *args, *extra, budget_s=budget_s, evals=evals) == 2
    err = capsys.readouterr().err
    assert f"different {field}" in err and "--force" in err


def test_compare_resume_refuses_another_scene_and_damaged_files(tmp_path, capsys):
    from arraysel.run.compare import compare
    from arraysel.selectors.contract import Budget
    from arraysel.testing import ToyObjective
    from arraysel.errors import ParameterError

    out = tmp_path / "cmp"
    compare(ToyObjective(12, 6), ["uniform"], out_dir=out, budget=Budget(evaluations=5), progress=False,
            figures=False)
    with pytest.raises(ParameterError, match=r"different scene \(scene\.seed"):
        compare(ToyObjective(12, 6, seed=1), ["uniform"], out_dir=out, budget=Budget(evaluations=5),
                progress=False, figures=False, resume=True)
    with pytest.raises(ParameterError, match="n_elements is 12 in run.json, 16 now"):
        compare(ToyObjective(16, 6), ["uniform"], out_dir=out, budget=Budget(evaluations=5),
                progress=False, figures=False, resume=True)
    (out / "runs.csv").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ParameterError, match="runs.csv is damaged"):
        compare(ToyObjective(12, 6), ["uniform"], out_dir=out, budget=Budget(evaluations=5),
                progress=False, figures=False, resume=True)
    (out / "run.json").write_text("{not json")
    with pytest.raises(ParameterError, match="run.json is damaged"):
        compare(ToyObjective(12, 6), ["uniform"], out_dir=out, budget=Budget(evaluations=5),
                progress=False, figures=False, resume=True)


def test_compare_resume_records_every_selector_and_seed(tmp_path):
    import json

    from arraysel.run.compare import compare
    from arraysel.selectors.contract import Budget
    from arraysel.testing import ToyObjective

    out = tmp_path / "cmp"
    obj = ToyObjective(12, 6)
    compare(obj, ["uniform"], out_dir=out, seeds=[0], budget=Budget(evaluations=5), progress=False,
            figures=False)
    compare(obj, ["random"], out_dir=out, seeds=[1], budget=Budget(evaluations=5), progress=False,
            figures=False, resume=True)
    meta = json.loads((out / "run.json").read_text())
    assert [s["config"] for s in meta["selectors"]] == ["uniform", "random"] and meta["seeds"] == [0, 1]


@pytest.mark.parametrize("value", ["inf", "nan", "-1"])
def test_compare_refuses_non_finite_budgets(tmp_path, capsys, value):
    assert _compare(tmp_path / "cmp", "uniform", budget_s=value) == 2
    assert "--budget-s" in capsys.readouterr().err
    assert not (tmp_path / "cmp").exists()


def test_compare_api_refuses_infinite_budget(tmp_path):
    from arraysel.errors import ParameterError
    from arraysel.run.compare import compare
    from arraysel.selectors.contract import Budget
    from arraysel.testing import ToyObjective

    with pytest.raises(ParameterError, match="budget seconds"):
        compare(ToyObjective(12, 6), ["uniform"], out_dir=tmp_path, budget=Budget(seconds=float("inf")),
                progress=False, figures=False)


def test_compare_unwritable_out_fails_before_the_objective_is_built(tmp_path, capsys, monkeypatch):
    from arraysel.cli import compare as cmd

    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setattr(cmd, "build_objective", lambda *a, **k: pytest.fail("objective was built"))
    from arraysel.cli.main import main
    assert main(["compare", "--selectors", "uniform", "--scene", "toy", "--out", str(blocker / "sub"),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "not a folder" in err and len(err.strip().splitlines()) == 1
    assert main(["compare", "--selectors", "uniform", "--scene", "toy", "--out", str(blocker),
                 "--no-progress"]) == 2
    assert "is a file" in capsys.readouterr().err


# ---------------------------------------------------------------------------
# evaluate: streaming, long lines, encodings, paths, unwritable outputs
# ---------------------------------------------------------------------------



@pytest.fixture
def tiny_scene(tmp_path, monkeypatch):
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")
    path = tmp_path / "tiny.toml"
    path.write_text(TINY_SCENE)
    return str(path)


def _random_masks(path, n, ne=64, k=32, seed=0):
    rng = np.random.default_rng(seed)
    with open(path, "w") as fh:
        for s in range(0, n, 50_000):
            b = min(50_000, n - s)
            idx = np.sort(np.argsort(rng.random((b, ne)), axis=1)[:, :k], axis=1)
            fh.write("\n".join(" ".join(map(str, r)) for r in idx.tolist()) + "\n")


def test_evaluate_streams_kernels_and_rows_in_chunks(tmp_path, tiny_scene, monkeypatch):
    from arraysel.cli.main import main
    from arraysel.cli import evaluate as ev
    import pandas as pd

    monkeypatch.setattr(ev, "CHUNK_WITH_KERNELS", 7)  # several chunks
    rng = np.random.default_rng(1)
    sels = [sorted(rng.choice(8, 4, replace=False).tolist()) for _ in range(30)]
    masks = tmp_path / "m.txt"
    masks.write_text("\n".join(",".join(map(str, s)) for s in sels) + "\n")
    out, psf = tmp_path / "o.csv", tmp_path / "k.npz"
    assert main(["evaluate", "--scene", tiny_scene, "--masks", str(masks), "--out", str(out),
                 "--psf-out", str(psf), "--no-progress"]) == 0
    df = pd.read_csv(out)
    assert list(df["elements"]) == [" ".join(map(str, s)) for s in sels]
    d = np.load(psf)
    assert d["psf"].shape == (30, 16, 16) and d["psf_ref"].shape == (16, 16)
    from arraysel.objective.psf_objective import build_objective
    from arraysel.selection import masks_from_indices
    obj = build_objective(tiny_scene)
    want = obj.evaluate(masks_from_indices(sels, 8, 4), return_kernels=True)
    assert np.allclose(d["psf"], want["kernels"], atol=1e-6)
    assert np.allclose(df["Mean"], want["Mean"], rtol=1e-6)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["k.npz", "m.txt", "o.csv", "tiny.toml"]


def test_evaluate_unwritable_psf_out_leaves_no_csv(tmp_path, tiny_scene, capsys):
    from arraysel.cli.main import main

    masks = tmp_path / "m.txt"
    masks.write_text("0 1 2 3\n")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    out = tmp_path / "o.csv"
    assert main(["evaluate", "--scene", tiny_scene, "--masks", str(masks), "--out", str(out),
                 "--psf-out", str(blocker / "k.npz")]) == 2
    err = capsys.readouterr().err
    assert "--psf-out" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


@pytest.mark.parametrize("case", ["missing", "folder", "latin1", "binary", "no-selection", "parent-is-file"])
def test_evaluate_path_and_encoding_errors_are_one_line(tmp_path, capsys, monkeypatch, case):
    from arraysel.cli.main import main
    from arraysel.cli import compare as cmp

    monkeypatch.setattr(cmp, "build_objective", lambda *a, **k: pytest.fail("objective was built"))
    masks = tmp_path / "m.txt"
    out = tmp_path / "o.csv"
    if case == "folder":
        masks.mkdir()
    elif case == "latin1":
        masks.write_bytes("0 1 2 # caf\u00e9\n".encode("latin-1"))
    elif case == "binary":
        masks.write_bytes(bytes(range(256)) * 4)
    elif case == "no-selection":
        masks.write_text("# nothing\n\n")
    elif case == "parent-is-file":
        masks.write_text(" ".join(map(str, range(32))) + "\n")
        (tmp_path / "f").write_text("x")
        out = tmp_path / "f" / "o.csv"
    code = main(["evaluate", "--scene", "toy", "--masks", str(masks), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert err.startswith("arraysel evaluate: error:")
    assert "Traceback" not in err
    assert not out.exists()
    want = {"missing": "does not exist", "folder": "is a folder", "latin1": "not UTF-8",
            "binary": "not UTF-8", "no-selection": "no selection", "parent-is-file": "not a folder"}[case]
    assert want in err


def test_long_mask_lines_are_linear(tmp_path):
    from arraysel.errors import SelectionError
    from arraysel.io.masks import iter_mask_lines, parse_elements

    idx = list(range(40_000))
    t0 = time.perf_counter()
    assert parse_elements(" ".join(map(str, idx)), 100_000) == idx
    with pytest.raises(SelectionError, match=r"repeated element index \[7\]"):
        parse_elements(" ".join(map(str, idx + [7])), 100_000)
    assert time.perf_counter() - t0 < 2.0
    masks = tmp_path / "m.txt"
    masks.write_text(" ".join(map(str, idx)) + "\n")
    with pytest.raises(SelectionError, match="line 1: expected k = 32 elements, got 40000"):
        list(iter_mask_lines(str(masks), 100_000, 32))
    masks.write_text("1" * (2 ** 21))  # one 2 MB line without a newline: refused, not read whole
    with pytest.raises(SelectionError, match="line 1: longer than"):
        list(iter_mask_lines(str(masks), 64, 32))


# VmHWM: the peak RSS of this process's own memory (ru_maxrss would carry the parent's peak
# across the exec of a vfork-ed child)
_MEMORY_SCRIPT = textwrap.dedent("""
    import sys
    from arraysel.cli.main import main
    code = main(["evaluate", "--scene", "toy", "--masks", sys.argv[1], "--out", sys.argv[2], "--no-progress"])
    with open("/proc/self/status") as fh:
        kb = next(int(l.split()[1]) for l in fh if l.startswith("VmHWM:"))
    print("peak_mib", kb / 1024)
    sys.exit(code)
""")


def _peak_evaluate(tmp_path, n) -> float:
    masks, out = tmp_path / f"m{n}.txt", tmp_path / f"o{n}.csv"
    _random_masks(masks, n)
    proc = subprocess.run([sys.executable, "-c", _MEMORY_SCRIPT, str(masks), str(out)], capture_output=True,
                          text=True, timeout=1800)
    assert proc.returncode == 0, proc.stderr
    with open(out) as fh:
        assert sum(1 for _ in fh) == n + 1
    return float(proc.stdout.split("peak_mib")[1])


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads VmHWM from /proc (Linux)")
def test_evaluate_memory_does_not_grow_with_the_number_of_masks(tmp_path):
    small, large = _peak_evaluate(tmp_path, 1_000), _peak_evaluate(tmp_path, 25_000)
    assert large < small + 100, (small, large)  # MiB: bounded by the chunk, not the input


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads VmHWM from /proc (Linux)")
def test_evaluate_a_million_masks_under_a_memory_ceiling(tmp_path):
    peak = _peak_evaluate(tmp_path, 1_000_000)
    assert peak < 600, peak  # MiB (~370 measured; holding every mask and result needed ~9 GB before)


def test_scene_relative_base_resolves_next_to_the_scene_file(tmp_path, monkeypatch):
    from arraysel.scenes.schema import load_scene

    folder = tmp_path / "scenes"
    (folder / "sub").mkdir(parents=True)
    (folder / "parent.toml").write_text('name = "parent"\nbase = "paper"\n[selection]\nk = 20\n')
    (folder / "sub" / "child.toml").write_text('base = "../parent.toml"\n[transmit]\nn_tx = 3\n')
    (folder / "child.toml").write_text('base = "parent.toml"\n[transmit]\nn_tx = 3\n')
    monkeypatch.chdir(tmp_path)  # not the scene folder
    for path in (folder / "child.toml", folder / "sub" / "child.toml"):
        scene = load_scene(str(path))
        assert scene.k == 20 and scene.get("transmit", "n_tx") == 3


@pytest.mark.parametrize("case", ["folder", "latin1"])
def test_scene_file_errors_are_one_line(tmp_path, capsys, case):
    from arraysel.cli.main import main

    path = tmp_path / "bad.toml"
    if case == "folder":
        path.mkdir()
    else:
        path.write_bytes('name = "caf\u00e9"\n'.encode("latin-1"))
    masks = tmp_path / "m.txt"
    masks.write_text("0 1 2\n")
    for argv in (["evaluate", "--masks", str(masks), "--out", str(tmp_path / "o.csv")],
                 ["psf", "--out", str(tmp_path / "p.npz")]):
        assert main([*argv, "--scene", str(path)]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and ("is a folder" in err or "not UTF-8" in err), err


# ---------------------------------------------------------------------------
# Python API and the example notebook
# ---------------------------------------------------------------------------

def test_import_arraysel_is_light_and_exposes_the_api():
    code = ("import sys, arraysel as asel; heavy = [m for m in ('torch', 'pandas', 'matplotlib') if m in sys.modules]; "
            "assert not heavy, heavy; "
            "assert callable(asel.load_scene) and callable(asel.compare) and asel.Objective.__name__ == 'Objective'; "
            "print('ok')")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0 and "ok" in proc.stdout, proc.stderr
    import arraysel
    assert {"load_scene", "Objective", "compare", "build_objective"} <= set(dir(arraysel))
    with pytest.raises(AttributeError):
        arraysel.no_such_thing


def test_api_compare_returns_dataframes_and_figures(tmp_path):
    import pandas as pd
    from matplotlib.figure import Figure

    import arraysel as asel

    res = asel.compare("toy", ["uniform", "random"], seeds=[0, 1], budget_s=5, budget_evals=20,
                       out_dir=tmp_path / "cmp", progress=False)
    assert isinstance(res.table, pd.DataFrame) and list(res.table["config"]) == ["full", "uniform", "random"]
    # full, uniform once (deterministic), random once per seed
    assert isinstance(res.runs, pd.DataFrame) and len(res.runs) == 4
    assert set(res.figures) == {"masks", "psfs", "profiles", "trace", "anytime"}
    assert all(isinstance(f, Figure) for f in res.figures.values())
    from arraysel.errors import ParameterError
    with pytest.raises(ParameterError, match="already holds"):
        asel.compare("toy", ["uniform"], budget_evals=5, out_dir=tmp_path / "cmp", progress=False)


def _notebook_code(path: Path) -> list[str]:
    import json

    nb = json.loads(path.read_text())
    return ["".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code"]


def test_example_notebook_is_valid_and_uses_the_public_api():
    cells = _notebook_code(ROOT / "examples" / "quickstart.ipynb")
    assert cells and "import arraysel as asel" in cells[0]
    for src in cells:
        compile(src, "quickstart.ipynb", "exec")


@pytest.mark.slow
def test_example_notebook_runs_top_to_bottom(tmp_path, monkeypatch):
    """Every code cell, in order, in one namespace (as a kernel would), on the paper scene."""
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    for src in _notebook_code(ROOT / "examples" / "quickstart.ipynb"):
        exec(compile(src, "quickstart.ipynb", "exec"), ns)
    assert list(ns["result"].table["config"]) == ["full", "uniform", "random"]


def test_compare_outputs_follow_the_umask(tmp_path):
    import arraysel as asel

    old = os.umask(0o022)
    try:
        res = asel.compare("toy", ["uniform"], budget_evals=5, out_dir=tmp_path / "cmp", progress=False)
    finally:
        os.umask(old)
    files = list(Path(res.out_dir).iterdir())
    assert len(files) >= 9
    for f in files:  # folders (the IOHprofiler data) get the umask's 0755
        assert stat.S_IMODE(f.stat().st_mode) == (0o755 if f.is_dir() else 0o644), f


def test_license_and_citation():
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License")
    yaml = pytest.importorskip("yaml")
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    titles = [r["title"] for r in cff["references"]]
    assert "End-to-end optimization of sparse ultrasound linear probes" in titles
    assert any("PyMUST" in t for t in titles) and cff["license"] == "MIT"

