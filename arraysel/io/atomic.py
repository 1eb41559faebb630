"""Atomic file writing: the one home of it (every result file, the cache, checkpoints).

A file is written to a temporary name in its target folder and renamed over the
target with ``os.replace``, so a reader sees the old complete file or the new
complete one, never a part. A failure (disk full, ``KeyboardInterrupt``) removes
the temporary file and leaves the old file untouched. The temporary names start
with ``.`` and end with ``.tmp`` (:data:`TMP_SUFFIX`) so that a leftover from a
killed process is recognisable (:func:`remove_stale_temporaries`).

Files get the mode of a file created with ``open()``: ``0o666`` less the
process umask (``0o644`` under the usual umask 022), not the ``0o600`` of
:func:`tempfile.mkstemp`.

:class:`AtomicFile` is the streaming form (rows written as they are computed):
it writes to the temporary file and renames it into place on :meth:`commit`.
"""
from __future__ import annotations

import io
import os
import tempfile
import threading
import time

__all__ = ["TMP_SUFFIX", "file_mode", "atomic_write_bytes", "atomic_write_text", "atomic_savez",
           "AtomicFile", "StreamingNpz", "remove_stale_temporaries", "check_writable"]

TMP_SUFFIX = ".tmp"

_umask_lock = threading.Lock()


def _umask() -> int:
    """The process umask: from ``/proc/self/status`` where Linux shows it, else by setting and
    restoring it (``os.umask`` can only be read that way) under a lock."""
    try:
        with open("/proc/self/status", "rb") as fh:
            for line in fh:
                if line.startswith(b"Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _umask_lock:
        value = os.umask(0o022)
        os.umask(value)
        return value


def file_mode() -> int:
    """Mode of a new regular file under the process umask (``0o666 & ~umask``)."""
    return 0o666 & ~_umask()


def _temporary(path: str) -> tuple[int, str]:
    folder = os.path.dirname(os.path.abspath(path)) or "."
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=TMP_SUFFIX, dir=folder)
    try:
        os.fchmod(fd, file_mode())
    except (AttributeError, OSError):  # pragma: no cover - platforms without fchmod
        pass
    return fd, tmp


def _discard(tmp: str) -> None:
    try:
        os.unlink(tmp)
    except FileNotFoundError:
        pass


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and ``os.replace``."""
    path = os.fspath(path)
    fd, tmp = _temporary(path)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        _discard(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_savez(path: str | os.PathLike, **arrays) -> None:
    """``numpy.savez_compressed`` to ``path``, atomically."""
    import numpy as np

    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


class AtomicFile:
    """A binary file written in pieces and published in one step.

    >>> with AtomicFile("rows.csv") as f:   # doctest: +SKIP
    ...     f.write(b"a,b\\n")
    ...     f.commit()

    Leaving the ``with`` block without :meth:`commit` (an exception) removes the
    temporary file; the target keeps its old content (or is not created).
    """

    def __init__(self, path: str | os.PathLike):
        self.path = os.fspath(path)
        fd, self.tmp = _temporary(self.path)
        self.fh = os.fdopen(fd, "wb")
        self.committed = False

    def write(self, data: bytes) -> int:
        return self.fh.write(data)

    def commit(self) -> None:
        self.fh.close()
        os.replace(self.tmp, self.path)
        self.committed = True

    def discard(self) -> None:
        if not self.fh.closed:
            self.fh.close()
        if not self.committed:
            _discard(self.tmp)

    def __enter__(self) -> "AtomicFile":
        return self

    def __exit__(self, *exc) -> bool:
        self.discard()
        return False


class StreamingNpz:
    """An ``.npz`` file (a zip of ``.npy`` members, as :func:`numpy.savez_compressed` writes and
    :func:`numpy.load` reads) written member by member, a member in row chunks when its number
    of rows is known up front, and published atomically by :meth:`commit`. Memory use is one
    chunk, whatever the size of the file."""

    def __init__(self, path: str | os.PathLike, compress: bool = True):
        import zipfile

        self.file = AtomicFile(path)
        try:
            self.zip = zipfile.ZipFile(self.file.fh, "w", allowZip64=True,
                                       compression=zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED)
        except BaseException:
            self.file.discard()
            raise
        self._member = None

    def begin(self, name: str, shape: tuple, dtype) -> None:
        """Start member ``name`` holding an array of ``shape`` and ``dtype`` (rows to follow)."""
        import numpy as np

        if self._member is not None:
            raise RuntimeError(f"member {self._name!r} is not finished")
        self._dtype, self._shape, self._name = np.dtype(dtype), tuple(int(v) for v in shape), name
        self._rows = 0
        self._member = self.zip.open(f"{name}.npy", "w", force_zip64=True)
        np.lib.format.write_array_header_1_0(
            self._member, {"descr": np.lib.format.dtype_to_descr(self._dtype), "fortran_order": False,
                           "shape": self._shape})

    def write_rows(self, rows) -> None:
        import numpy as np

        rows = np.ascontiguousarray(rows, dtype=self._dtype)
        if self._shape and rows.shape[1:] != self._shape[1:]:
            raise ValueError(f"{self._name}: rows of shape {rows.shape[1:]}, expected {self._shape[1:]}")
        self._member.write(rows.tobytes())
        self._rows += rows.shape[0] if self._shape else 1

    def end(self) -> None:
        want = self._shape[0] if self._shape else 1
        if self._rows != want:
            raise ValueError(f"{self._name}: {self._rows} rows written, {want} announced")
        self._member.close()
        self._member = None

    def add(self, name: str, array) -> None:
        """A whole member at once."""
        import numpy as np

        array = np.asarray(array)
        self.begin(name, array.shape, array.dtype)
        self.write_rows(array)
        self.end()

    def commit(self) -> None:
        self.zip.close()
        self.file.commit()

    def discard(self) -> None:
        try:
            if self._member is not None:
                self._member.close()
            self.zip.close()
        except Exception:  # the file is thrown away anyway
            pass
        self.file.discard()

    def __enter__(self) -> "StreamingNpz":
        return self

    def __exit__(self, *exc) -> bool:
        if not self.file.committed:
            self.discard()
        return False


def remove_stale_temporaries(folder: str | os.PathLike, prefix: str = ".", older_than_s: float = 0.0) -> int:
    """Remove files ``<prefix>*.tmp`` in ``folder`` last modified more than ``older_than_s`` ago;
    return how many were removed (missing folder: 0)."""
    folder = os.fspath(folder)
    try:
        names = os.listdir(folder)
    except OSError:
        return 0
    now = time.time()
    removed = 0
    for name in names:
        if not (name.startswith(prefix) and name.endswith(TMP_SUFFIX)):
            continue
        p = os.path.join(folder, name)
        try:
            if os.path.isfile(p) and now - os.path.getmtime(p) >= older_than_s:
                os.unlink(p)
                removed += 1
        except OSError:
            pass
    return removed


def check_writable(path: str | os.PathLike, what: str) -> str:
    """Check, before any heavy work, that a file can be created at ``path`` (its folder exists or
    can be made, is writable, and ``path`` is not a folder). Returns ``path`` as a string; raises
    :class:`~arraysel.errors.ParameterError` naming ``what`` (the option) otherwise."""
    from arraysel.errors import ParameterError

    path = os.fspath(path)
    if not path:
        raise ParameterError(f"{what}: empty path")
    if os.path.isdir(path):
        raise ParameterError(f"{what}: {path!r} is a folder, not a file")
    folder = os.path.dirname(os.path.abspath(path))
    probe = folder
    while not os.path.exists(probe):  # the nearest existing ancestor must let us create the rest
        parent = os.path.dirname(probe)
        if parent == probe:
            break
        probe = parent
    if not os.path.isdir(probe):
        raise ParameterError(f"{what}: cannot create {path!r}: {probe!r} is not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise ParameterError(f"{what}: cannot write {path!r}: folder {probe!r} is not writable")
    if os.path.exists(path) and not os.access(path, os.W_OK) and not os.access(folder, os.W_OK):
        raise ParameterError(f"{what}: cannot write {path!r}: permission denied")
    return path
