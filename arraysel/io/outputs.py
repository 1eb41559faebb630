"""What a command may write: the one check of its outputs, made before any heavy work.

Every command (``psf``, ``evaluate``, ``compare``, ``train``, and any new one) lists the files
it will write and the files it reads, and calls :func:`check_outputs` first. It refuses, in one
line naming the option (:class:`~arraysel.errors.ParameterError`, exit code 2):

* an output whose folder cannot be created or written (:func:`arraysel.io.atomic.check_writable`);
* an output that exists and is not a regular file: a character or block device (``--out
  /dev/null``), a FIFO, a socket, or a folder where a file is expected, also through a symbolic
  link. Results are written to a temporary file and renamed into place
  (:mod:`arraysel.io.atomic`), which would replace such a node with a regular file, so these are
  refused rather than written (the writers refuse them too, as a last guard);
* an output that is one of the command's inputs (``evaluate --masks m.txt --out m.txt``), by
  path or as the same file through a symbolic or hard link (:func:`os.path.samefile`);
* two outputs that are the same file (``--out x.npz --psf-out x.npz``).

:func:`check_result_folder` is the rule of an output *folder* that holds the results of an
earlier run: refused unless the command is told to continue it (``--resume``) or to replace
it (``--force``).
"""
from __future__ import annotations

import os
from typing import Iterable, Sequence

from arraysel.errors import ParameterError
from arraysel.io.atomic import check_writable, file_kind

__all__ = ["check_outputs", "folder_files", "check_result_folder", "same_file", "scene_input"]

Named = Iterable[tuple[str, "str | os.PathLike | None"]]


def _identity(path: str) -> tuple[str, tuple[int, int] | None]:
    """(resolved path, (device, inode) of the file it names or None when there is none)."""
    real = os.path.normcase(os.path.realpath(path))
    try:
        st = os.stat(path)
    except OSError:
        return real, None
    return real, (st.st_dev, st.st_ino)


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether ``a`` and ``b`` name one file: the same resolved path (symbolic links followed), or
    the same device and inode (hard links)."""
    ra, ia = _identity(os.fspath(a))
    rb, ib = _identity(os.fspath(b))
    return ra == rb or (ia is not None and ia == ib)


def folder_files(option: str, folder: str | os.PathLike, names: Iterable[str]) -> list[tuple[str, str]]:
    """The outputs ``folder/name`` of a command that writes a folder, each labelled
    ``"<option> (<name>)"`` for :func:`check_outputs`."""
    return [(f"{option} ({name})", os.path.join(os.fspath(folder), name)) for name in names]


def _folder_ok(option: str, folder: str) -> None:
    if not folder:
        raise ParameterError(f"{option}: empty path")
    if os.path.lexists(folder) and not os.path.isdir(folder):
        try:
            kind = file_kind(os.stat(folder).st_mode) or "a file"
        except OSError:
            kind = "a broken link"
        raise ParameterError(f"{option}: {folder!r} is {kind}, not a folder")


def check_outputs(outputs: Named, inputs: Named = (), folders: Named = ()) -> None:
    """Refuse, before any work, outputs that cannot or must not be written (see the module).

    ``outputs``: (option, path) of every file the command writes (``None`` paths are skipped);
    ``inputs``: (option, path) of every file it reads (files that do not exist are skipped:
    their own check reports them); ``folders``: (option, path) of output folders (each must be
    a folder or not exist; their files go in ``outputs``, see :func:`folder_files`)."""
    for option, folder in folders:
        if folder is not None:
            _folder_ok(option, os.fspath(folder))
    outs = [(o, os.fspath(p)) for o, p in outputs if p is not None]
    ins = [(o, os.fspath(p)) for o, p in inputs if p is not None and os.path.exists(os.fspath(p))]
    for option, path in outs:
        check_writable(path, option)
    for option, path in outs:
        for in_option, in_path in ins:
            if same_file(path, in_path):
                how = "" if os.path.normcase(os.path.abspath(path)) == os.path.normcase(
                    os.path.abspath(in_path)) else f" (through a link: {in_path!r})"
                raise ParameterError(f"{option}: {path!r} is the file given to {in_option}{how}; an output "
                                     f"must not replace an input: choose another {option.split(' ')[0]}")
    for i, (option, path) in enumerate(outs):
        for other, other_path in outs[:i]:
            if same_file(path, other_path):
                raise ParameterError(f"{option}: {path!r} is the same file as {other} ({other_path!r}); "
                                     f"give each output its own path")


def check_result_folder(folder: str | os.PathLike, option: str, *, held: Sequence[str], what: str,
                        resume: bool = False, force: bool = False, resume_needs: str | None = None) -> list[str]:
    """The rule of an output folder that may hold an earlier run: return the names of ``held``
    (the files that make up a run's results) present in ``folder``.

    Refused (:class:`~arraysel.errors.ParameterError`, one line) when ``resume`` and ``force``
    are both given; when results are present and neither is; when ``resume`` is given, the
    folder holds results and ``resume_needs`` (the file a resumed run continues from) is not
    among them. ``what`` names the run in the message (``"a training"``)."""
    folder = os.fspath(folder)
    if resume and force:
        raise ParameterError(f"--resume and --force exclude each other: --resume continues the run in "
                             f"{option}, --force replaces it")
    _folder_ok(option, folder)
    present = [n for n in held if os.path.lexists(os.path.join(folder, n))]
    if not present:
        return present
    if resume:
        if resume_needs is not None and resume_needs not in present:
            raise ParameterError(f"--resume: {folder} holds {', '.join(present)} but no {resume_needs} to "
                                 f"continue from; rerun with --force to start over, or choose another {option}")
        return present
    if force:
        return present
    raise ParameterError(f"{option} {folder!r} already holds {what} ({', '.join(present)}); rerun with --resume "
                         f"to continue it, with --force to replace it, or choose another {option}")


def scene_input(scene) -> str | None:
    """The file a ``--scene`` value names (a ``.toml`` path or a path with a folder), or None for a
    built-in scene's name (the rule of :func:`arraysel.scenes.schema.load_scene`)."""
    if not isinstance(scene, (str, os.PathLike)):
        return None
    s = os.fspath(scene)
    return s if s.endswith(".toml") or os.sep in s else None
