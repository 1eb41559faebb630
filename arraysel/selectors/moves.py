"""The moves of a swap search over exact-``k`` selections, as the few elements each changes.

* a *swap* (one active element off, one inactive on): :func:`random_swap_pairs` draws distinct
  ones, :func:`random_swaps` applies several at once (a perturbation);
* a *segment shift* (:func:`shift_moves`): the active and inactive elements of a run of
  consecutive indices rotated by a few places, which moves a group of active elements (a block of
  a periodic layout) together where single swaps would pass through worse selections;
  :func:`shift_segments` holds each as the few places it changes and :func:`apply_shifts` /
  :func:`shifted_masks` form the selections.

:mod:`arraysel.selectors.lossmodel` predicts what a move does to the loss;
:class:`~arraysel.selectors.localsearch.SwapSearch` scores and takes them.
"""
from __future__ import annotations

import numpy as np

from arraysel.selectors.contract import Option

#: longest segment a shift move displaces (``shift_len`` default)
SHIFT_LEN = 24
#: shift moves scored without improvement before a selection counts as a local optimum of them
SHIFT_SCAN = 4096

__all__ = ["SHIFT_LEN", "SHIFT_SCAN", "shift_options", "random_swap_pairs", "random_swaps", "shift_moves",
           "shift_segments", "apply_shifts", "shifted_masks"]


def shift_options(shift: int = 0, shift_scan: int = SHIFT_SCAN) -> dict[str, Option]:
    """The segment-shift options of the selectors built on
    :class:`~arraysel.selectors.localsearch.SwapSearch` (``shift``, ``shift_len``, ``shift_scan``,
    with the defaults given), passed on as keywords of the same names."""
    return {
        "shift": Option(int, shift, "largest displacement of a segment shift, the second neighbourhood a descent "
                        "tries at a local optimum of swaps (0: swaps only)", lo=0),
        "shift_len": Option(int, SHIFT_LEN, "longest segment (consecutive element indices) a shift moves", lo=2),
        "shift_scan": Option(int, shift_scan, "shifts scored without improvement before a local optimum is "
                             "declared (a guided descent scores them in its model's order: with the quadratic "
                             "model 512 is enough)", lo=1),
    }


def random_swap_pairs(mask: np.ndarray, b: int, rng: np.random.Generator,
                      constraints=None) -> tuple[np.ndarray, np.ndarray]:
    """``min(b, k (Ne - k))`` distinct random swaps ``(out, into)`` of a boolean mask (only
    those that keep it feasible under channel-group ``constraints``)."""
    if constraints is not None:
        return constraints.random_swap_pairs(mask, b, rng)
    on, off = np.flatnonzero(mask), np.flatnonzero(~mask)
    total = on.size * off.size
    pick = rng.choice(total, size=min(b, total), replace=False)
    return on[pick // off.size], off[pick % off.size]


def random_swaps(mask: np.ndarray, m: int, rng: np.random.Generator, constraints=None) -> np.ndarray:
    """``mask`` after ``m`` random swaps (distinct elements swapped out and in; feasible ones
    under channel-group ``constraints``)."""
    if constraints is not None:
        return constraints.random_swaps(mask, m, rng)
    out = mask.copy()
    on, off = np.flatnonzero(mask), np.flatnonzero(~mask)
    m = min(m, on.size, off.size)
    if m <= 0:
        return out
    out[rng.choice(on, m, replace=False)] = False
    out[rng.choice(off, m, replace=False)] = True
    return out


def shift_moves(n: int, longest: int, most: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """Every segment shift of an ``n``-element selection as rows ``(start, length, d)``: the
    segment ``start .. start + length - 1`` (``2 <= length <= longest``) is rotated by ``d``
    places (``1 <= |d| <= min(most, length - 1)``; positive: towards higher indices, the
    elements pushed past its end coming back at its start), which keeps ``k``. A shift moves a
    group of active elements together, which single swaps can only do through worse
    selections. In a random order when ``rng`` is given; ``(0, 3)`` when there is none."""
    rows = []
    for length in range(2, min(int(longest), int(n)) + 1):
        dmax = min(int(most), length - 1)
        if dmax < 1:
            continue
        starts = np.arange(n - length + 1)
        ds = np.concatenate([np.arange(1, dmax + 1), -np.arange(1, dmax + 1)])
        st, dd = np.meshgrid(starts, ds, indexing="ij")
        rows.append(np.stack([st.ravel(), np.full(st.size, length), dd.ravel()], axis=1))
    moves = np.concatenate(rows) if rows else np.zeros((0, 3), dtype=np.int64)
    return moves[rng.permutation(len(moves))] if rng is not None else moves


def shift_segments(n: int, moves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The segment shifts ``moves`` (rows ``(start, length, d)``, :func:`shift_moves`) as two
    ``(len(moves), L)`` int32 arrays ``(at, source)``, ``L`` the longest segment: shift ``i`` puts
    element ``source[i, j]`` of a selection at ``at[i, j]``. Rows of shorter segments are padded
    with ``n``, a place past the selection's last element (extend the selection by one ``False``):
    a few integers a shift, where a whole shifted selection would take ``n``."""
    moves = np.asarray(moves, dtype=np.int64).reshape(-1, 3)
    longest = int(moves[:, 1].max()) if len(moves) else 1
    start, length, d = moves[:, 0:1], moves[:, 1:2], moves[:, 2:3]
    j = np.arange(longest)[None]
    inside = j < length
    at = np.where(inside, start + j, n).astype(np.int32)
    source = np.where(inside, start + (j - d) % np.maximum(length, 1), n).astype(np.int32)
    return at, source


def apply_shifts(extended: np.ndarray, at: np.ndarray, source: np.ndarray) -> np.ndarray:
    """The selections ``extended[:-1]`` with the shifts ``(at, source)`` of :func:`shift_segments`
    applied, one a row: ``(len(at), Ne)``; ``extended`` is the selection with one ``False`` appended."""
    out = np.repeat(extended[None], len(at), axis=0)
    out[np.arange(len(at))[:, None], at] = extended[source]
    return out[:, :-1]


def shifted_masks(mask: np.ndarray, moves: np.ndarray) -> np.ndarray:
    """``(len(moves), Ne)`` copies of ``mask``, each with one segment shift of ``moves``
    (rows ``(start, length, d)``, :func:`shift_moves`) applied."""
    mask = np.asarray(mask, dtype=bool)
    return apply_shifts(np.append(mask, False), *shift_segments(mask.shape[0], moves))

