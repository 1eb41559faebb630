"""Reading element selections from text, and writing result files atomically."""
from __future__ import annotations

import io
import os
import re
import tempfile

import numpy as np

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


def atomic_write_bytes(path: str, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and ``os.replace``."""
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_savez(path: str, **arrays) -> None:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())
