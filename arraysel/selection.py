"""One selection, its representations and their checks (one home, imported everywhere else).

A selection of ``k`` of ``Ne`` elements is a :class:`Selection`: its sorted indices and the
array's size, with its two other forms as properties,

* a **mask** -- :attr:`Selection.mask`, ``bool`` array ``(Ne,)`` (a batch ``(B, Ne)`` of 0/1
  floats for the objective: :func:`masks_from_indices`);
* **text** -- :attr:`Selection.text`, ``"0 2 4"``, the ``elements`` column of ``runs.csv`` /
  ``table1.csv`` (:func:`format_elements`); :meth:`Selection.from_text` is its one reader.

Selectors return plain index lists; :func:`check_selection` validates what a selector returned
and :func:`masks_from_indices` a batch of index lists given by a user. Every check raises
:class:`~arraysel.errors.SelectionError` naming what is wrong. Numpy only (a torch tensor is
accepted wherever a sequence is, through ``.detach()``).

Batches of masks in a search: :func:`mask_key` is a mask's hashable key, :func:`survivors` the
best distinct masks of a scored batch (a population's survivors, a race's starts), and
:func:`flagged_elements` the elements each row of a boolean batch flags (the elements a move
switches), as padded index rows.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Iterable, Iterator, Sequence

import numpy as np

from arraysel.errors import SelectionError

__all__ = ["Selection", "check_selection", "indices_to_mask", "mask_to_indices", "masks_from_indices", "format_elements",
           "parse_element_text", "mask_key", "survivors", "flagged_elements", "random_masks"]


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


def random_masks(n_elements: int, k: int, n: int, seed: int = 0) -> np.ndarray:
    """``n`` uniformly random selections of ``k`` of ``n_elements`` elements, boolean (n, Ne), from
    ``seed`` (numpy's default generator: the same seed gives the same masks)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((int(n), int(n_elements)), dtype=bool)
    for r in range(int(n)):
        out[r, rng.choice(int(n_elements), int(k), replace=False)] = True
    return out


def format_elements(indices: Iterable[int] | None) -> str:
    """``"0 2 4"`` (the ``elements`` column of the tables); ``""`` for no selection."""
    return "" if not indices else " ".join(str(int(i)) for i in indices)


def parse_element_text(text: Any) -> list[int]:
    """The indices of an ``elements`` column entry written by :func:`format_elements` (``[]`` when
    empty or missing)."""
    if not isinstance(text, str):
        return []
    tokens = text.split()
    bad = next((t for t in tokens if not _DIGITS.fullmatch(t)), None)
    if bad is not None:  # int() would also take "6_2" and full-width digits
        raise ValueError(f"{bad[:40]!r} is not an element index")
    return [int(t) for t in tokens]


#: an element index as text: ASCII digits only
_DIGITS = re.compile(r"[0-9]+")


@dataclass(frozen=True)
class Selection:
    """A selection of elements: ``indices`` (sorted, distinct, in ``[0, n_elements)``) of an array
    of ``n_elements``. The one type figures and tables take; its text and mask are properties.

    >>> s = Selection.of([4, 0, 2], 8)
    >>> s.text, s.mask.nonzero()[0].tolist(), len(s)
    ('0 2 4', [0, 2, 4], 3)
    >>> Selection.from_text("0 2 4", 8) == s
    True
    """

    indices: tuple[int, ...]
    n_elements: int

    def __post_init__(self) -> None:
        n = self.n_elements
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise SelectionError(f"n_elements must be a whole number >= 1, got {n!r}")
        idx = tuple(self.indices)
        if any(isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)) for i in idx):
            raise SelectionError(f"a selection's indices must be whole numbers, got {list(idx)[:8]}")
        if any(not 0 <= i < n for i in idx):
            raise SelectionError(f"a selection's indices must be in [0, {n - 1}], got "
                                 f"{[int(i) for i in idx if not 0 <= i < n][:5]}")
        if len(set(idx)) != len(idx):
            raise SelectionError(f"a selection repeats elements: {sorted(int(i) for i in idx)}")
        object.__setattr__(self, "indices", tuple(sorted(int(i) for i in idx)))
        object.__setattr__(self, "n_elements", int(n))

    @classmethod
    def of(cls, indices: Any, n_elements: int, k: int | None = None) -> "Selection":
        """The selection of element ``indices`` (a sequence, array or tensor of whole numbers),
        checked (with ``k``: exactly ``k`` of them, :func:`check_selection`)."""
        if k is not None:
            return cls(tuple(check_selection(indices, n_elements, k)), n_elements)
        indices = _plain(indices)
        return cls(tuple(np.asarray(indices).tolist()) if isinstance(indices, np.ndarray) else tuple(indices),
                   n_elements)

    @classmethod
    def from_mask(cls, mask: Any) -> "Selection":
        """The active elements (``> 0.5``) of a mask ``(Ne,)``."""
        m = np.asarray(_plain(mask))
        if m.ndim != 1:
            raise SelectionError(f"a mask must have shape (Ne,), got {m.shape}")
        return cls(tuple(mask_to_indices(m)), m.shape[0])

    @classmethod
    def from_text(cls, text: str, n_elements: int) -> "Selection":
        """The selection an ``elements`` cell holds (:attr:`text`; ``""`` is the empty selection)."""
        try:
            return cls(tuple(parse_element_text(text)), n_elements)
        except ValueError:
            raise SelectionError(f"{str(text)[:40]!r} is not a list of element indices") from None

    @property
    def mask(self) -> np.ndarray:
        """``bool`` mask ``(n_elements,)``."""
        return indices_to_mask(self.indices, self.n_elements)

    @property
    def text(self) -> str:
        """``"0 2 4"``: the ``elements`` column of the tables (:func:`format_elements`)."""
        return format_elements(self.indices)

    def __len__(self) -> int:
        return len(self.indices)

    def __iter__(self) -> Iterator[int]:
        return iter(self.indices)

    def __str__(self) -> str:
        return self.text


def mask_key(mask: np.ndarray) -> bytes:
    """A hashable key of a boolean mask (its packed bits)."""
    return np.packbits(mask).tobytes()


def flagged_elements(flags: np.ndarray, width: int | None = None) -> np.ndarray:
    """The elements each row of ``flags`` (B, Ne) bool flags, in increasing order: int64
    ``(B, width)``, each row padded with ``-1`` after its elements. ``width`` defaults to the
    most any row flags (0 for none); a smaller one than that is refused."""
    flags = np.asarray(flags, dtype=bool)
    most = int(flags.sum(1).max(initial=0))
    width = most if width is None else int(width)
    if width < most:
        raise SelectionError(f"width must be at least {most} (the most elements a row flags), got {width}")
    out = np.full((flags.shape[0], width), -1, dtype=np.int64)
    rows, cols = np.nonzero(flags)
    out[rows, np.arange(rows.size) - np.searchsorted(rows, rows)] = cols
    return out


def survivors(masks: np.ndarray, values: np.ndarray, mu: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``mu`` best distinct masks of ``masks`` (ties: the earlier first) and their values,
    best first."""
    order = np.lexsort((np.arange(values.size), values))
    keep, seen = [], set()
    for idx in order:
        key = mask_key(masks[idx])
        if key not in seen:
            seen.add(key)
            keep.append(idx)
        if len(keep) == mu:
            break
    return masks[keep], values[keep]
