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
    files and ``manifest.json``), their lock files ``<kind>-<key>.lock``, their
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
    cache for the computation that follows. ``$ARRAYSEL_CACHE_VERIFY=size`` checks only the sizes and
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

import hashlib
import json
import logging
import os
import re
import shutil
import stat
import sys
import threading
import time
import uuid
import zlib
from typing import Callable, Mapping

from arraysel.errors import ArrayselError, ParameterError

_log = logging.getLogger(__name__)

__all__ = ["FORMAT", "BLOCK", "cache_dir", "entry_name", "save_state", "load_state", "load_or_build", "peek",
           "list_entries", "clear", "classify", "DamagedEntry"]

FORMAT = 1
#: bytes per checksum block
BLOCK = 16 * 2 ** 20
MANIFEST = "manifest.json"
_OFF = ("", "0", "off", "none", "false", "no")
#: checksum that new entries carry (the manifest key of each tensor's block digests)
CHECKSUM = "crc32"


class _Crc32:
    """``hashlib``-style running CRC-32 (``zlib``, which releases the GIL on large buffers)."""

    def __init__(self, data=b""):
        self._v = zlib.crc32(data)

    def update(self, data) -> None:
        self._v = zlib.crc32(data, self._v)

    def hexdigest(self) -> str:
        return f"{self._v:08x}"


#: block checksums a manifest may carry (older entries: SHA-256)
_CHECKSUMS = {"crc32": _Crc32, "sha256": hashlib.sha256}


class DamagedEntry(ArrayselError):
    """A cache entry that is incomplete or does not match its checksums."""


def cache_dir() -> str | None:
    """Folder of the cache: ``$ARRAYSEL_CACHE`` (``off`` disables: ``None``), else the platform's
    user cache folder for ``arraysel``."""
    path = os.environ.get("ARRAYSEL_CACHE")
    if path is not None:
        if path.strip().lower() in _OFF:
            return None
        return os.path.abspath(os.path.expanduser(path))
    try:
        from platformdirs import user_cache_dir
    except ImportError:  # pragma: no cover - platformdirs is a dependency
        return os.path.join(os.path.expanduser("~"), ".cache", "arraysel")
    return user_cache_dir("arraysel", appauthor=False)


def verify_mode() -> str:
    """``$ARRAYSEL_CACHE_VERIFY``: ``full`` (default: every block's checksum) or ``size``."""
    mode = os.environ.get("ARRAYSEL_CACHE_VERIFY", "full").strip().lower() or "full"
    if mode not in ("full", "size"):
        raise ParameterError(f"ARRAYSEL_CACHE_VERIFY = {mode!r} is not allowed; choose 'full' or 'size'")
    return mode


#: the names the cache writes: an entry ``<kind>-<24 hex>``; its lock; its temporary folders
#: ``.<entry>.<pid>-<host>.<8 random>.tmp`` (a writer) and ``.<entry>.<8 hex>.tmp`` (an entry
#: renamed aside to be removed); an entry of the older single-file format ``<entry>.pt``
_KIND = r"[a-z][a-z0-9]*(?:-[a-z0-9]+)*"
_ENTRY_RE = re.compile(rf"^{_KIND}-[0-9a-f]{{24}}$")
_LOCK_RE = re.compile(rf"^({_KIND}-[0-9a-f]{{24}})\.lock$")
_WRITER_TMP_RE = re.compile(rf"^\.({_KIND}-[0-9a-f]{{24}})\.(\d+(?:-[0-9a-f]{{6}})?)\.[0-9a-f]{{8}}\.tmp$")
_ASIDE_TMP_RE = re.compile(rf"^\.({_KIND}-[0-9a-f]{{24}})\.[0-9a-f]{{8}}\.tmp$")
_OLD_RE = re.compile(rf"^{_KIND}-[0-9a-f]{{24}}\.pt$")


def entry_name(kind: str, key_parts) -> str:
    """``<kind>-<24 hex digits of SHA-256(repr(key_parts))>``; ``kind``: lower-case letters and
    digits, words joined by ``-`` (``psf-basis``)."""
    if not isinstance(kind, str) or not re.fullmatch(_KIND, kind):
        raise ParameterError(f"cache kind {kind!r} is not allowed; use lower-case letters and digits, "
                             f"words joined by '-'")
    return f"{kind}-{hashlib.sha256(repr(key_parts).encode()).hexdigest()[:24]}"


def _dir_mode() -> int:
    from arraysel.io.atomic import file_mode

    return file_mode() | ((file_mode() & 0o444) >> 2)  # x wherever r: 0o755 under umask 022


# ---------------------------------------------------------------------------- writing
class _BlockHasher:
    """A file writer that also computes the :data:`CHECKSUM` of every ``BLOCK`` bytes."""

    def __init__(self, fh, block: int = BLOCK):
        self.fh, self.block = fh, block
        self.digests: list[str] = []
        self._new = _CHECKSUMS[CHECKSUM]
        self._h = self._new()
        self._fill = 0
        self.size = 0

    def write(self, data) -> int:
        mv = memoryview(data).cast("B")
        self.fh.write(mv)
        self.size += len(mv)
        while len(mv):
            take = min(len(mv), self.block - self._fill)
            self._h.update(mv[:take])
            self._fill += take
            mv = mv[take:]
            if self._fill == self.block:
                self.digests.append(self._h.hexdigest())
                self._h, self._fill = self._new(), 0
        return len(data)

    def close(self) -> list[str]:
        if self._fill or not self.digests:
            self.digests.append(self._h.hexdigest())
        return self.digests


def _as_numpy(name: str, value):
    import numpy as np
    import torch

    if isinstance(value, torch.Tensor):
        if value.is_sparse or value.layout != torch.strided:
            raise TypeError(f"cache entry {name!r}: only dense tensors can be stored (got {value.layout})")
        return value.detach().cpu().contiguous().numpy()
    if isinstance(value, np.ndarray):
        return np.ascontiguousarray(value)
    raise TypeError(f"cache entry {name!r}: expected a tensor or numpy array, got {type(value).__name__}")


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
        os.chmod(tmp, _dir_mode())
        tensors = {}
        for key, value in state.items():
            arr = _as_numpy(key, value)
            fname = f"{key}.npy"
            with open(os.path.join(tmp, fname), "wb") as fh:
                hw = _BlockHasher(fh)
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
            _remove(final)
        os.rename(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


# ---------------------------------------------------------------------------- reading
def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _read_manifest(path: str) -> dict:
    """The manifest of the entry at ``path``, checked for consistency (types, a positive block
    size, safe and distinct file names, a dtype numpy knows, non-negative shapes, byte counts
    that hold the shape's data, one digest per block); :class:`DamagedEntry` otherwise."""
    import numpy as np

    mpath = os.path.join(path, MANIFEST)
    try:
        with open(mpath, "rb") as fh:
            manifest = json.loads(fh.read().decode("utf-8"))
    except FileNotFoundError:
        raise DamagedEntry("manifest.json is missing (an incomplete entry)") from None
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise DamagedEntry(f"manifest.json is unreadable ({type(exc).__name__}: {exc})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT or not isinstance(
            manifest.get("tensors"), dict):
        raise DamagedEntry(f"manifest.json is not a format-{FORMAT} manifest")
    block = manifest.get("block", BLOCK)
    if not _is_int(block) or not 0 < block <= 2 ** 40:
        raise DamagedEntry(f"manifest.json: block = {block!r} is not a positive whole number of bytes")
    if not manifest["tensors"]:
        raise DamagedEntry("manifest.json lists no tensor")
    files = set()
    for key, info in manifest["tensors"].items():
        def bad(why: str):
            return DamagedEntry(f"manifest.json: the entry of tensor {key!r} is inconsistent ({why})")

        if not isinstance(info, dict):
            raise bad("not an object")
        fname = info.get("file")
        if not isinstance(fname, str) or not fname.endswith(".npy") or fname.startswith(".") or any(
                c in fname for c in "/\\\0") or fname == MANIFEST:
            raise bad(f"file {fname!r} is not the name of a .npy file in the entry")
        if fname in files:
            raise bad(f"file {fname!r} is listed twice")
        files.add(fname)
        try:
            dtype = np.dtype(info.get("dtype")) if isinstance(info.get("dtype"), str) else None
        except (TypeError, ValueError):
            dtype = None
        if dtype is None or dtype.hasobject:
            raise bad(f"dtype {info.get('dtype')!r} is not a numeric dtype")
        shape = info.get("shape")
        if not isinstance(shape, list) or not all(_is_int(d) and d >= 0 for d in shape):
            raise bad(f"shape {shape!r} is not a list of whole numbers >= 0")
        size = info.get("bytes")
        data = int(np.prod(shape, dtype=object)) * dtype.itemsize
        if not _is_int(size) or size < data + 10:  # a .npy file: magic, header, then the data
            raise bad(f"bytes = {size!r} cannot hold a {dtype.str} {shape} array ({data} bytes and a header)")
        algo = _checksum(info)
        if algo is None:
            raise bad("no block checksums")
        want = max(1, -(-size // block))
        if len(algo[1]) != want or not all(isinstance(d, str) for d in algo[1]):
            raise bad(f"{len(algo[1])} {algo[0]} digests for {want} blocks of {block} bytes")
    return manifest


def _checksum(info: dict) -> tuple[str, list] | None:
    """``(algorithm, block digests)`` of a tensor's manifest entry (None: it has none)."""
    for algo in _CHECKSUMS:
        if isinstance(info.get(algo), list):
            return algo, info[algo]
    return None


def _verify_blocks(path: str, items: list[tuple[str, dict]], block: int) -> None:
    """Check every block's checksum (threads; zlib and hashlib release the GIL on large buffers)."""
    from concurrent.futures import ThreadPoolExecutor

    jobs = []
    for key, info in items:
        algo, digests = _checksum(info)
        size = int(info["bytes"])
        want = max(1, -(-size // block))
        if len(digests) != want:
            raise DamagedEntry(f"tensor {key!r}: the manifest lists {len(digests)} checksum blocks, "
                               f"its size needs {want}")
        for i, digest in enumerate(digests):
            jobs.append((key, info["file"], i, algo, digest))

    # read into a buffer per thread rather than through a memory map: the pages stay in the file
    # system's cache but are never mapped into this process, so checking a 1 GB entry does not
    # raise the process's resident memory by 1 GB
    import threading

    local = threading.local()

    def check(job):
        key, fname, i, algo, digest = job
        buf = getattr(local, "buf", None)
        if buf is None:
            buf = local.buf = bytearray(block)
        with open(os.path.join(path, fname), "rb", buffering=0) as fh, memoryview(buf) as view:
            fh.seek(i * block)
            n = fh.readinto(view) or 0
            ok = _CHECKSUMS[algo](view[:n]).hexdigest() == digest
        return None if ok else (key, i)

    workers = max(1, min(4, os.cpu_count() or 1, len(jobs)))
    with ThreadPoolExecutor(workers) as pool:
        for bad in pool.map(check, jobs):
            if bad is not None:
                key, i = bad
                raise DamagedEntry(f"tensor {key!r}: checksum mismatch in bytes "
                                   f"{i * block}..{(i + 1) * block - 1} of {dict(items)[key]['file']}")


def load_state(path: str, verify: str | None = None, only=None) -> dict:
    """The tensors of the entry at ``path``, memory-mapped (copy-on-write: writing to one does not
    touch the file). ``verify``: ``full`` or ``size`` (default :func:`verify_mode`); ``only``: the
    names of the tensors to load (and verify), default all.

    Raises :class:`DamagedEntry` naming the first fault found."""
    import numpy as np
    import torch

    arrays = _arrays(path, verify, only)
    return {k: torch.from_numpy(a) if a.ndim else torch.from_numpy(np.array(a)) for k, a in arrays.items()}


def _arrays(path: str, verify: str | None = None, only=None) -> dict:
    """The numpy arrays of :func:`load_state` (memory maps), checked the same way."""
    import numpy as np

    verify = verify_mode() if verify is None else verify
    manifest = _read_manifest(path)
    block = int(manifest.get("block", BLOCK))
    items = list(manifest["tensors"].items())
    if only is not None:
        missing = set(only) - set(manifest["tensors"])
        if missing:
            raise DamagedEntry(f"tensor {sorted(missing)[0]!r} is not in the entry")
        items = [(k, info) for k, info in items if k in set(only)]
    arrays = {}
    for key, info in items:
        fpath = os.path.join(path, str(info.get("file", "")))
        try:
            size = os.path.getsize(fpath)
        except OSError:
            raise DamagedEntry(f"tensor {key!r}: file {info.get('file')!r} is missing") from None
        if size != int(info["bytes"]):
            raise DamagedEntry(f"tensor {key!r}: {info['file']} holds {size} bytes, the manifest says "
                               f"{info['bytes']} (a partial or altered file)")
        empty = any(int(d) == 0 for d in info["shape"])  # numpy cannot map a zero-size array
        try:
            arr = np.load(fpath, mmap_mode=None if empty else "c", allow_pickle=False)
        except Exception as exc:  # numpy's header parser raises several kinds on garbage
            raise DamagedEntry(f"tensor {key!r}: {info['file']} does not parse ({type(exc).__name__})") from None
        if arr.dtype.str != info["dtype"] or list(arr.shape) != list(info["shape"]):
            raise DamagedEntry(f"tensor {key!r}: {info['file']} holds {arr.dtype.str} {list(arr.shape)}, the "
                               f"manifest says {info['dtype']} {info['shape']}")
        offset = getattr(arr, "offset", None)
        if offset is not None and offset + arr.nbytes != size:
            raise DamagedEntry(f"tensor {key!r}: {info['file']} holds {size - offset} bytes of data, its shape "
                               f"needs {arr.nbytes}")
        arrays[key] = arr
    if verify == "full":
        try:
            _verify_blocks(path, items, block)
        except OSError as exc:
            raise DamagedEntry(f"cannot read the entry's files ({exc.strerror})") from None
    return arrays


# ---------------------------------------------------------------------------- load or build
def _remove(path: str) -> None:
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


def _remove_stale(folder: str, name: str) -> int:
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
            _remove_stale(folder, name)
            if os.path.lexists(path):
                state, why2 = _try_load(path, check)  # built while we waited
                if state is not None:
                    return state
                if why2 and not why:
                    _report(path, what, why2)
                if classify(folder, name)["owner"] != "cache":
                    return _without_cache(folder, f"{name} is taken by something the cache did not write",
                                          what, build)
                _remove(path)
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
    finally:
        lock.release()


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
    """None when ``path`` is a real folder holding only regular files named ``*.npy`` or
    ``manifest.json`` (what the cache writes into an entry), else what is wrong (in words)."""
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
        ok_name = f == MANIFEST or (f.endswith(".npy") and not f.startswith("."))
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
    if _ENTRY_RE.match(name):
        wrong = _entry_files_only(p)
        if wrong is not None:
            info["status"] = f"foreign: named like a cache entry, but {wrong} (left alone)"
            return info
        info.update(kind="entry", owner="cache", entry=name)
        try:
            _arrays(p, verify="size")  # the manifest, file sizes and headers (no block is read)
            info["status"] = "ok"
        except DamagedEntry as exc:
            info["status"] = f"damaged: {exc}"
        return info
    m = _LOCK_RE.match(name)
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
    m = _WRITER_TMP_RE.match(name) or _ASIDE_TMP_RE.match(name)
    if m:
        wrong = _entry_files_only(p)
        if wrong is not None:
            info["status"] = f"foreign: named like a cache leftover, but {wrong} (left alone)"
            return info
        info.update(owner="cache", entry=m.group(1))
        if m.re is _ASIDE_TMP_RE:
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
    if _OLD_RE.match(name):
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
            m = _read_manifest(p)
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
                _remove(p)
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
