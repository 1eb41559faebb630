"""On-disk cache of precomputed tensors (the PSF fast path's pair basis).

Location
    ``$ARRAYSEL_CACHE`` when set (``off``, ``none``, ``0`` or empty disable the
    cache), else the platform's user cache folder (``platformdirs``:
    ``~/.cache/arraysel`` on Linux, ``~/Library/Caches/arraysel`` on macOS,
    ``%LOCALAPPDATA%\\arraysel\\Cache`` on Windows). ``arraysel cache path|info|clear``
    shows and clears it.

Format (``FORMAT`` 1)
    One folder per entry, ``<kind>-<key>/`` (the key: 24 hex digits hashing
    everything the content depends on), holding one ``<name>.npy`` file per
    named tensor and ``manifest.json``: for each tensor its file, dtype, shape,
    size in bytes and the CRC-32 of every :data:`BLOCK` bytes of the file
    (entries written by earlier versions carry SHA-256 digests instead, and are
    verified with them). An entry is written into a temporary folder
    ``.<kind>-<key>.<pid>-<host>.<random>.tmp`` and renamed into place once
    complete (``manifest.json`` last), so a reader never sees a partial entry; a
    temporary folder left by a killed writer is removed by the next builder of
    that entry (under the lock) or by ``arraysel cache clear`` (which leaves a
    live writer's alone).

What the cache owns
    The folder may hold other things (it may be a folder the user chose, with a
    ``.git`` or notes in it). The cache touches only names it writes
    (:func:`classify`): entries (``<kind>-<key>`` folders holding only ``.npy``
    files, ``manifest.json`` and ``checked.json``), their lock files ``<kind>-<key>.lock``, their
    temporary folders, and files of the older single-file format
    (``<kind>-<key>.pt``). Anything else is *foreign*: listed as such by
    ``arraysel cache info``, never removed or replaced, neither by ``clear`` nor
    by a build (a build whose entry's name is taken by a foreign file builds
    without the cache).

Loading
    Tensors are memory-mapped (``numpy.load(mmap_mode="c")`` then
    ``torch.from_numpy``): nothing is copied, and pages are read from disk when
    first touched. Before the tensors are handed out, the file sizes and the
    ``.npy`` headers are checked against the manifest, and every block's
    checksum is verified (``$ARRAYSEL_CACHE_VERIFY=full``, the default): any
    burst of flipped bits up to 32 bits long, and any odd number of flipped
    bits, is caught with certainty, other damage with probability 1 - 2^-32
    per block. The checksums guard against damage (a disk, a killed or
    concurrent writer), not against tampering. CRC-32 runs at 2.6 GB/s a core
    here against 1.4 for SHA-256, which cost a cold start on the paper scene
    about 0.45 s. The checking runs on a few threads
    and, since it touches every page once, it leaves the file in the page
    cache for the computation that follows. A full check is recorded in the
    entry (``checked.json``: each file's size, inode, modification and change
    times) when its files were last changed at least 10 s before it, and a
    later load of files whose record still matches skips the hashing (0.7 CPU s
    a start on a 128-element probe's 0.8 GB basis): anything that writes to a
    file, replaces it or resets its times changes its change time, so the
    file is hashed again; damage that leaves a file's times alone (a failing
    disk) is caught by the first check only. A cache the user cannot write
    records nothing and hashes every load. ``$ARRAYSEL_CACHE_VERIFY=size`` checks only the sizes and
    headers (a truncated or partial file is still caught, a flipped bit is
    not), for a cold start that must read only the pages it uses.

    A damaged entry (missing or unparsable manifest, a manifest that parses but
    is inconsistent: wrong types, a block size that is not a positive integer,
    a checksum count or byte count that does not fit the shape; a missing,
    short or long file, a header that disagrees, a checksum mismatch, a tensor
    the caller needs that is missing: ``check``) is reported in one warning line
    naming the entry and the first fault, and rebuilt.

Concurrency
    Builders of the same entry serialise on a lock file ``<kind>-<key>.lock``
    (``filelock``): the second waits (saying so on stderr), then loads what the
    first saved instead of building it again.

A folder that cannot be used
    A cache folder that cannot be created or written, a lock file that cannot be
    opened (another user's, or a folder in its place), a file where the folder
    should be: the content is built without the cache, after one warning line
    saying why. Never a traceback.

File modes follow the umask, like any file the user creates.
"""
from __future__ import annotations

import json
import logging
import os
import stat
import sys
import threading
import time
from typing import Callable, Mapping

# the entries' format and the folder's contents live in their own modules; their names stay here
from arraysel.io.cachefiles import (BLOCK, CHECKSUM, FORMAT, MANIFEST, DamagedEntry, cache_dir, entry_name,
                                    load_state, verify_mode)
from arraysel.io.cachefolder import remove_entry, remove_stale, classify, clear, list_entries, save_state

_log = logging.getLogger(__name__)

__all__ = ["FORMAT", "BLOCK", "cache_dir", "entry_name", "save_state", "load_state", "load_or_build", "peek",
           "list_entries", "clear", "classify", "DamagedEntry", "verify_mode", "MANIFEST", "CHECKSUM"]


class _BuildProgress:
    """A tqdm bar of the elapsed time against an estimate, refreshed by a thread while a build
    (which has no progress hooks of its own) runs."""

    def __init__(self, label: str, seconds: float | None):
        self.label, self.seconds = label, seconds
        self._stop = threading.Event()

    def __enter__(self):
        from tqdm.auto import tqdm

        total = None if not self.seconds else max(1, round(self.seconds))
        self.bar = tqdm(total=total, desc=self.label, unit="s", file=sys.stderr, dynamic_ncols=True,
                        bar_format="{desc}: {bar} {n:.0f}/~{total:.0f} s" if total else None)
        self.t0 = time.monotonic()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()
        return self

    def _tick(self):
        el = time.monotonic() - self.t0
        if self.bar.total is not None:
            el = min(el, self.bar.total)
        self.bar.update(el - self.bar.n)

    def _loop(self):
        while not self._stop.wait(0.5):
            self._tick()

    def __exit__(self, *exc):
        self._stop.set()
        self.thread.join()
        if exc[0] is None and self.bar.total is not None:
            self.bar.update(self.bar.total - self.bar.n)
        self.bar.close()
        return False


def _fmt_bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"  # pragma: no cover


def load_or_build(kind: str, key_parts, build: Callable[[], Mapping], *, what: str = "cache entry",
                  size_hint: int | None = None, seconds_hint: float | None = None,
                  progress: bool | None = None, check: Callable[[dict], None] | None = None) -> dict:
    """The state (name -> tensor) cached under ``(kind, key_parts)``, built by ``build()`` and
    saved when absent or damaged. With the cache off, ``build()`` is simply called; with a cache
    folder that cannot be used (see the module), too, after one warning line.

    ``what`` names the content in messages; ``size_hint`` (bytes) and ``seconds_hint`` are the
    estimates announced before a build (and the length of its progress bar); ``progress``: show
    the bar (default: when stderr is a terminal). ``check(state)`` is called on a loaded state
    before it is returned: any exception it raises (a tensor the caller needs is missing, shapes
    that do not fit together) makes the entry damaged, reported and rebuilt."""
    folder = cache_dir()
    if folder is None:
        return dict(build())
    name = entry_name(kind, key_parts)
    path = os.path.join(folder, name)
    state, why = _try_load(path, check)
    if state is not None:
        return state
    problem = _unusable(folder, name)
    if problem:
        return _without_cache(folder, problem, what, build)
    if why:
        _report(path, what, why)
    from filelock import Timeout

    lock = _lock(folder, name)
    try:
        try:
            lock.acquire(timeout=0)
        except Timeout:
            _log.warning("arraysel: waiting for another process that is building %s (%s)", what, path)
            lock.acquire()
    except OSError as exc:
        return _without_cache(folder, f"its lock file {name}.lock cannot be opened: {_oserror(exc)}", what, build)
    try:
        try:
            remove_stale(folder, name)
            if os.path.lexists(path):
                state, why2 = _try_load(path, check)  # built while we waited
                if state is not None:
                    return state
                if why2 and not why:
                    _report(path, what, why2)
                if classify(folder, name)["owner"] != "cache":
                    return _without_cache(folder, f"{name} is taken by something the cache did not write",
                                          what, build)
                remove_entry(path)
        except OSError as exc:
            return _without_cache(folder, _oserror(exc), what, build)
        size = f" (about {_fmt_bytes(size_hint)})" if size_hint else ""
        eta = build_seconds_estimate(folder, seconds_hint)
        _log.warning("arraysel: building %s (first run with these settings%s); it will be cached in %s%s",
                     what, f"; an estimate: about {eta:.0f} s" if eta else "", folder, size)
        t0 = time.monotonic()
        with _BuildProgress(f"building {what}", eta) if _want_bar(progress) else _Null():
            state = dict(build())
        meta = {"kind": kind, "what": what, "build_seconds": round(time.monotonic() - t0, 3)}
        if seconds_hint:
            meta["estimated_seconds"] = round(float(seconds_hint), 3)
        try:
            save_state(folder, name, state, meta=meta)
        except OSError as exc:
            _log.warning("could not save %s to the cache %s (%s); it will be built again next time",
                         what, folder, _oserror(exc))
            return state
        return _saved(path, state)
    finally:
        lock.release()


def _saved(path: str, built: dict) -> dict:
    """The entry just saved at ``path``, memory-mapped as a later run loads it, in place of
    ``built``: the built tensors are then freed, so a process that builds several entries holds
    at most one of them in its own memory (the rest are pages of the files, which the system may
    drop), and the first run computes with the very tensors every later run reads. ``built`` when
    the saved entry cannot be read back. Its blocks were hashed as they were written, so only the
    sizes and headers are checked here (the next load checks it in full)."""
    try:
        return load_state(path, verify="size")
    except (DamagedEntry, OSError) as exc:
        _log.warning("the cache entry %s could not be read back (%s); using the built tensors", path, exc)
        return built


def build_seconds_estimate(folder: str | None, seconds_hint: float | None) -> float | None:
    """The time a build announces: ``seconds_hint`` (the model's estimate, e.g.
    :func:`arraysel.physics.psf.sizing.basis_build_seconds`) times what the latest build saved in
    ``folder`` measured over its own estimate (``build_seconds`` / ``estimated_seconds`` of its
    manifest), kept within 1/4 to 4; the model's estimate when no build there recorded both. So
    the announced time follows the measured cost of this machine once it has built one entry."""
    if not seconds_hint or folder is None:
        return seconds_hint
    latest = ("", None)
    try:
        names = os.listdir(folder)
    except OSError:
        return seconds_hint
    for n in names:
        try:
            with open(os.path.join(folder, n, MANIFEST), "rb") as fh:
                m = json.loads(fh.read().decode("utf-8"))
            took, est, when = float(m["build_seconds"]), float(m["estimated_seconds"]), str(m["created"])
        except (OSError, ValueError, KeyError, TypeError, UnicodeDecodeError):
            continue
        if took > 0 and est > 0 and when >= latest[0]:
            latest = (when, took / est)
    return seconds_hint if latest[1] is None else seconds_hint * min(4.0, max(0.25, latest[1]))


def _oserror(exc: OSError) -> str:
    return f"{exc.strerror}: {exc.filename}" if exc.strerror and exc.filename else str(exc)


def _without_cache(folder: str, problem: str, what: str, build: Callable[[], Mapping]) -> dict:
    _log.warning("cache folder %s cannot be used (%s); building %s without the cache", folder, problem, what)
    return dict(build())


def _unusable(folder: str, name: str) -> str | None:
    """Why the cache folder cannot take entry ``name`` (None when it can): a file in the folder's
    place, a folder that cannot be created or written, the entry's name or its lock's taken by
    something else, a lock file this process cannot open."""
    if os.path.lexists(folder) and not os.path.isdir(folder):
        return "it is a file, not a folder"
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        return f"it cannot be created: {exc.strerror or exc}"
    if not os.access(folder, os.W_OK | os.X_OK):
        return "it is not writable"
    path = os.path.join(folder, name)
    if os.path.lexists(path) and classify(folder, name)["owner"] != "cache":
        return f"{name} is taken by something the cache did not write"
    lock = os.path.join(folder, f"{name}.lock")
    try:
        st = os.lstat(lock)
    except FileNotFoundError:
        return None
    except OSError as exc:
        return f"its lock file {name}.lock cannot be examined: {exc.strerror}"
    if not stat.S_ISREG(st.st_mode):
        return f"its lock file {name}.lock is not a file"
    if not os.access(lock, os.R_OK | os.W_OK):
        owner = "" if st.st_uid == os.geteuid() else f", it belongs to user id {st.st_uid}"
        return f"its lock file {name}.lock cannot be opened for writing{owner}"
    return None


class _Null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def _want_bar(progress: bool | None) -> bool:
    if progress is not None:
        return progress
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def _lock(folder: str, name: str):
    from filelock import FileLock

    from arraysel.io.atomic import file_mode

    return FileLock(os.path.join(folder, f"{name}.lock"), mode=file_mode())


def _try_load(path: str, check: Callable[[dict], None] | None = None) -> tuple[dict | None, str]:
    """(state, "") or (None, why it cannot be used; "" when there is no entry)."""
    if not os.path.lexists(path):
        return None, ""
    if os.path.islink(path) or not os.path.isdir(path):
        return None, "not a folder"
    try:
        state = load_state(path)
    except DamagedEntry as exc:
        return None, str(exc)
    if check is not None:
        try:
            check(state)
        except MemoryError:
            raise
        except Exception as exc:  # the caller's view: anything that does not fit is damage
            from arraysel.errors import error_text

            return None, f"its tensors do not fit together ({error_text(exc)})"
    return state, ""


def peek(kind: str, key_parts, names) -> dict | None:
    """The tensors ``names`` of the entry cached under ``(kind, key_parts)``, verified like
    :func:`load_state` (only those), or None when the cache is off, the entry is absent, lacks one
    of them or is damaged (a later full load reports and rebuilds a damaged entry)."""
    folder = cache_dir()
    if folder is None:
        return None
    path = os.path.join(folder, entry_name(kind, key_parts))
    if os.path.islink(path) or not os.path.isdir(path):
        return None
    try:
        return load_state(path, only=list(names))
    except DamagedEntry:
        return None


def _report(path: str, what: str, why: str) -> None:
    _log.warning("cache entry %s of %s is damaged (%s); rebuilding it", path, what, why)


