"""Reading element selections from text (streamed, linear in the input size).

The writers that used to live here are in :mod:`arraysel.io.atomic` (re-exported).
"""
from __future__ import annotations

import os  # noqa: F401  (tests patch maskio.os)
import re
from typing import Iterator

import numpy as np

from arraysel.io.atomic import atomic_savez, atomic_write_bytes  # noqa: F401  (re-exported: the writers live in arraysel.io.atomic)
from arraysel.errors import ParameterError, SelectionError

#: longest line of a mask file (characters); longer ones are refused without reading them whole
MAX_LINE = 1 << 20
_SPLIT = re.compile(r"[,\s]+")
#: an element index: ASCII digits only (Python's ``int`` also takes ``6_2`` and full-width digits)
_INT = re.compile(r"[+-]?[0-9]+")
#: a UTF-8 byte-order mark, allowed at the start of a file
_BOM = "\ufeff"


def parse_elements(text: str, n_elements: int, k: int | None = None, where: str = "--elements") -> list[int]:
    """Parse '0,2,4' or '0 2 4' (0-based indices) and validate them.

    Raises :class:`SelectionError` naming ``where`` for a non-integer, repeated,
    negative or out-of-range index, or a count different from ``k``. Linear in the
    length of ``text``.
    """
    tokens = [t for t in _SPLIT.split(text.strip()) if t]
    if not tokens:
        raise SelectionError(f"{where}: no element index given")
    bad = next((t for t in tokens if not _INT.fullmatch(t)), None)
    if bad is not None:
        raise SelectionError(f"{where}: {bad[:40]!r} is not an integer element index (digits 0-9, "
                             f"optionally signed)")
    idx = [int(t) for t in tokens]
    out_of_range = [i for i in idx if i < 0 or i >= n_elements]
    if out_of_range:
        raise SelectionError(f"{where}: element indices must be in [0, {n_elements - 1}], got "
                             f"{_short(out_of_range)}")
    if len(set(idx)) != len(idx):
        seen, dup = set(), set()
        for i in idx:
            (dup if i in seen else seen).add(i)
        raise SelectionError(f"{where}: repeated element index {_short(sorted(dup))}")
    if k is not None and len(idx) != k:
        raise SelectionError(f"{where}: expected k = {k} elements, got {len(idx)}")
    return idx


def _short(values: list, n: int = 10) -> str:
    return str(values) if len(values) <= n else f"{values[:n]} and {len(values) - n} more"


def _open_text(path: str, what: str):
    """Open ``path`` for reading UTF-8 text; one-line :class:`ParameterError` for every path problem."""
    if os.path.isdir(path):
        raise ParameterError(f"{what}: {path!r} is a folder, not a file")
    try:
        return open(path, encoding="utf-8", errors="strict", newline=None)
    except FileNotFoundError:
        raise ParameterError(f"{what}: file {path!r} does not exist") from None
    except PermissionError:
        raise ParameterError(f"{what}: file {path!r} cannot be read (permission denied)") from None
    except OSError as exc:
        raise ParameterError(f"{what}: file {path!r} cannot be read ({exc.strerror or exc})") from None


def iter_mask_lines(path: str, n_elements: int, k: int | None, what: str = "--masks") -> Iterator[list[int]]:
    """Yield the selections of a mask file one by one (validated), reading it as a stream.

    One selection per line (0-based indices, comma or whitespace separated, '#' comments).
    Raises :class:`SelectionError` naming the line, :class:`ParameterError` for a path, encoding
    or line-length problem."""
    with _open_text(path, what) as fh:
        no = 0
        while True:
            try:
                line = fh.readline(MAX_LINE + 1)
            except UnicodeDecodeError as exc:
                raise ParameterError(f"{what}: {path!r} is not UTF-8 text (line {no + 1}: byte "
                                     f"0x{exc.object[exc.start]:02x})") from None
            except OSError as exc:
                raise ParameterError(f"{what}: {path!r} cannot be read ({exc.strerror or exc})") from None
            if not line:
                return
            no += 1
            if no == 1 and line.startswith(_BOM):  # a byte-order mark some editors write
                line = line[1:]
            if len(line) > MAX_LINE:
                raise SelectionError(f"{path}, line {no}: longer than {MAX_LINE} characters")
            body = line.split("#", 1)[0].strip()
            if body:
                yield parse_elements(body, n_elements, k, where=f"{path}, line {no}")


def mask_line(path: str, line: int, n_elements: int, what: str = "--masks") -> list[int]:
    """The selection on line ``line`` (1-based, counting every line of the file) of a mask file;
    refused, naming the file and the line, when that line is blank, a comment or past the end."""
    if isinstance(line, bool) or not isinstance(line, int) or line < 1:
        raise ParameterError(f"{what}: the line number must be an integer >= 1, got {line!r}")
    with _open_text(path, what) as fh:
        for no in range(1, line + 1):
            try:
                text = fh.readline(MAX_LINE + 1)
            except UnicodeDecodeError:
                raise ParameterError(f"{what}: {path!r} is not UTF-8 text (line {no})") from None
            if not text:
                raise ParameterError(f"{what}: {path!r} has {no - 1} lines, no line {line}")
            if len(text) > MAX_LINE:
                raise SelectionError(f"{path}, line {no}: longer than {MAX_LINE} characters")
    body = text.split("#", 1)[0].strip()
    if not body:
        raise SelectionError(f"{path}, line {line}: holds no selection (blank or a comment)")
    return parse_elements(body, n_elements, None, where=f"{path}, line {line}")


def count_masks(path: str, n_elements: int, k: int | None, what: str = "--masks") -> int:
    """Validate every line of a mask file (streaming) and return how many selections it holds;
    refuses a file with none."""
    n = 0
    for _ in iter_mask_lines(path, n_elements, k, what):
        n += 1
    if not n:
        raise SelectionError(f"{what}: file {path!r} holds no selection")
    return n


def iter_mask_chunks(path: str, n_elements: int, k: int | None, chunk: int) -> Iterator[tuple[list, np.ndarray]]:
    """Yield ``(selections, masks)`` chunks of at most ``chunk`` selections: the index lists and
    their (B, Ne) float32 0/1 masks."""
    sels: list[list[int]] = []
    for sel in iter_mask_lines(path, n_elements, k):
        sels.append(sel)
        if len(sels) == chunk:
            yield sels, _masks(sels, n_elements)
            sels = []
    if sels:
        yield sels, _masks(sels, n_elements)


def _masks(sels: list[list[int]], n_elements: int) -> np.ndarray:
    m = np.zeros((len(sels), n_elements), dtype=np.float32)
    rows = np.repeat(np.arange(len(sels)), [len(s) for s in sels])
    m[rows, np.fromiter((i for s in sels for i in s), dtype=np.int64, count=len(rows))] = 1.0
    return m
