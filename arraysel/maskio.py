"""Reading element selections from text, and writing result files atomically."""
from __future__ import annotations

import os  # noqa: F401  (tests patch maskio.os)
import re

from .atomic import atomic_savez, atomic_write_bytes  # noqa: F401  (re-exported: the writers live in arraysel.atomic)
from .errors import ParameterError, SelectionError


def parse_elements(text: str, n_elements: int, k: int | None = None, where: str = "--elements") -> list[int]:
    """Parse '0,2,4' or '0 2 4' (0-based indices) and validate them.

    Raises :class:`SelectionError` naming ``where`` for a non-integer, repeated,
    negative or out-of-range index, or a count different from ``k``.
    """
    tokens = [t for t in re.split(r"[,\s]+", text.strip()) if t]
    if not tokens:
        raise SelectionError(f"{where}: no element index given")
    try:
        idx = [int(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not re.fullmatch(r"[+-]?\d+", t))
        raise SelectionError(f"{where}: {bad!r} is not an integer element index") from None
    out_of_range = [i for i in idx if i < 0 or i >= n_elements]
    if out_of_range:
        raise SelectionError(f"{where}: element indices must be in [0, {n_elements - 1}], got {out_of_range}")
    dup = sorted({i for i in idx if idx.count(i) > 1})
    if dup:
        raise SelectionError(f"{where}: repeated element index {dup}")
    if k is not None and len(idx) != k:
        raise SelectionError(f"{where}: expected k = {k} elements, got {len(idx)}")
    return idx


def read_mask_file(path: str, n_elements: int, k: int | None) -> list[list[int]]:
    """One selection per line (0-based indices, comma or whitespace separated, '#' comments)."""
    try:
        with open(path) as fh:
            lines = fh.readlines()
    except FileNotFoundError:
        raise ParameterError(f"--masks: file {path!r} does not exist") from None
    out = []
    for no, line in enumerate(lines, 1):
        body = line.split("#", 1)[0].strip()
        if not body:
            continue
        out.append(parse_elements(body, n_elements, k, where=f"{path}, line {no}"))
    if not out:
        raise SelectionError(f"--masks: file {path!r} holds no selection")
    return out
