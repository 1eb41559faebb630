"""Where the element maps of :class:`arraysel.constraints.Constraints` come from: the channel
groups of a multiplexer rule (``mux-N-B``) or of a CSV file (``element,group``), either of those
or a sequence of group numbers (:func:`group_map`), and the mirror images of every element under
a symmetry (:func:`mirror_orbits`). :mod:`arraysel.constraints` re-exports every name here.
"""
from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import Any

import numpy as np

from arraysel.errors import ParameterError

_MUX = re.compile(r"^mux-(\d+)-(\d+)$")


def mux_groups(rule: str, n_elements: int) -> np.ndarray:
    """The group (scanner channel) of every element under the multiplexer rule ``mux-N-B``: ``N``
    elements in ``B`` banks of ``N / B`` consecutive elements; channel ``c`` reaches element
    ``c`` of each bank, so element ``e`` is on channel ``e mod (N / B)``. ``mux-1024-4`` is the
    32 x 32 probe on a 256-channel scanner (banks of 8 rows x 32 columns)."""
    m = _MUX.match(str(rule))
    if m is None:
        raise ParameterError(f"constraints.groups = {rule!r} is not a known rule; allowed: 'mux-N-B' "
                             f"(such as 'mux-1024-4') or a CSV file (element,group)")
    n, banks = int(m.group(1)), int(m.group(2))
    if banks < 1 or n < 1 or n % banks:
        raise ParameterError(f"constraints.groups = {rule!r}: N = {n} must be a positive multiple of B = {banks}")
    if n != n_elements:
        raise ParameterError(f"constraints.groups = {rule!r} is for {n} elements; the probe has {n_elements}")
    return np.arange(n, dtype=np.int64) % (n // banks)


def read_group_csv(path: str | Path, n_elements: int) -> np.ndarray:
    """The group of every element from a CSV file with the columns ``element`` and ``group``
    (one row per element, every element once; integers)."""
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(line for line in fh if not line.lstrip().startswith("#")))
    except OSError as exc:
        raise ParameterError(f"constraints.groups: cannot read {path}: {exc}") from None
    if not rows or not {"element", "group"} <= set(rows[0]):
        raise ParameterError(f"{path}: a group file needs the columns element,group")
    out = np.full(n_elements, -1, dtype=np.int64)
    for i, row in enumerate(rows, start=2):
        try:
            e, g = int(row["element"]), int(row["group"])
        except (TypeError, ValueError):
            raise ParameterError(f"{path}, line {i}: element and group must be integers, got "
                                 f"{row['element']!r}, {row['group']!r}") from None
        if not 0 <= e < n_elements or g < 0:
            raise ParameterError(f"{path}, line {i}: element {e} out of range [0, {n_elements - 1}] or group {g} < 0")
        if out[e] >= 0:
            raise ParameterError(f"{path}, line {i}: element {e} is listed twice")
        out[e] = g
    missing = np.flatnonzero(out < 0)
    if missing.size:
        raise ParameterError(f"{path}: elements {missing[:10].tolist()} have no group (the groups must "
                             f"partition all {n_elements} elements; force unconnected ones off)")
    return out


def group_map(spec: Any, n_elements: int, base: Path | None = None) -> np.ndarray:
    """Groups from a rule name, a CSV path (relative to ``base``) or a sequence of group numbers."""
    if isinstance(spec, (str, Path)):
        text = str(spec)
        if _MUX.match(text):
            return mux_groups(text, n_elements)
        if text.lower().endswith(".csv"):
            p = Path(text)
            return read_group_csv(p if p.is_absolute() or base is None else base / p, n_elements)
        return mux_groups(text, n_elements)  # raises naming the allowed forms
    g = np.asarray(spec)
    if g.shape != (n_elements,) or g.dtype.kind not in "iu" or (g < 0).any():
        raise ParameterError(f"constraints.groups must give one group number >= 0 per element "
                             f"({n_elements}), got shape {g.shape}")
    return g.astype(np.int64)


def mirror_orbits(positions: np.ndarray, symmetry: str) -> np.ndarray:
    """``(Ne, m)`` element indices: row ``e`` holds ``e`` and its mirror images (``m`` = 2 for
    ``x`` or ``y``, 4 for ``xy``; an element on a mirror line is its own image)."""
    p = np.asarray(positions, dtype=np.float64)[:, :2]
    scale = max(float(np.ptp(p)) if p.size else 1.0, 1e-12)
    key = {tuple(np.round(q / scale * 1e6).astype(np.int64)): i for i, q in enumerate(p)}
    flips = {"x": [(1, 1), (-1, 1)], "y": [(1, 1), (1, -1)],
             "xy": [(1, 1), (-1, 1), (1, -1), (-1, -1)]}[symmetry]
    out = np.empty((p.shape[0], len(flips)), dtype=np.int64)
    for j, (sx, sy) in enumerate(flips):
        for i, q in enumerate(p):
            img = key.get(tuple(np.round(q * (sx, sy) / scale * 1e6).astype(np.int64)))
            if img is None:
                raise ParameterError(f"constraints.symmetry = {symmetry!r}: element {i} at ({q[0]:.6g}, "
                                     f"{q[1]:.6g}) m has no mirror image among the elements")
            out[i, j] = img
    return out
