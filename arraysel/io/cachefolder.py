"""What the cache folder holds and what the cache owns in it: listing, classifying and removing.

An entry is written into a temporary folder and renamed into place (:func:`save_state`). The
cache touches only the names it writes (:func:`classify`); anything else in the folder is
*foreign*, listed by ``arraysel cache info`` and never removed (:mod:`arraysel.io.cache`).
"""
from __future__ import annotations

import json
import os
import shutil
import stat
import time
import uuid
from typing import Mapping

from arraysel.errors import ParameterError
from arraysel.io.atomic import TMP_SUFFIX
from arraysel.io.cachefiles import (ASIDE_TMP_RE, BLOCK, CHECKED, CHECKSUM, ENTRY_RE, FORMAT, LOCK_RE, MANIFEST, OLD_RE,
                                    WRITER_TMP_RE, BlockHasher, DamagedEntry, as_numpy, cache_dir, dir_mode,
                                    read_arrays, read_manifest)

__all__ = ["save_state", "classify", "list_entries", "clear", "remove_entry", "remove_stale"]


# ---------------------------------------------------------------------------- writing and removing entries
def remove_entry(path: str) -> None:
    """Remove an entry folder (renamed aside first, so nobody sees it half-deleted). Call only on a
    name :func:`classify` says the cache owns."""
    aside = os.path.join(os.path.dirname(path), f".{os.path.basename(path)}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        os.rename(path, aside)
    except FileNotFoundError:
        return
    if os.path.isdir(aside) and not os.path.islink(aside):
        shutil.rmtree(aside, ignore_errors=True)
    else:
        os.unlink(aside)


def remove_stale(folder: str, name: str) -> int:
    """Remove the temporary folders of entry ``name`` that the cache wrote (call with its lock held:
    nobody else writes them)."""
    n = 0
    for item in _items(folder):
        if item["entry"] == name and item["kind"] in ("leftover", "aside") and item["owner"] == "cache":
            _delete(os.path.join(folder, item["name"]))
            n += 1
    return n


def _delete(p: str) -> None:
    try:
        if os.path.isdir(p) and not os.path.islink(p):
            shutil.rmtree(p)
        else:
            os.unlink(p)
    except FileNotFoundError:
        pass



def save_state(folder: str, name: str, state: Mapping, meta: dict | None = None) -> str:
    """Write ``state`` (name -> tensor) as the entry ``folder/name``, atomically; return its path.

    An existing entry of that name is replaced."""
    import numpy as np

    if not state:
        raise ParameterError("save_state: the state is empty")
    bad = [k for k in state if not k or "/" in k or "\\" in k or k.startswith(".") or k == "manifest"]
    if bad:
        raise ParameterError(f"save_state: tensor names {bad} cannot be file names")
    os.makedirs(folder, exist_ok=True)
    final = os.path.join(folder, name)
    from arraysel.io.atomic import writer_tag

    tmp = os.path.join(folder, f".{name}.{writer_tag()}.{uuid.uuid4().hex[:8]}.tmp")
    os.mkdir(tmp)
    try:
        os.chmod(tmp, dir_mode())
        tensors = {}
        for key, value in state.items():
            arr = as_numpy(key, value)
            fname = f"{key}.npy"
            with open(os.path.join(tmp, fname), "wb") as fh:
                hw = BlockHasher(fh)
                np.lib.format.write_array(hw, arr, allow_pickle=False)
                fh.flush()
                os.fsync(fh.fileno())
            tensors[key] = {"file": fname, "dtype": arr.dtype.str, "shape": list(arr.shape),
                            "bytes": hw.size, CHECKSUM: hw.close()}
        from arraysel import __version__

        manifest = {"format": FORMAT, "name": name, "block": BLOCK, "arraysel": __version__,
                    "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **(meta or {}),
                    "tensors": tensors}
        with open(os.path.join(tmp, MANIFEST), "w", encoding="utf-8") as fh:
            json.dump(manifest, fh, indent=1)
            fh.flush()
            os.fsync(fh.fileno())
        if os.path.lexists(final):
            if classify(folder, name)["owner"] != "cache":
                raise OSError(f"{final} is taken by something the cache did not write")
            remove_entry(final)
        os.rename(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


# ---------------------------------------------------------------------------- inspection
def _du(path: str) -> int:
    try:
        st = os.lstat(path)
    except OSError:
        return 0
    if not stat.S_ISDIR(st.st_mode):
        return st.st_size
    total = 0
    for root, _dirs, files in os.walk(path):
        for f in files:
            try:
                total += os.lstat(os.path.join(root, f)).st_size
            except OSError:
                pass
    return total


def _entry_files_only(path: str) -> str | None:
    """None when ``path`` is a real folder holding only regular files named ``*.npy``,
    ``manifest.json`` or ``checked.json`` (and the latter's temporary file: what the cache writes
    into an entry), else what is wrong (in words)."""
    try:
        st = os.lstat(path)
    except OSError as exc:
        return f"cannot be examined ({exc.strerror})"
    if stat.S_ISLNK(st.st_mode):
        return "it is a symbolic link"
    if not stat.S_ISDIR(st.st_mode):
        return "it is a file, not a folder"
    try:
        names = os.listdir(path)
    except OSError as exc:
        return f"cannot be listed ({exc.strerror})"
    for f in names:
        ok_name = f in (MANIFEST, CHECKED) or (f.endswith(".npy") and not f.startswith(".")) or (
            f.startswith(f".{CHECKED}.") and f.endswith(TMP_SUFFIX))  # the record of a check, being written
        try:
            regular = stat.S_ISREG(os.lstat(os.path.join(path, f)).st_mode)
        except OSError:
            regular = False
        if not (ok_name and regular):
            return f"it holds {f!r}, which the cache does not write"
    return None


def classify(folder: str, name: str) -> dict:
    """What ``folder/name`` is to the cache: ``{"name", "kind", "owner", "entry", "status"}``.

    ``owner`` is ``"cache"`` for the names the cache writes (see the module) and ``"foreign"``
    for anything else; ``kind``: ``entry``, ``lock``, ``leftover`` (a writer's temporary folder),
    ``aside`` (an entry being removed), ``old`` (the older single-file format) or ``foreign``;
    ``entry``: the entry a lock or temporary folder belongs to; ``status``: in words, for
    ``arraysel cache info``. A temporary folder of a writer that still runs is ``owner`` cache
    but ``kind`` ``"writing"`` (nobody removes it)."""
    from arraysel.io.atomic import pid_alive, stale_writer

    p = os.path.join(folder, name)
    info = {"name": name, "kind": "foreign", "owner": "foreign", "entry": None,
            "status": "foreign: not written by the arraysel cache (left alone)"}
    if ENTRY_RE.match(name):
        wrong = _entry_files_only(p)
        if wrong is not None:
            info["status"] = f"foreign: named like a cache entry, but {wrong} (left alone)"
            return info
        info.update(kind="entry", owner="cache", entry=name)
        try:
            read_arrays(p, verify="size")  # the manifest, file sizes and headers (no block is read)
            info["status"] = "ok"
        except DamagedEntry as exc:
            info["status"] = f"damaged: {exc}"
        return info
    m = LOCK_RE.match(name)
    if m:
        try:
            regular = stat.S_ISREG(os.lstat(p).st_mode)
        except OSError:
            regular = False
        if regular:
            info.update(kind="lock", owner="cache", entry=m.group(1), status="lock file")
        else:
            info["status"] = "foreign: named like a lock file, but not a file (left alone)"
        return info
    m = WRITER_TMP_RE.match(name) or ASIDE_TMP_RE.match(name)
    if m:
        wrong = _entry_files_only(p)
        if wrong is not None:
            info["status"] = f"foreign: named like a cache leftover, but {wrong} (left alone)"
            return info
        info.update(owner="cache", entry=m.group(1))
        if m.re is ASIDE_TMP_RE:
            info.update(kind="aside", status="leftover of a removal")
            return info
        tag = m.group(2)
        pid = int(tag.split("-")[0])
        live = (not stale_writer(tag)) if "-" in tag else (pid == os.getpid() or pid_alive(pid))
        if live:
            info.update(kind="writing", status=f"being written by process {pid} (left alone)")
        else:
            info.update(kind="leftover", status="leftover of an interrupted write")
        return info
    if OLD_RE.match(name):
        try:
            regular = stat.S_ISREG(os.lstat(p).st_mode)
        except OSError:
            regular = False
        if regular:
            info.update(kind="old", owner="cache", status="file of an older cache format (unused)")
    return info


def _items(folder: str) -> list[dict]:
    try:
        names = sorted(os.listdir(folder))
    except OSError:
        return []
    return [classify(folder, f) for f in names]


def list_entries(folder: str | None = None) -> list[dict]:
    """Everything in the cache folder, each ``{"name", "kind", "owner", "entry", "bytes",
    "created", "status"}`` (see :func:`classify`): entries, their lock files, leftovers of killed
    writers, files of the older format, and foreign files (listed, never touched)."""
    folder = cache_dir() if folder is None else folder
    if folder is None or not os.path.isdir(folder):
        return []
    out = []
    for info in _items(folder):
        p = os.path.join(folder, info["name"])
        info.update(bytes=_du(p), created="")
        if info["kind"] == "entry" and info["status"] == "ok":
            m = read_manifest(p)
            info["created"] = m.get("created", "") if isinstance(m.get("created"), str) else ""
            if isinstance(m.get("build_seconds"), (int, float)):
                info["build_seconds"] = float(m["build_seconds"])
        out.append(info)
    return out


def clear(folder: str | None = None) -> tuple[int, int]:
    """Remove what the cache wrote in its folder: its entries (each under its lock: an entry a
    live process is building is left), their lock files, the leftovers of killed writers and
    files of the older format. Foreign files and folders, and a live writer's temporary folder,
    are left alone. Returns (items removed, bytes freed).

    An entry's lock file is removed while this call holds it; a process that opened that lock
    file just before may then hold a lock on the removed file while another creates a new one,
    and both build the entry: the second save replaces the first's identical entry."""
    from filelock import FileLock, Timeout

    from arraysel.io.atomic import file_mode

    folder = cache_dir() if folder is None else folder
    if folder is None or not os.path.isdir(folder):
        return 0, 0
    n = freed = 0
    items = list_entries(folder)
    busy = set()
    for info in items:
        if info["owner"] != "cache" or info["kind"] not in ("entry", "lock"):
            continue
        name = info["entry"]
        if name in busy or info["kind"] == "lock" and any(
                i["kind"] == "entry" and i["entry"] == name for i in items):
            continue  # a lock goes with its entry
        lock = FileLock(os.path.join(folder, f"{name}.lock"), mode=file_mode())
        try:
            lock.acquire(timeout=0)
        except (Timeout, OSError):
            busy.add(name)  # being built (or a lock this process cannot take): left as it is
            continue
        try:
            p = os.path.join(folder, name)
            if os.path.lexists(p) and classify(folder, name)["owner"] == "cache":
                size = _du(p)
                remove_entry(p)
                n += 1
                freed += size
            # the lock file goes too (counted when it was there before this call took it)
            n += any(i["kind"] == "lock" and i["entry"] == name for i in items)
            os.unlink(os.path.join(folder, f"{name}.lock"))
        except FileNotFoundError:
            pass
        finally:
            lock.release()
    for info in items:
        if info["owner"] == "cache" and info["kind"] in ("leftover", "aside", "old"):
            p = os.path.join(folder, info["name"])
            if classify(folder, info["name"])["kind"] == info["kind"]:  # still what it was
                _delete(p)
                n += 1
                freed += info["bytes"]
    return n, freed
