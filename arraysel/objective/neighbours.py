"""One-swap neighbourhoods of a selection: listed, built and scored in one call.

A *swap* switches one active element ``out`` off and one inactive element ``into`` on, so a
neighbour keeps exactly ``k`` active elements; a selection of ``k`` of ``Ne`` elements has
``k (Ne - k)`` of them.

:func:`evaluate_swaps` scores the neighbours ``(out[i], into[i])`` of ``mask``: through the
objective's own ``evaluate_swaps`` when it has the capability
(:class:`~arraysel.objective.contract.ScoresSwaps`: it exploits what the neighbours share and
returns the values scoring them independently gives), otherwise by building the neighbour masks
(:func:`swap_masks`) and calling ``evaluate``. Either way the result is what ``evaluate`` of the
neighbour masks returns, in the order of the pairs.
"""
from __future__ import annotations

import numpy as np

from arraysel.errors import SelectionError

__all__ = ["swap_pairs", "swap_masks", "evaluate_swaps", "check_swaps", "prepare_neighbourhoods"]


def swap_pairs(mask: np.ndarray, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Every swap ``(out, into)`` of a boolean mask (out-major order), shuffled when ``rng`` is given."""
    on, off = np.flatnonzero(mask), np.flatnonzero(~np.asarray(mask, dtype=bool))
    out = np.repeat(on, off.size)
    into = np.tile(off, on.size)
    if rng is not None:
        order = rng.permutation(out.size)
        out, into = out[order], into[order]
    return out, into


def check_swaps(mask, out, into) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``mask`` as a boolean ``(Ne,)`` array and ``out``, ``into`` as int64 ``(B,)`` arrays;
    :class:`~arraysel.errors.SelectionError` naming the argument when ``mask`` is not 1-D
    boolean (or 0/1), an index is out of range, ``mask[out]`` is not all active or
    ``mask[into]`` not all inactive."""
    m = np.asarray(mask)
    if m.ndim != 1:
        raise SelectionError(f"mask must be one selection of shape (Ne,), got shape {m.shape}")
    if m.dtype != bool:
        if m.dtype.kind not in "biuf" or not np.isin(m, (0, 1)).all():
            raise SelectionError("mask must hold booleans or 0/1")
        m = m != 0
    n = m.size
    a = np.asarray(out, dtype=np.int64).reshape(-1)
    b = np.asarray(into, dtype=np.int64).reshape(-1)
    if a.shape != b.shape:
        raise SelectionError(f"out and into must have the same length, got {a.size} and {b.size}")
    for name, idx in (("out", a), ("into", b)):
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise SelectionError(f"{name} holds element indices outside [0, {n - 1}]")
    if a.size and not m[a].all():
        raise SelectionError("out must name active elements of mask")
    if b.size and m[b].any():
        raise SelectionError("into must name inactive elements of mask")
    return m, a, b


def swap_masks(mask, out, into) -> np.ndarray:
    """The neighbour masks ``(B, Ne)``: ``mask`` with ``out[i]`` off and ``into[i]`` on."""
    m, a, b = check_swaps(mask, out, into)
    cands = np.repeat(m[None], a.size, axis=0)
    rows = np.arange(a.size)
    cands[rows, a] = False
    cands[rows, b] = True
    return cands


def evaluate_swaps(objective, mask, out, into) -> dict[str, np.ndarray]:
    """What ``objective.evaluate`` returns for the neighbours ``(out[i], into[i])`` of ``mask``
    (``{name: float64 (B,)}``), through the objective's ``evaluate_swaps`` when it has one."""
    m, a, b = check_swaps(mask, out, into)
    own = getattr(objective, "evaluate_swaps", None)
    if callable(own):
        return own(m, a, b)
    return objective.evaluate(swap_masks(m, a, b))


def prepare_neighbourhoods(objective) -> float:
    """Do an objective's one-off work for scoring neighbourhoods now (its
    ``prepare_neighbourhoods()``, where it has one: the physics objective forms the pair-image
    rows its :meth:`evaluate_swaps` gathers); returns the seconds it took. The runners call it
    before the budget of a run whose selector scores neighbourhoods starts."""
    import time

    prepare = getattr(objective, "prepare_neighbourhoods", None)
    t0 = time.perf_counter()
    if callable(prepare):
        prepare()
    return time.perf_counter() - t0
