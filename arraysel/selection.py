"""One selection, its representations and their checks (one home, imported everywhere else).

A selection of ``k`` of ``Ne`` elements travels as

* **indices** -- a sorted ``list[int]`` (what selectors return, what rows store);
* a **mask** -- ``bool`` array ``(Ne,)`` (or a batch ``(B, Ne)`` of 0/1 floats for the objective);
* **text** -- ``"0 2 4"`` in ``runs.csv`` / ``table1.csv``.

:func:`check_selection` validates what a selector returned; :func:`masks_from_indices`
validates a batch of index lists given by a user. Both raise
:class:`~arraysel.errors.SelectionError` naming what is wrong. Numpy only (a torch tensor is
accepted wherever a sequence is, through ``.detach()``).
"""
from __future__ import annotations

from typing import Any, Iterable, Sequence

import numpy as np

from arraysel.errors import SelectionError

__all__ = ["check_selection", "indices_to_mask", "mask_to_indices", "masks_from_indices", "format_elements",
           "parse_element_text"]


def _plain(x: Any):
    """A torch tensor as numpy (without importing torch)."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):
        return x.detach().cpu().numpy()
    return x


def check_selection(selection: Any, n_elements: int, k: int) -> list[int]:
    """Return ``selection`` as a sorted list of ints after checking it holds exactly
    ``k`` distinct indices in ``[0, n_elements)``; raise :class:`SelectionError`."""
    selection = _plain(selection)
    if isinstance(selection, np.ndarray):
        selection = selection.tolist()
    if not isinstance(selection, Sequence) or isinstance(selection, (str, bytes)):
        raise SelectionError(f"a selection must be a list of element indices, got {type(selection).__name__}")
    out = []
    for x in selection:
        if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, np.integer)):
            raise SelectionError(f"selection holds a non-integer entry {x!r}")
        out.append(int(x))
    bad = [i for i in out if not 0 <= i < n_elements]
    if bad:
        raise SelectionError(f"selection holds indices outside [0, {n_elements}): {bad[:5]}")
    if len(set(out)) != len(out):
        raise SelectionError(f"selection repeats elements: {sorted(out)}")
    if len(out) != k:
        raise SelectionError(f"selection holds {len(out)} elements, expected k = {k}")
    return sorted(out)


def indices_to_mask(indices: Iterable[int], n_elements: int) -> np.ndarray:
    """Boolean mask ``(Ne,)`` with ``True`` at ``indices``."""
    m = np.zeros(n_elements, dtype=bool)
    m[list(indices)] = True
    return m


def mask_to_indices(mask, n_elements: int | None = None) -> list[int]:
    """Sorted active indices of a mask (bool or 0/1)."""
    return [int(i) for i in np.flatnonzero(np.asarray(_plain(mask)) > 0.5)]


def masks_from_indices(selections, n_elements: int, k: int | None = None) -> np.ndarray:
    """(B, Ne) 0/1 float masks from lists of active element indices, validated.

    Raises :class:`SelectionError` naming the offending selection (its position)
    for a repeated, negative or out-of-range index, or a wrong count.
    """
    out = np.zeros((len(selections), n_elements), dtype=np.float64)
    for i, sel in enumerate(selections):
        idx = [int(v) for v in sel]
        if any(v < 0 or v >= n_elements for v in idx):
            raise SelectionError(f"selection {i}: element indices must be in [0, {n_elements - 1}], got {idx}")
        if len(set(idx)) != len(idx):
            raise SelectionError(f"selection {i}: repeated element index in {idx}")
        if k is not None and len(idx) != k:
            raise SelectionError(f"selection {i}: expected k = {k} elements, got {len(idx)}")
        if not idx:
            raise SelectionError(f"selection {i}: empty selection")
        out[i, idx] = 1.0
    return out


def format_elements(indices: Iterable[int] | None) -> str:
    """``"0 2 4"`` (the ``elements`` column of the tables); ``""`` for no selection."""
    return "" if not indices else " ".join(str(int(i)) for i in indices)


def parse_element_text(text: Any) -> list[int]:
    """The indices of an ``elements`` column entry written by :func:`format_elements` (``[]`` when
    empty or missing)."""
    return [int(i) for i in text.split()] if isinstance(text, str) else []
