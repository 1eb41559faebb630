"""One-swap neighbourhoods of a selection: listed, built and scored in one call.

A *swap* switches one active element ``out`` off and one inactive element ``into`` on, so a
neighbour keeps exactly ``k`` active elements; a selection of ``k`` of ``Ne`` elements has
``k (Ne - k)`` of them.

:func:`evaluate_swaps` scores the neighbours ``(out[i], into[i])`` of ``mask``: through the
objective's neighbourhood when it has the capability (``objective.neighbourhood()``,
:class:`~arraysel.objective.contract.Neighbourhood`: it exploits what the neighbours share and
returns the values scoring them independently gives), otherwise by building the neighbour masks
(:func:`swap_masks`) and calling ``evaluate``. Either way the result is what ``evaluate`` of the
neighbour masks returns, in the order of the pairs.

A *move* of ``m`` elements switches the active elements ``out[i, :]`` off and the inactive
elements ``into[i, :]`` on at once (a segment shift is one: it moves a group of active elements
together; rows of fewer elements are padded with ``-1``, :func:`moves_between`);
:func:`evaluate_moves` scores the neighbours ``(out[i], into[i])`` (``(B, m)`` each)
through the objective's neighbourhood when it has one, else ``evaluate`` of the masks
(:func:`move_masks`).
"""
from __future__ import annotations

import numpy as np

from arraysel.errors import SelectionError
from arraysel.objective.contract import MovesNeighbourhood, Neighbourhood
from arraysel.selection import flagged_elements

__all__ = ["swap_pairs", "swap_masks", "evaluate_swaps", "check_swaps", "check_moves", "move_masks", "moves_between",
           "evaluate_moves", "swaps_as_moves", "prepare_neighbourhoods", "neighbourhood_of"]


def swap_pairs(mask: np.ndarray, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Every swap ``(out, into)`` of a boolean mask (out-major order), shuffled when ``rng`` is given."""
    on, off = np.flatnonzero(mask), np.flatnonzero(~np.asarray(mask, dtype=bool))
    out = np.repeat(on, off.size)
    into = np.tile(off, on.size)
    if rng is not None:
        order = rng.permutation(out.size)
        out, into = out[order], into[order]
    return out, into


def _as_mask(mask) -> np.ndarray:
    """``mask`` as a boolean ``(Ne,)`` array (SelectionError when it is not one selection of 0/1)."""
    m = np.asarray(mask)
    if m.ndim != 1:
        raise SelectionError(f"mask must be one selection of shape (Ne,), got shape {m.shape}")
    if m.dtype != bool:
        if m.dtype.kind not in "biuf" or not np.isin(m, (0, 1)).all():
            raise SelectionError("mask must hold booleans or 0/1")
        m = m != 0
    return m


def _check_elements(m: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """SelectionError naming ``out``/``into`` when an index of ``a``/``b`` is out of range, or an
    element of ``a`` is inactive in ``m``, or one of ``b`` active."""
    n = m.size
    for name, idx in (("out", a), ("into", b)):
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise SelectionError(f"{name} holds element indices outside [0, {n - 1}]")
    if a.size and not m[a].all():
        raise SelectionError("out must name active elements of mask")
    if b.size and m[b].any():
        raise SelectionError("into must name inactive elements of mask")


def check_swaps(mask, out, into) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``mask`` as a boolean ``(Ne,)`` array and ``out``, ``into`` as int64 ``(B,)`` arrays;
    :class:`~arraysel.errors.SelectionError` naming the argument when ``mask`` is not 1-D
    boolean (or 0/1), an index is out of range, ``mask[out]`` is not all active or
    ``mask[into]`` not all inactive."""
    m = _as_mask(mask)
    a = np.asarray(out, dtype=np.int64).reshape(-1)
    b = np.asarray(into, dtype=np.int64).reshape(-1)
    if a.shape != b.shape:
        raise SelectionError(f"out and into must have the same length, got {a.size} and {b.size}")
    _check_elements(m, a, b)
    return m, a, b


def check_moves(mask, out, into) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``mask`` as a boolean ``(Ne,)`` array and ``out``, ``into`` as int64 ``(B, m)`` arrays (a
    ``(B,)`` array is read as ``m = 1``; ``-1`` pads a row that switches fewer than m elements);
    :class:`~arraysel.errors.SelectionError` naming the argument when they differ in shape, an
    index is out of range, ``mask[out]`` is not all active, ``mask[into]`` not all inactive, a
    row names an element twice, or a row of ``out`` and ``into`` switch different numbers of
    elements."""
    m = _as_mask(mask)
    a, b = (np.asarray(v, dtype=np.int64) for v in (out, into))
    a, b = (v.reshape(-1, 1) if v.ndim < 2 else v for v in (a, b))
    if a.ndim != 2 or a.shape != b.shape:
        raise SelectionError(f"out and into must be (B, m) arrays of one shape, got {a.shape} and {b.shape}")
    n = m.size
    for name, idx in (("out", a), ("into", b)):
        if idx.size and (idx.min() < -1 or idx.max() >= n):
            raise SelectionError(f"{name} holds element indices outside [0, {n - 1}] (-1: no element)")
    va, vb = a >= 0, b >= 0
    if (va.sum(1) != vb.sum(1)).any():
        raise SelectionError("out and into must switch as many elements in each row (-1 pads a row)")
    _check_elements(m, a[va], b[vb])
    if a.shape[1] > 1:
        for name, idx in (("out", a), ("into", b)):
            s = np.sort(idx, axis=1)
            if ((s[:, 1:] == s[:, :-1]) & (s[:, 1:] >= 0)).any():
                raise SelectionError(f"{name} names an element twice in one move")
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
    (``{name: float64 (B,)}``), through the objective's neighbourhood
    (:func:`neighbourhood_of`) when it has one."""
    m, a, b = check_swaps(mask, out, into)
    return evaluate_moves(objective, m, a[:, None], b[:, None])


def move_masks(mask, out, into) -> np.ndarray:
    """The neighbour masks ``(B, Ne)``: ``mask`` with the elements ``out[i]`` off and ``into[i]``
    on (``(B, m)`` each, ``-1`` for none; :func:`check_moves`)."""
    m, a, b = check_moves(mask, out, into)
    cands = np.repeat(m[None], a.shape[0], axis=0)
    for idx, on in ((a, False), (b, True)):
        r, c = np.nonzero(idx >= 0)
        cands[r, idx[r, c]] = on
    return cands


def moves_between(mask, cands) -> tuple[np.ndarray, np.ndarray]:
    """``(out, into)``, int64 ``(B, m)`` each, of the moves that take ``mask`` (Ne,) to each of the
    selections ``cands`` (B, Ne) of as many elements: the elements switched off and on, in
    increasing order, rows padded with ``-1`` to the widest move (m = 0 for no selection)."""
    m = _as_mask(mask)
    c = np.asarray(cands, dtype=bool).reshape(-1, m.size)
    if (c.sum(1) != m.sum()).any():
        raise SelectionError("cands must hold as many active elements as mask")
    return flagged_elements(m[None] & ~c), flagged_elements(c & ~m[None])


def evaluate_moves(objective, mask, out, into) -> dict[str, np.ndarray]:
    """What ``objective.evaluate`` returns for the neighbours of ``mask`` that switch the elements
    ``out[i]`` off and ``into[i]`` on (``(B, m)`` each; ``{name: float64 (B,)}``): through the
    objective's neighbourhood (:func:`neighbourhood_of`) when it has
    one, else ``evaluate`` of the masks. A search asks for the neighbourhood once and keeps it;
    this function asks at every call."""
    m, a, b = check_moves(mask, out, into)
    nb = neighbourhood_of(objective)
    if nb is not None:
        return nb.evaluate(m, a, b)
    return objective.evaluate(move_masks(m, a, b))


def swaps_as_moves(objective, evaluate_swaps):
    """``evaluate_moves(mask, out, into)`` of an objective that scores one-swaps only
    (``evaluate_swaps``): moves of one element each go to it, other moves to ``evaluate`` of their
    masks."""
    def evaluate(mask, out, into):
        m, a, b = check_moves(mask, out, into)
        if a.shape[1] == 1 and (a >= 0).all():
            return evaluate_swaps(m, a[:, 0], b[:, 0])
        return objective.evaluate(move_masks(m, a, b))

    return evaluate


def prepare_neighbourhoods(objective) -> float:
    """Do an objective's one-off work for scoring neighbourhoods now (its neighbourhood's
    ``prepare()``, :func:`neighbourhood_of`, where it has one: the
    physics objective forms the pair-image rows its neighbourhood gathers); returns the seconds it
    took. The runners call it before the budget of a run whose selector scores neighbourhoods
    starts."""
    import time

    t0 = time.perf_counter()
    nb = neighbourhood_of(objective)
    if nb is not None:
        nb.prepare()
    return time.perf_counter() - t0


def neighbourhood_of(objective) -> Neighbourhood | None:
    """The :class:`Neighbourhood` of ``objective``: its ``neighbourhood()``; for an objective
    written before that method existed, one made of its ``evaluate_moves`` (or ``evaluate_swaps``,
    or ``evaluate`` of the masks) and ``prepare_neighbourhoods`` methods
    (:class:`MovesNeighbourhood`), when it has one of them besides ``evaluate``; else ``None``. A
    neighbourhood without ``block()`` (written before it) is given one that prefers no block. The one
    place the optional methods are looked up: a search asks once, and keeps what it gets."""
    own = getattr(objective, "neighbourhood", None)
    if callable(own):
        nb = own()
        if nb is not None and not callable(getattr(nb, "block", None)):  # written before block()
            return MovesNeighbourhood(nb.evaluate, nb.prepare)
        return nb
    moves = getattr(objective, "evaluate_moves", None)
    swaps = getattr(objective, "evaluate_swaps", None)
    prepare = getattr(objective, "prepare_neighbourhoods", None)
    prepare = prepare if callable(prepare) else None
    if callable(moves):
        return MovesNeighbourhood(moves, prepare)
    if callable(swaps):
        return MovesNeighbourhood(swaps_as_moves(objective, swaps), prepare)
    if prepare is not None:  # prepared for neighbourhoods that it scores as their masks
        return MovesNeighbourhood(lambda m, a, b: objective.evaluate(move_masks(m, a, b)), prepare)
    return None
