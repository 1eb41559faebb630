"""Hostile cases, cache states: the cache owns only what it wrote, an unusable cache folder means
building without it (one warning line), an inconsistent manifest is damage (rebuilt).

Each case asserts that nothing is lost (foreign files keep their content), that the numbers are
right (a rebuilt or uncached state equals a fresh one), a one-line message and the exit code.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

from arraysel.io import cache
from scene_texts import TINY_SCENE

ROOT = Path(__file__).resolve().parents[2]
AS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0
SETPRIV = shutil.which("setpriv")


def _state(seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    return {"V": torch.randn(4000, generator=g), "meta": torch.tensor([3, 4, 5]), "s": torch.tensor(2.5)}


def _builder(seed: int = 0):
    calls = []

    def build():
        calls.append(1)
        return _state(seed)
    return build, calls


def _same(a: dict, b: dict) -> bool:
    return set(a) == set(b) and all(torch.equal(a[k], b[k]) for k in a)


def _run(args, env, cwd=None, user=None, timeout=300):
    """``python -m arraysel.cli.main ARGS`` in a child (as ``user`` through setpriv when given)."""
    cmd = [sys.executable, "-c", "import sys; from arraysel.cli.main import main; sys.exit(main())", *args]
    if user is not None:
        cmd = [SETPRIV, f"--reuid={user}", f"--regid={user}", "--clear-groups", *cmd]
    return subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, **env}, cwd=cwd,
                          timeout=timeout)


def _snapshot(folder: Path) -> dict:
    """Every path under ``folder`` (links not followed) -> its bytes, link target or 'dir'."""
    out = {}
    for root, dirs, files in os.walk(folder):
        for d in dirs:
            p = Path(root, d)
            out[str(p.relative_to(folder))] = f"link:{os.readlink(p)}" if p.is_symlink() else "dir"
        for f in files:
            p = Path(root, f)
            out[str(p.relative_to(folder))] = f"link:{os.readlink(p)}" if p.is_symlink() else p.read_bytes()
    return out


@pytest.fixture
def cache_folder(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv("ARRAYSEL_CACHE", str(folder))
    monkeypatch.delenv("ARRAYSEL_CACHE_VERIFY", raising=False)
    return folder


def _foreign(folder: Path, outside: Path) -> None:
    """Things a user keeps in a folder that ARRAYSEL_CACHE names."""
    (folder / ".git" / "objects").mkdir(parents=True)
    (folder / ".git" / "HEAD").write_text("ref: refs/heads/main\n")
    (folder / ".git" / "objects" / "ab").write_bytes(b"\x00blob")
    (folder / "notes.txt").write_text("my notes\n")
    (folder / "results.tmp").write_text("a file of mine ending in .tmp\n")
    (folder / "data.lock").write_text("not a cache lock\n")
    like = folder / cache.entry_name("t", ("looks-like",))   # named like an entry, holds a foreign file
    like.mkdir()
    (like / "manifest.json").write_text("{}")
    (like / "thesis.tex").write_text("\\documentclass{article}\n")
    outside.mkdir()
    (outside / "precious.txt").write_text("outside the cache\n")
    os.symlink(outside, folder / cache.entry_name("t", ("a-link",)))  # named like an entry, a link
    leftover_like = folder / f".{cache.entry_name('t', ('x',))}.999999999.0123abcd.tmp"
    leftover_like.mkdir()                                   # named like a leftover, holds a folder
    (leftover_like / "sub").mkdir()


def test_cache_clear_removes_only_what_the_cache_wrote(cache_folder, tmp_path, capsys):
    built = cache.load_or_build("t", ("k",), _builder()[0])
    cache.load_or_build("t", ("k2",), _builder(1)[0])
    stale = cache.entry_name("t", ("stale",))
    (cache_folder / f".{stale}.999999999-{'0' * 6}.0123abcd.tmp").mkdir()    # another host's: kept
    dead = cache_folder / f".{stale}.999999999.0123abcd.tmp"                   # a dead writer's
    dead.mkdir()
    (dead / "V.npy").write_bytes(b"partial")
    (cache_folder / f"{cache.entry_name('psf-basis', ('old',))}.pt").write_bytes(b"old format")
    _foreign(cache_folder, tmp_path / "outside")
    before = _snapshot(cache_folder)
    outside = _snapshot(tmp_path / "outside")

    from arraysel.cli.main import main

    capsys.readouterr()
    assert main(["cache", "info"]) == 0
    info = capsys.readouterr()
    lines = {ln.split()[0]: ln for ln in info.out.splitlines()[2:]}
    for name in (".git", "notes.txt", "results.tmp", "data.lock", cache.entry_name("t", ("looks-like",)),
                 cache.entry_name("t", ("a-link",))):
        assert "foreign" in lines[name] and "damaged" not in lines[name], lines[name]
    assert "ok" in lines[cache.entry_name("t", ("k",))]
    assert "leftover of an interrupted write" in lines[dead.name]

    assert main(["cache", "clear"]) == 0
    out = capsys.readouterr()
    assert len(out.out.strip().splitlines()) == 1 and "foreign" in out.out and out.err == "", out
    after = _snapshot(cache_folder)
    foreign = {k: v for k, v in before.items()
               if not k.startswith(("t-", ".t-", "psf-basis-")) or "looks-like" in k or k.startswith(
                   (cache.entry_name("t", ("looks-like",)), cache.entry_name("t", ("a-link",)),
                    f".{cache.entry_name('t', ('x',))}"))}
    assert foreign and all(after.get(k) == v for k, v in foreign.items()), sorted(set(foreign) - set(after))
    assert _snapshot(tmp_path / "outside") == outside          # nothing followed through the link
    gone = [cache.entry_name("t", ("k",)), cache.entry_name("t", ("k2",)), dead.name,
            f"{cache.entry_name('t', ('k',))}.lock", f"{cache.entry_name('psf-basis', ('old',))}.pt"]
    assert not [g for g in gone if os.path.lexists(cache_folder / g)]
    assert (cache_folder / f".{stale}.999999999-{'0' * 6}.0123abcd.tmp").is_dir()
    # the cache works in the same folder afterwards, and clear leaves the foreign files again
    build, calls = _builder()
    assert _same(cache.load_or_build("t", ("k",), build), built) and calls == [1]


_HOLDER = textwrap.dedent("""
    import sys, time
    from filelock import FileLock
    lock = FileLock(sys.argv[1])
    lock.acquire()
    print("held", flush=True)
    time.sleep(60)
""")


def test_cache_clear_leaves_an_entry_being_built_and_a_live_writers_folder(cache_folder):
    cache.load_or_build("t", ("busy",), _builder()[0])
    name = cache.entry_name("t", ("busy",))
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(cache_folder / f"{name}.lock")],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        live = cache_folder / f".{cache.entry_name('t', ('w',))}.{holder.pid}.0123abcd.tmp"
        live.mkdir()
        (live / "V.npy").write_bytes(b"being written")
        n, _ = cache.clear(str(cache_folder))
        assert n == 0
        assert (cache_folder / name / "manifest.json").is_file() and (live / "V.npy").is_file()
        assert "being written by process" in {e["name"]: e["status"] for e in cache.list_entries()}[live.name]
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    n, _ = cache.clear(str(cache_folder))        # the holder is gone: now both go
    assert n == 3 and sorted(os.listdir(cache_folder)) == []


def test_a_build_never_replaces_a_foreign_file_named_like_its_entry(cache_folder, caplog):
    name = cache.entry_name("t", ("k",))
    cache_folder.mkdir()
    (cache_folder / name).write_text("a file of mine\n")
    build, calls = _builder()
    with caplog.at_level(logging.WARNING, logger="arraysel.io.cache"):
        got = cache.load_or_build("t", ("k",), build)
    assert _same(got, _state()) and calls == [1]
    assert (cache_folder / name).read_text() == "a file of mine\n"
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 1 and "without the cache" in msgs[0] and "did not write" in msgs[0], msgs


# ------------------------------------------------------------------ unusable cache folders
def _unusable(case: str, tmp_path: Path) -> Path:
    if case == "file-in-place":
        (tmp_path / "cachefile").write_text("a file where the folder should be\n")
        return tmp_path / "cachefile"
    if case == "below-a-file":
        (tmp_path / "afile").write_text("x")
        return tmp_path / "afile" / "cache"
    if case == "lock-is-a-folder":
        folder = tmp_path / "cache"
        (folder / f"{cache.entry_name('t', ('k',))}.lock").mkdir(parents=True)
        return folder
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["file-in-place", "below-a-file", "lock-is-a-folder"])
def test_unusable_cache_folder_builds_without_the_cache_in_one_line(tmp_path, monkeypatch, caplog, case):
    folder = _unusable(case, tmp_path)
    monkeypatch.setenv("ARRAYSEL_CACHE", str(folder))
    build, calls = _builder()
    with caplog.at_level(logging.WARNING, logger="arraysel.io.cache"):
        got = cache.load_or_build("t", ("k",), build, what="a test state")
        again = cache.load_or_build("t", ("k",), build, what="a test state")
    assert _same(got, _state()) and _same(again, _state()) and calls == [1, 1]
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 2 and all("cannot be used" in m and "without the cache" in m for m in msgs), msgs
    assert all("\n" not in m for m in msgs)




def _psf_command(base: Path, env: dict, user=None, name="psf.npz"):
    scene = _write(base)
    work = base / "work"
    work.mkdir(exist_ok=True)
    os.chmod(work, 0o777)
    proc = _run(["psf", "--scene", scene, "--elements", "0,2,4,6", "--out", str(work / name)], env,
                user=user, cwd=str(base))
    return proc, work / name


def _write(base: Path) -> str:
    scene = base / "tiny.toml"
    if not scene.exists():
        scene.write_text(TINY_SCENE)
    return str(scene)


@pytest.fixture
def open_tmp():
    """A folder another user can enter (pytest's tmp_path is private to this user)."""
    import tempfile

    path = Path(tempfile.mkdtemp(prefix="arraysel-hostile-"))
    os.chmod(path, 0o755)
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(scope="module")
def reference_kernel(tmp_path_factory):
    import numpy as np

    proc, out = _psf_command(tmp_path_factory.mktemp("ref"), {"ARRAYSEL_CACHE": "off"})
    assert proc.returncode == 0, proc.stderr
    return np.load(out)["psf"]


def _other_user_can_run(base: Path) -> bool:
    """Whether uid 65534 can run arraysel here through setpriv (root only)."""
    if not (AS_ROOT and SETPRIV):
        return False
    probe = subprocess.run([SETPRIV, "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable, "-c",
                            "import arraysel, torch, filelock"], capture_output=True, cwd=str(base),
                           env=os.environ.copy())
    return probe.returncode == 0


def _basis_entry(scene: str, monkeypatch) -> str:
    """The cache entry name of the scene's PSF basis (seen by building it with the cache off)."""
    from arraysel.objective.psf_objective import build_objective

    names = []
    real = cache.load_or_build

    def spy(kind, key_parts, *a, **k):
        names.append(cache.entry_name(kind, key_parts))
        return real(kind, key_parts, *a, **k)

    from arraysel.objective import psf_objective

    with monkeypatch.context() as m:
        m.setenv("ARRAYSEL_CACHE", "off")
        m.setattr(cache, "load_or_build", spy)
        m.setattr(psf_objective, "_CACHE", {})  # no objective kept from (or for) another test
        build_objective(scene)
    assert len(names) == 1, names
    return names[0]


@pytest.mark.slow
@pytest.mark.parametrize("case", ["file-in-place", "lock-is-a-folder", "not-writable", "lock-of-another-user"])
def test_cli_with_an_unusable_cache_folder_warns_once_and_computes(open_tmp, reference_kernel, monkeypatch, case):
    """The ``psf`` command end to end, each case real: a file in the folder's place; a folder in
    the place of the basis entry's lock file; a folder the command's user cannot write and a lock
    file (mode 0600) of another user: the folder and lock belong to root and the command runs as
    uid 65534 through setpriv when the tests run as root; as a non-root user the folder is made
    read-only with chmod (which binds its owner), and the other-user lock is skipped (it needs
    root to make)."""
    import numpy as np

    base, user = open_tmp, None
    if case == "file-in-place":
        folder = base / "cachefile"
        folder.write_text("a file where the folder should be\n")
    else:
        folder = base / "cache"
        folder.mkdir()
    if case == "lock-is-a-folder":
        (folder / f"{_basis_entry(_write(base), monkeypatch)}.lock").mkdir()
    if case in ("not-writable", "lock-of-another-user"):
        if AS_ROOT:
            if not _other_user_can_run(base):
                pytest.skip("needs setpriv and a checkout that uid 65534 can read")
            user = 65534
            os.chmod(folder, 0o755)  # root's folder: uid 65534 cannot write it
        elif case == "not-writable":
            os.chmod(folder, 0o555)
        else:
            pytest.skip("a lock file of another user needs root to make")
    if case == "lock-of-another-user":
        lock = folder / f"{_basis_entry(_write(base), monkeypatch)}.lock"
        lock.write_bytes(b"")
        os.chmod(lock, 0o600)
        os.chmod(folder, 0o777)  # the folder is writable: only the lock is in the way
    env = {"ARRAYSEL_CACHE": str(folder)}
    if user is not None:  # the other user's own home (numba keeps its compiled kernels there)
        (base / "home").mkdir()
        os.chmod(base / "home", 0o777)
        env["HOME"] = str(base / "home")
    proc, out = _psf_command(base, env, user=user)
    assert proc.returncode == 0, proc.stderr
    warn = [ln for ln in proc.stderr.splitlines() if "cannot be used" in ln]
    assert len(warn) == 1 and "without the cache" in warn[0], proc.stderr
    assert "Traceback" not in proc.stderr
    assert np.array_equal(np.load(out)["psf"], reference_kernel)
    if case == "lock-of-another-user":
        assert "belongs to user id" in warn[0]


# ------------------------------------------------------------------ inconsistent manifests
def _edit(entry: Path, change) -> None:
    m = json.loads((entry / "manifest.json").read_text())
    change(m)
    (entry / "manifest.json").write_text(json.dumps(m))


def _tensor(name):
    return lambda m: m["tensors"][name]


MANIFEST_DAMAGE = {
    "block-zero": lambda m: m.update(block=0),
    "block-negative": lambda m: m.update(block=-16),
    "block-text": lambda m: m.update(block="16"),
    "block-float": lambda m: m.update(block=16.5),
    "tensors-empty": lambda m: m.update(tensors={}),
    "tensors-list": lambda m: m.update(tensors=[1, 2]),
    "tensor-missing": lambda m: m["tensors"].pop("V"),
    "entry-not-object": lambda m: m["tensors"].update(V=[1, 2]),
    "bytes-text": lambda m: _tensor("V")(m).update(bytes="16128"),
    "bytes-bool": lambda m: _tensor("s")(m).update(bytes=True),
    "bytes-negative": lambda m: _tensor("V")(m).update(bytes=-1),
    "bytes-too-small": lambda m: _tensor("V")(m).update(bytes=100),
    "bytes-not-the-file": lambda m: _tensor("V")(m).update(bytes=_tensor("V")(m)["bytes"] + 64),
    "shape-text": lambda m: _tensor("V")(m).update(shape=["a"]),
    "shape-negative": lambda m: _tensor("V")(m).update(shape=[-4000]),
    "shape-mismatch": lambda m: _tensor("V")(m).update(shape=[2000, 2]),
    "dtype-object": lambda m: _tensor("V")(m).update(dtype="|O"),
    "dtype-garbage": lambda m: _tensor("V")(m).update(dtype="float77"),
    "file-outside": lambda m: _tensor("V")(m).update(file="../V.npy"),
    "file-twice": lambda m: _tensor("s")(m).update(file=_tensor("V")(m)["file"]),
    "digests-missing": lambda m: _tensor("V")(m).pop("crc32"),
    "digests-count": lambda m: _tensor("V")(m).update(crc32=["0"] * 3),
    "digests-numbers": lambda m: _tensor("V")(m).update(crc32=[12345]),
}


@pytest.mark.parametrize("damage", sorted(MANIFEST_DAMAGE))
def test_inconsistent_manifest_is_damaged_and_rebuilt(cache_folder, caplog, damage):
    def check(state):  # the caller's view: it needs V, meta and s
        for key in ("V", "meta", "s"):
            if key not in state:
                raise KeyError(key)

    cache.load_or_build("t", ("k",), _builder()[0], check=check)
    entry = cache_folder / cache.entry_name("t", ("k",))
    _edit(entry, MANIFEST_DAMAGE[damage])
    info = {e["name"]: e["status"] for e in cache.list_entries()}
    build, calls = _builder()
    with caplog.at_level(logging.WARNING, logger="arraysel.io.cache"):
        got = cache.load_or_build("t", ("k",), build, check=check)
    assert _same(got, _state()) and calls == [1]                  # rebuilt: the right numbers
    # the build's announcement ("building ... (first run with these settings)") is a notice, not a problem
    msgs = [r.getMessage() for r in caplog.records if "(first run with these settings" not in r.getMessage()]
    assert len(msgs) == 1 and "damaged" in msgs[0] and "\n" not in msgs[0], msgs
    if damage != "tensor-missing":  # the manifest alone shows it (a missing tensor: the caller)
        assert info[entry.name].startswith("damaged"), info
    build, calls = _builder()
    assert _same(cache.load_or_build("t", ("k",), build, check=check), _state()) and calls == []  # fixed


def test_psf_basis_with_a_tensor_missing_from_its_manifest_is_rebuilt(cache_folder, tmp_path, caplog, monkeypatch):
    """The real consumer: a basis whose manifest lost a tensor entry (U, a stored basis's singular
    vectors) is damage, not a traceback and not a different basis."""
    from arraysel.objective import psf_objective
    from arraysel.selection import masks_from_indices

    def build_objective(scene):  # a new objective each time (the process keeps built ones)
        monkeypatch.setattr(psf_objective, "_CACHE", {})
        return psf_objective.build_objective(scene)

    scene = _write(tmp_path)
    sel = masks_from_indices([[0, 2, 4, 6]], 8, 4)
    want = build_objective(scene).evaluate(sel, return_kernels=True)["kernels"]
    entry = next(p for p in cache_folder.iterdir() if p.name.startswith("psf-basis-") and p.is_dir())
    tensors = json.loads((entry / "manifest.json").read_text())["tensors"]
    drop = "U" if "U" in tensors else "A"
    _edit(entry, lambda m: m["tensors"].pop(drop))
    with caplog.at_level(logging.WARNING):
        got = build_objective(scene).evaluate(sel, return_kernels=True)["kernels"]
    assert torch.equal(torch.as_tensor(got), torch.as_tensor(want))
    assert any("damaged" in r.getMessage() and repr(drop) in r.getMessage() for r in caplog.records), \
        [r.getMessage() for r in caplog.records]
    assert drop in json.loads((entry / "manifest.json").read_text())["tensors"]   # rebuilt in full


def test_clear_in_a_folder_of_many_foreign_files(cache_folder):
    """A folder full of the user's files is listed, not walked into or removed (a smoke check of
    the classification on 500 names; no timing is asserted)."""
    cache_folder.mkdir()
    for i in range(500):
        (cache_folder / f"note{i}.txt").write_text("x")
    build, calls = _builder()
    cache.load_or_build("t", ("k",), build)
    t0 = time.perf_counter()
    n, _ = cache.clear(str(cache_folder))
    assert n == 2 and len(os.listdir(cache_folder)) == 500
    assert time.perf_counter() - t0 < 600  # a guard against a hang, not a speed figure
