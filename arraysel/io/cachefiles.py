"""The cache's entries on disk: where the folder is, how entries are named, checked and read back.

The format (one folder an entry: a ``.npy`` file a tensor and ``manifest.json`` with the block
checksums), the checks made when an entry is loaded and the environment variables
(``ARRAYSEL_CACHE``, ``ARRAYSEL_CACHE_VERIFY``) are described in :mod:`arraysel.io.cache`, which
also gathers the names of this module.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import zlib

from arraysel.errors import ArrayselError, ParameterError

__all__ = ["FORMAT", "BLOCK", "MANIFEST", "CHECKSUM", "CHECKED", "DamagedEntry", "cache_dir", "verify_mode",
           "entry_name", "load_state"]

FORMAT = 1
#: bytes per checksum block
BLOCK = 16 * 2 ** 20
MANIFEST = "manifest.json"
_OFF = ("", "0", "off", "none", "false", "no")
#: checksum that new entries carry (the manifest key of each tensor's block digests)
CHECKSUM = "crc32"
#: the record, in an entry, of the files its last full check hashed (:func:`_record_checked`)
CHECKED = "checked.json"
#: a full check records only files last changed at least this long (ns) before it began: file
#: times are coarse on some file systems, and a change in the same tick could keep them
SETTLED_NS = 10 * 10 ** 9


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
KIND = r"[a-z][a-z0-9]*(?:-[a-z0-9]+)*"
ENTRY_RE = re.compile(rf"^{KIND}-[0-9a-f]{{24}}$")
LOCK_RE = re.compile(rf"^({KIND}-[0-9a-f]{{24}})\.lock$")
WRITER_TMP_RE = re.compile(rf"^\.({KIND}-[0-9a-f]{{24}})\.(\d+(?:-[0-9a-f]{{6}})?)\.[0-9a-f]{{8}}\.tmp$")
ASIDE_TMP_RE = re.compile(rf"^\.({KIND}-[0-9a-f]{{24}})\.[0-9a-f]{{8}}\.tmp$")
OLD_RE = re.compile(rf"^{KIND}-[0-9a-f]{{24}}\.pt$")


def entry_name(kind: str, key_parts) -> str:
    """``<kind>-<24 hex digits of SHA-256(repr(key_parts))>``; ``kind``: lower-case letters and
    digits, words joined by ``-`` (``psf-basis``)."""
    if not isinstance(kind, str) or not re.fullmatch(KIND, kind):
        raise ParameterError(f"cache kind {kind!r} is not allowed; use lower-case letters and digits, "
                             f"words joined by '-'")
    return f"{kind}-{hashlib.sha256(repr(key_parts).encode()).hexdigest()[:24]}"


def dir_mode() -> int:
    from arraysel.io.atomic import file_mode

    return file_mode() | ((file_mode() & 0o444) >> 2)  # x wherever r: 0o755 under umask 022




# ---------------------------------------------------------------------------- writing
class BlockHasher:
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


def as_numpy(name: str, value):
    import numpy as np
    import torch

    if isinstance(value, torch.Tensor):
        if value.is_sparse or value.layout != torch.strided:
            raise TypeError(f"cache entry {name!r}: only dense tensors can be stored (got {value.layout})")
        return value.detach().cpu().contiguous().numpy()
    if isinstance(value, np.ndarray):
        return np.ascontiguousarray(value)
    raise TypeError(f"cache entry {name!r}: expected a tensor or numpy array, got {type(value).__name__}")


# ---------------------------------------------------------------------------- reading
def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def read_manifest(path: str) -> dict:
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


def _file_key(path: str) -> list[int]:
    """What a full check records of a file: size, inode, device, modification and change times
    (ns). Writing to the file, replacing it or changing its times changes the change time."""
    st = os.stat(path)
    return [st.st_size, st.st_ino, st.st_dev, st.st_mtime_ns, st.st_ctime_ns]


def _checked_files(path: str) -> dict:
    """``{file: key}`` of the entry's record of its last full check (empty when there is none or
    it does not parse)."""
    try:
        with open(os.path.join(path, CHECKED), "rb") as fh:
            files = json.loads(fh.read().decode("utf-8")).get("files")
    except (OSError, ValueError, AttributeError, UnicodeDecodeError, RecursionError):
        return {}
    return files if isinstance(files, dict) else {}


def _unchanged_since_checked(path: str, items: list[tuple[str, dict]]) -> bool:
    """Whether the manifest and every file of ``items`` are as the entry's last full check
    recorded them (:func:`_record_checked`): their blocks were hashed then and nothing has
    written to them since."""
    files = _checked_files(path)
    try:
        return all(files.get(f) == _file_key(os.path.join(path, f))
                   for f in [MANIFEST, *(str(info["file"]) for _, info in items)])
    except OSError:
        return False


def _record_checked(path: str, items: list[tuple[str, dict]], started_ns: int) -> None:
    """Record in the entry that the files of ``items`` (and the manifest) passed a full check
    that began at ``started_ns`` (keeping the record of its other files that have not changed):
    a later load of them skips the hashing while their keys (:func:`_file_key`) stay the same.
    Nothing is recorded when one of them changed less than :data:`SETTLED_NS` before the check,
    nor when the entry cannot be written (a shared, read-only cache: every load hashes)."""
    from arraysel.io.atomic import atomic_write_text

    try:
        files = {}
        for f, k in _checked_files(path).items():  # the record of the entry's other files, still valid
            if isinstance(f, str) and os.path.isfile(os.path.join(path, f)) and k == _file_key(os.path.join(path, f)):
                files[f] = k
        for f in [MANIFEST, *(str(info["file"]) for _, info in items)]:
            key = _file_key(os.path.join(path, f))
            if max(key[3], key[4]) > started_ns - SETTLED_NS:
                return
            files[f] = key
        atomic_write_text(os.path.join(path, CHECKED), json.dumps({"format": FORMAT, "files": files}))
    except (OSError, ValueError, TypeError):
        pass


def load_state(path: str, verify: str | None = None, only=None) -> dict:
    """The tensors of the entry at ``path``, memory-mapped (copy-on-write: writing to one does not
    touch the file). ``verify``: ``full`` or ``size`` (default :func:`verify_mode`); ``only``: the
    names of the tensors to load (and verify), default all.

    Raises :class:`DamagedEntry` naming the first fault found."""
    import numpy as np
    import torch

    arrays = read_arrays(path, verify, only)
    return {k: torch.from_numpy(a) if a.ndim else torch.from_numpy(np.array(a)) for k, a in arrays.items()}


def read_arrays(path: str, verify: str | None = None, only=None) -> dict:
    """The numpy arrays of :func:`load_state` (memory maps), checked the same way."""
    import numpy as np

    verify = verify_mode() if verify is None else verify
    manifest = read_manifest(path)
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
    if verify == "full" and not _unchanged_since_checked(path, items):
        import time

        started = time.time_ns()
        try:
            _verify_blocks(path, items, block)
        except OSError as exc:
            raise DamagedEntry(f"cannot read the entry's files ({exc.strerror})") from None
        _record_checked(path, items, started)
    return arrays


