"""The output folder of ``arraysel compare``: which files are results, whether a folder may be
written (``--resume`` / ``--force``), whether a resumed run matches the one on disk, and the lock
that keeps one compare at a time in a folder (:func:`lock_out_dir`)."""
from __future__ import annotations

import contextlib
import errno
import json
import os
import threading
import time
from pathlib import Path

from arraysel.errors import ParameterError, error_text as _error_text
from arraysel.io.atomic import check_writable

__all__ = ["RESULT_FILES", "RESUME_FIELDS", "LOCK_NAME", "check_out_dir", "check_resume", "remove_results",
           "lock_out_dir"]

#: files ``compare`` writes in its folder (``--force`` removes these and nothing else)
RESULT_FILES = ("runs.csv", "table1.csv", "stats.csv", "trace.csv", "trace_nevergrad.csv", "ioh", "run.json",
                "masks.png", "psfs.png", "profiles.png", "trace.png", "anytime.png")
#: the lock file of a folder a compare is writing (held with ``flock`` for the whole run; it holds
#: the pid of the holder, and goes when the run ends)
LOCK_NAME = ".arraysel-compare.lock"
#: fields of ``run.json`` that a resumed run must share with the new one
RESUME_FIELDS = ("scene", "n_elements", "k", "dtype", "budget")


def check_out_dir(out: str | os.PathLike, *, resume: bool = False, force: bool = False) -> dict | None:
    """Check ``out`` before any work: a folder (or creatable), writable, and not holding the
    results of another compare run unless ``resume`` (continue it) or ``force`` (replace it).

    Returns the old ``run.json`` content when resuming (``None`` otherwise, or when there is
    nothing to resume). Raises :class:`ParameterError` with a one-line message."""
    out = Path(out)
    if resume and force:
        raise ParameterError("--resume and --force exclude each other: --resume continues the run in --out, "
                             "--force replaces it")
    if out.exists() and not out.is_dir():
        raise ParameterError(f"--out {str(out)!r} is a file, not a folder")
    check_writable(out / "run.json", "--out")
    held = [n for n in ("runs.csv", "run.json", "table1.csv") if (out / n).exists()]
    if not held:
        return None
    meta = None
    if (out / "run.json").exists():
        try:
            meta = json.loads((out / "run.json").read_bytes().decode("utf-8"))
            if not isinstance(meta, dict):
                raise ValueError("not a JSON object")
        except (OSError, ValueError) as exc:
            if resume:
                raise ParameterError(f"--resume: {out / 'run.json'} is damaged ({_error_text(exc)}); rerun "
                                     f"with --force to start over, or choose another --out") from None
            meta = None
    if resume:
        if meta is None:
            raise ParameterError(f"--resume: {out} has no run.json describing its runs; rerun with --force to "
                                 f"start over, or choose another --out")
        return meta
    if force:
        return None
    status = (meta or {}).get("status", "unknown")
    raise ParameterError(f"--out {str(out)!r} already holds the results of a compare run (status: {status}); "
                         f"rerun with --resume to finish it, with --force to replace it, or choose another --out")


def _plain(value):
    """``value`` as ``run.json`` stores it (JSON round trip, ``default=str``)."""
    return json.loads(json.dumps(value, default=str))


def check_resume(old: dict, now: dict, out) -> None:
    """Refuse to resume when a field of :data:`RESUME_FIELDS` differs between ``old`` (run.json)
    and ``now``; the message names the field and both values (the first differing key of a
    scene)."""
    for field in RESUME_FIELDS:
        if field not in now:
            continue
        a, b = old.get(field), _plain(now[field])
        if a == b:
            continue
        detail = f"{a!r} in run.json, {b!r} now"
        if isinstance(a, dict) and isinstance(b, dict):
            keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
            if keys:
                detail = f"{field}.{keys[0]} is {a.get(keys[0])!r} in run.json, {b.get(keys[0])!r} now"
        raise ParameterError(f"--resume: the runs in {out} were made with a different {field} ({detail}); "
                             f"rerun with --force to start over, or choose another --out")


def remove_results(out: str | os.PathLike) -> None:
    """Remove the files of :data:`RESULT_FILES` from ``out`` (``--force``)."""
    import shutil

    for name in RESULT_FILES:
        path = Path(out) / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
            continue
        try:
            path.unlink()
        except FileNotFoundError:
            pass


# ---------------------------------------------------------------------------
# the lock of a folder
# ---------------------------------------------------------------------------

_HELD: dict[str, list] = {}   # real path of a locked folder -> [fd, depth] (this process's locks)
_HELD_LOCK = threading.Lock()


def _holder(fd: int) -> str:
    """The pid written in a lock file (``"unknown"`` while its holder has not written it yet)."""
    for _ in range(20):
        try:
            text = os.pread(fd, 64, 0).decode("ascii", "replace").strip()
        except OSError:
            text = ""
        if text.isdigit():
            return text
        time.sleep(0.05)
    return "unknown"


def _acquire(path: str, what: str, shown: str) -> int:
    from arraysel.errors import ParameterError
    from arraysel.io.atomic import file_mode

    try:
        import fcntl
    except ImportError:  # no flock on this platform (Windows): the folder is not locked
        return os.open(path, os.O_RDWR | os.O_CREAT, file_mode())

    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, file_mode())
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):  # a file system without locks
                import logging
                logging.getLogger(__name__).warning("arraysel: cannot lock %s %r (%s); going on without the lock",
                                                    what, shown, exc.strerror)
                return fd
            pid = _holder(fd)
            os.close(fd)
            raise ParameterError(f"{what} {shown!r} is in use by another arraysel compare "
                                 f"(pid {pid}); wait for it to end, or choose another {what}") from None
        try:  # the file may have been removed by a holder that just ended: lock the one in place
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
            return fd
        os.close(fd)


@contextlib.contextmanager
def lock_out_dir(out: str | os.PathLike, what: str = "--out"):
    """Hold the folder ``out`` (created) for the ``with`` block: another process that asks for it
    meanwhile is refused with :class:`~arraysel.errors.ParameterError` naming the folder and this
    process's pid. The lock is an ``flock`` on :data:`LOCK_NAME`, so the kernel releases it when
    its holder dies (a lock file left by a killed run is simply taken over). Re-entrant within a
    process."""
    from arraysel.errors import ParameterError

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ParameterError(f"{what} {str(out)!r} is a file, not a folder")
    check_writable(out / LOCK_NAME, what)
    created = []  # the folders made here, deepest first: removed again if nothing was written
    probe = out.absolute()
    while not probe.exists() and probe != probe.parent:
        created.append(probe)
        probe = probe.parent
    out.mkdir(parents=True, exist_ok=True)
    path = os.path.join(os.path.realpath(out), LOCK_NAME)
    with _HELD_LOCK:
        held = _HELD.get(path)
        if held is not None:
            held[1] += 1
        else:
            try:
                _HELD[path] = [_acquire(path, what, str(out)), 1, created]
            except BaseException:
                _remove_empty(created)
                raise
    try:
        yield
    finally:
        with _HELD_LOCK:
            held = _HELD[path]
            held[1] -= 1
            if held[1] == 0:
                del _HELD[path]
                with contextlib.suppress(OSError):
                    os.unlink(path)  # while still held: a waiter re-checks the file it locked
                os.close(held[0])
                _remove_empty(held[2])  # folders made for a command that wrote nothing (refused options)


def _remove_empty(folders) -> None:
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:  # not empty: a result is in it
            return
