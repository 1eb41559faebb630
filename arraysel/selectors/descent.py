"""The descent of a swap search: from a selection, improving moves until none improves.

A descent (:meth:`SwapDescent.descend`) scores the selection's one-swap neighbours, first or best
improvement (``mode``); in ``first`` mode in chunks of ``chunk`` a call, a share ``guide`` of each
in the order the model of the loss predicts (:class:`~arraysel.selectors.lossmodel.GuidedOrder`),
and declares a local optimum after ``scan`` x the neighbourhood without improvement. At a local
optimum of swaps it tries segment shifts (``shift`` above 0, :meth:`SwapDescent._shift_step`)
and the two-swaps the quadratic model predicts best (``pairs`` above 0,
:meth:`SwapDescent._pair_step`); with ``compound`` above 1 a chunk's improving swaps on distinct
elements may be taken together (:meth:`SwapDescent._compound_step`). See
:mod:`arraysel.selectors.localsearch` for the whole search.
"""
from __future__ import annotations

import math

import numpy as np

from arraysel.objective.neighbours import move_masks
from arraysel.selectors.lossmodel import GuidedOrder, best_pair_swaps, move_changes
from arraysel.selectors.moves import apply_shifts, shift_moves, shift_segments
from arraysel.selectors.searchstate import SearchState


class SwapDescent(SearchState):
    """Descents from selections (see the module); constructed as :class:`SearchState`."""

    def __init__(self, objective, k: int, rng: np.random.Generator, settings=None, **kw):
        super().__init__(objective, k, rng, settings, **kw)
        self.shifts = 0  # improving segment shifts taken
        self.pair_moves = 0  # improving two-swaps taken
        self.compound_moves = 0  # steps that took several swaps of a chunk together
        self._shifts: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (at, source, keys); formed once
        self.guide = GuidedOrder(self.settings.guide)
        self.shift_guide = GuidedOrder(self.guide.share)  # the shifts' guided share adapts on its own
        self._guided = self.guide.share > 0 and self.loss_model is not None

    def descend(self, mask: np.ndarray, value: float) -> tuple[np.ndarray, float]:
        """Improve ``mask`` by swaps until it is a local optimum; return it and its value."""
        mask = mask.copy()
        for mask, value in self._descent(mask, value):
            pass
        return mask, value

    def _descent(self, mask: np.ndarray, value: float):
        """:meth:`descend` one move at a time: yields ``(mask, value)`` after each improving swap
        and ends at a local optimum."""
        while True:
            a, b = self._swap_pairs(mask)
            if a.size == 0:
                return
            moved = False
            if self.mode == "best":
                cands, values = self.score_swaps(mask, a, b)
                i = int(np.argmin(values))
                if values[i] < value:
                    mask, value, moved = cands[i], float(values[i]), True
            else:
                limit = max(1, int(math.ceil(self.scan * a.size)))
                pred = None
                if self._guided and self.guide.wants_gradient():
                    pred = self._predict(mask, a, b)
                    self._guided = pred is not None  # an objective without a usable gradient: never again
                chunks = (self.guide.chunks(a, b, pred, self.chunk, limit, self.lead) if self.block is None
                          else self._block_chunks(a, pred))
                for pick, ng in chunks:
                    cands, values = self.score_swaps(mask, a[pick], b[pick])
                    i = int(np.argmin(values))
                    if values[i] < value:
                        self.guide.credit(None if pred is None else bool(i < ng))
                        step = cands[i], float(values[i])
                        if self.compound > 1:
                            step = self._compound_step(mask, value, a[pick], b[pick], values, step)
                        (mask, value), moved = step, True
                        break
            if not moved and self.shift:
                found = self._shift_step(mask, value)
                if found is not None:
                    (mask, value), moved = found, True
                    self.shifts += 1
            if not moved and self.pairs:
                found = self._pair_step(mask, value)
                if found is not None:
                    (mask, value), moved = found, True
                    self.pair_moves += 1
            if not moved:
                return
            self.moves += 1
            self._note(mask, value)
            yield mask, value

    def _block_chunks(self, a: np.ndarray, pred: np.ndarray | None):
        """The chunks of a first-improvement descent for a neighbourhood that prefers blocks
        (:attr:`block`): yield ``(index array into the swaps a, how many of them come first from
        the prediction)``, each chunk every swap of a few outgoing elements (at least the block's
        ``outgoing``, and as many as make ``chunk`` swaps), the outgoing elements in the random
        order of ``a`` and, a share ``guide`` of each chunk, in the order of their best predicted
        swap (:class:`GuidedOrder` over outgoing elements); ``scan`` x the outgoing elements in all."""
        _, first, inv, counts = np.unique(a, return_index=True, return_inverse=True, return_counts=True)
        rank = np.empty(first.size, dtype=np.int64)
        rank[np.argsort(first, kind="stable")] = np.arange(first.size)   # position in a's random order
        row = rank[inv]
        counts = counts[np.argsort(rank)]
        by_row = np.argsort(row, kind="stable")
        ends = np.cumsum(counts)
        starts = ends - counts
        opred = None
        if pred is not None:
            opred = np.full(first.size, np.inf)
            np.minimum.at(opred, row, pred)
        per = a.size / first.size
        rows = max(self.block.outgoing, int(math.ceil(self.chunk / per)))
        lead = int(math.ceil(self.lead / per)) if self.lead else 0
        idx = np.arange(first.size)
        for pick, ng in self.guide.chunks(idx, idx, opred, rows, max(1, int(math.ceil(self.scan * idx.size))), lead):
            swaps = np.concatenate([by_row[starts[r]:ends[r]] for r in pick])
            yield swaps, int(counts[pick[:ng]].sum())

    def _compound_step(self, mask: np.ndarray, value: float, a: np.ndarray, b: np.ndarray,
                       values: np.ndarray, single: tuple[np.ndarray, float]) -> tuple[np.ndarray, float]:
        """The move a chunk of swaps ``(a[i], b[i])`` of ``mask`` whose Means are ``values`` leads
        to, when its best one, ``single`` (its selection and Mean), improves on ``value``
        (``compound`` above 1): the improving swaps that switch distinct elements, best first,
        are taken together as far as that scores best (the prefixes of up to ``compound`` of
        them, scored in one call as moves, :meth:`score_moved`), so a descent where many swaps
        improve at once takes several a step; ``single`` when fewer than two such swaps improve
        or no prefix scores below it."""
        order = np.argsort(values, kind="stable")
        taken, used = [], set()
        for j in order:
            if not values[j] < value or len(taken) == self.compound:
                break
            if int(a[j]) in used or int(b[j]) in used:
                continue
            taken.append(j)
            used.update((int(a[j]), int(b[j])))
        if len(taken) < 2:
            return single
        prefixes = np.repeat(mask[None], len(taken) - 1, axis=0)   # row p: the first p + 2 swaps
        for q, j in enumerate(taken):
            prefixes[max(0, q - 1):, a[j]] = False
            prefixes[max(0, q - 1):, b[j]] = True
        pv = self.score_moved(mask, prefixes)
        j = int(np.argmin(pv))
        if pv[j] < single[1]:
            self.compound_moves += 1
            return prefixes[j].copy(), float(pv[j])
        return single

    def _shift_step(self, mask: np.ndarray, value: float) -> tuple[np.ndarray, float] | None:
        """The best shift of the first chunk holding one that improves on ``value``, or None after
        ``shift_scan`` shifts (or all) without improvement. Only the distinct shifted selections
        that differ from ``mask`` are scored, in a random order or, in a guided descent, a share
        of each chunk in the order the model predicts (:func:`move_changes`, :attr:`shift_guide`).
        A shift is held as the few elements it changes (:func:`shift_segments`); only the
        selections of the chunks scored are formed."""
        if self._shifts is None:
            at, source = shift_segments(self.n, shift_moves(self.n, self.shift_len, self.shift))
            keys = np.random.default_rng(0).integers(1, 2 ** 62, size=self.n + 1, dtype=np.int64)
            keys[self.n] = 0
            self._shifts = (at, source, keys)
        at, source, keys = self._shifts
        order = self.rng.permutation(len(at))
        at, source = at[order], source[order]
        extended = np.append(mask, False)
        d = extended[source].astype(np.int8) - extended[at]
        # equal changes give equal keys (sums mod 2**64 of a key an element): one of each is kept
        key = (d.astype(np.int64) * keys[at]).sum(axis=1)
        _, first = np.unique(key, return_index=True)
        first = np.sort(first)  # the random order
        first = first[np.any(d[first] != 0, axis=1)]
        if first.size == 0:
            return None
        at, source, d = at[first], source[first], d[first]
        pred = None
        if self._guided and self.guide_shifts and self.shift_guide.wants_gradient():
            m = self._model(mask)
            self._guided = m is not None
            pred = None if m is None else move_changes(m[0], m[1], at, d)
        index = np.arange(first.size)
        for pick, ng in self.shift_guide.chunks(index, index, pred, self.chunk, min(self.shift_scan, index.size)):
            cands = apply_shifts(extended, at[pick], source[pick])
            values = self.score_moved(mask, cands)
            i = int(np.argmin(values))
            if values[i] < value:
                self.shift_guide.credit(None if pred is None else bool(i < ng))
                return cands[i].copy(), float(values[i])
        return None

    def _pair_step(self, mask: np.ndarray, value: float) -> tuple[np.ndarray, float] | None:
        """The best two-swap of the first chunk holding one that improves on ``value``, among the
        ``pairs`` two-swaps the quadratic model at ``mask`` predicts best
        (:func:`best_pair_swaps`), scored ``chunk`` a call in that order (as moves of two elements,
        :meth:`score_moved`); None when none of them improves, or without a quadratic model
        (``model = linear``, or an objective without a usable loss)."""
        model = self._model(mask) if self._guided else None
        if model is None or model[1] is None:
            return None
        out, into, _ = best_pair_swaps(model[0], model[1], mask, self.pairs)
        for s in range(0, out.shape[0], self.chunk):
            cands = move_masks(mask, out[s:s + self.chunk], into[s:s + self.chunk])
            values = self.score_moved(mask, cands)
            j = int(np.argmin(values))
            if values[j] < value:
                return cands[j].copy(), float(values[j])
        return None

