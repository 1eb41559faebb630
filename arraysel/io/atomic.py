"""Atomic file writing: the one home of it (every result file, the cache, checkpoints).

A file is written to a temporary name in its target folder and renamed over the
target with ``os.replace``, so a reader sees the old complete file or the new
complete one, never a part. A failure (disk full, ``KeyboardInterrupt``) removes
the temporary file and leaves the old file untouched.

Temporary names are ``.<target name>.<pid>-<host>.<random>.tmp``: the writer's
process id and a tag of its host (:func:`writer_tag`). A process killed by
``SIGKILL`` cannot remove its temporary file; the next writer to the same target
removes the leftovers whose writer is no longer running on this host
(:func:`remove_stale_temporaries`), never those of a live writer.

Only regular files are replaced: an existing target that is a device node, a
FIFO, a socket or a folder is refused (:class:`~arraysel.errors.ParameterError`)
before anything is written, so ``/dev/null`` stays a device. A symbolic link
target is replaced by the new file (the file it pointed to is left as it was).

Files get the mode of a file created with ``open()``: ``0o666`` less the
process umask (``0o644`` under the usual umask 022), not the ``0o600`` of
:func:`tempfile.mkstemp`.

:class:`AtomicFile` is the streaming form (rows written as they are computed):
it writes to the temporary file and renames it into place on :meth:`commit`.
"""
from __future__ import annotations

import io
import os
import re
import socket
import stat
import tempfile
import threading
import zlib

__all__ = ["TMP_SUFFIX", "file_mode", "atomic_write_bytes", "atomic_write_text", "atomic_savez",
           "AtomicFile", "StreamingNpz", "remove_stale_temporaries", "check_writable", "writer_tag",
           "pid_alive", "stale_writer", "check_replaceable", "file_kind"]

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


def _host_tag() -> str:
    """Six hex digits naming this host (a CRC-32 of its name): a leftover written on another
    host sharing the folder is never taken for a dead writer's."""
    return f"{zlib.crc32(socket.gethostname().encode()) & 0xFFFFFF:06x}"


def writer_tag(pid: int | None = None) -> str:
    """``<pid>-<host tag>``: the part of a temporary name that identifies its writer."""
    return f"{os.getpid() if pid is None else pid}-{_host_tag()}"


_TAG_RE = re.compile(r"^(\d+)-([0-9a-f]{6})$")


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this host (signal 0; a process of another user counts as alive)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:  # pragma: no cover - unknown: keep the file
        return True
    return True


def stale_writer(tag: str) -> bool:
    """Whether the writer named by ``tag`` (:func:`writer_tag`) has ended: its host is this one and
    its process is gone. Anything else (a live process, another host, a tag this function does not
    know) is not stale."""
    m = _TAG_RE.match(tag)
    if m is None or m.group(2) != _host_tag():
        return False
    pid = int(m.group(1))
    return pid != os.getpid() and not pid_alive(pid)


def file_kind(mode: int) -> str | None:
    """What a non-regular file is, in words (None for a regular file)."""
    for test, name in ((stat.S_ISDIR, "a folder"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISREG, None)):
        if test(mode):
            return name
    return "not a regular file"


def check_replaceable(path: str | os.PathLike, what: str | None = None, follow: bool = False) -> None:
    """Raise :class:`~arraysel.errors.ParameterError` when ``path`` exists and is not a regular file
    (a device, FIFO, socket or folder), which a rename would replace. ``follow``: judge the file a
    symbolic link points to (the command-line check) instead of the link itself (the writer, which
    replaces a link, not its target). ``what`` names the option in the message."""
    from arraysel.errors import ParameterError

    path = os.fspath(path)
    try:
        st = os.stat(path) if follow else os.lstat(path)
    except (FileNotFoundError, NotADirectoryError):
        return
    except OSError as exc:
        raise ParameterError(f"{what + ': ' if what else ''}cannot examine {path!r} ({exc.strerror})") from None
    if stat.S_ISLNK(st.st_mode):
        return
    kind = file_kind(st.st_mode)
    if kind is not None:
        raise ParameterError(f"{what + ': ' if what else ''}{path!r} is {kind}, not a regular file; "
                             f"give the path of a file to write")


def _temporary(path: str) -> tuple[int, str]:
    folder = os.path.dirname(os.path.abspath(path)) or "."
    os.makedirs(folder, exist_ok=True)
    check_replaceable(path)
    base = os.path.basename(path)
    remove_stale_temporaries(folder, base)
    fd, tmp = tempfile.mkstemp(prefix=f".{base}.{writer_tag()}.", suffix=TMP_SUFFIX, dir=folder)
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
        check_replaceable(path)
        os.replace(tmp, path)
    except BaseException as exc:
        _discard(tmp)
        if isinstance(exc, OSError) and exc.filename in (None, tmp):  # name the file the user knows
            exc.filename = path
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
        try:
            check_replaceable(self.path)  # a target made a device or FIFO while we wrote
        except BaseException:
            _discard(self.tmp)
            raise
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


def remove_stale_temporaries(folder: str | os.PathLike, target: str) -> int:
    """Remove the temporary files ``.<target>.<pid>-<host>.<random>.tmp`` in ``folder`` whose writer
    has ended (:func:`stale_writer`: same host, process gone); return how many were removed. A live
    writer's file, another host's and anything not named that way are left alone."""
    folder = os.fspath(folder)
    try:
        names = os.listdir(folder)
    except OSError:
        return 0
    head = f".{target}."
    removed = 0
    for name in names:
        if not (name.startswith(head) and name.endswith(TMP_SUFFIX)):
            continue
        middle = name[len(head):-len(TMP_SUFFIX)]
        tag, dot, rand = middle.rpartition(".")
        if not dot or len(rand) != 8 or not stale_writer(tag):
            continue
        p = os.path.join(folder, name)
        try:
            if stat.S_ISREG(os.lstat(p).st_mode):
                os.unlink(p)
                removed += 1
        except OSError:
            pass
    return removed


def check_writable(path: str | os.PathLike, what: str) -> str:
    """Check, before any heavy work, that a file can be created at ``path`` (its folder exists or
    can be made, is writable, and ``path`` is not a folder, device, FIFO or socket, even through a
    symbolic link). Returns ``path`` as a string; raises :class:`~arraysel.errors.ParameterError`
    naming ``what`` (the option) otherwise. :func:`arraysel.io.outputs.check_outputs` calls it for
    every output of a command, and also refuses outputs that are inputs or each other."""
    from arraysel.errors import ParameterError

    path = os.fspath(path)
    if not path:
        raise ParameterError(f"{what}: empty path")
    if os.path.isdir(path):
        raise ParameterError(f"{what}: {path!r} is a folder, not a file")
    check_replaceable(path, what, follow=True)
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
