"""Multi-start iterated local search over an elite pool, with path relinking (``ils``'s search)."""
from __future__ import annotations

import math

import numpy as np

from arraysel.errors import check_number
from arraysel.selection import mask_key
from arraysel.selectors.descent import SwapDescent
from arraysel.selectors.moves import random_swaps
from arraysel.selectors.swapsettings import ILS

#: the elite pool's own settings, ``ils``'s defaults: starting selections, elites kept, the chance
#: that a round relinks two elites (else it perturbs one)
STARTS, ELITE, RELINK = 2, 8, 0.3

class EliteSearch(SwapDescent):
    """Multi-start iterated local search over an elite pool, with path relinking.

    1. **starts**: the given start and ``starts - 1`` random selections, each improved by a
       descent (:meth:`~arraysel.selectors.descent.SwapDescent.descend`) into a local optimum; the distinct local optima
       found so far, at most ``elite`` of them, the best first, form the *elite pool*;
    2. **rounds**, until the budget ends: with probability ``relink`` (and at least two
       elites) a *path relinking* from one elite towards another (:meth:`relink`), otherwise a
       *perturbation* of an elite (a random one of the better half) by ``strength`` random
       swaps; then a descent from the result, which enters the pool when it is new and better
       than its worst member (replacing it). ``strength`` starts at ``perturb``, grows by one
       after each round that found no new best (up to ``max_perturb``) and falls back to
       ``perturb`` when one does (variable-strength perturbation);
    3. **restart**: after ``restart_after`` rounds in a row without a new best, a fresh random
       selection is descended and enters the pool (which keeps the best elites).

    Path relinking from ``A`` towards ``B`` walks, one swap at a time, from ``A`` to ``B``: each
    step scores (one batched call) the swaps of an element of ``A`` not in ``B`` for one of ``B``
    not in ``A`` still to be made (at most ``relink_batch`` of them, a random subset when there
    are more) and takes the best; the best selection strictly between the two ends is the
    result. It combines what two good, different selections share.

    Every call of the objective is a batch; the run is reproducible from the generator. It
    ends like :class:`~arraysel.selectors.localsearch.SwapSearch` (the objective's
    BudgetExhausted, or ``max_rounds``). The descents and rounds read ``settings`` (default:
    :data:`~arraysel.selectors.swapsettings.ILS`; ``race`` is not used); a ``perturb`` of 0 acts
    as 1. Other keywords as :class:`~arraysel.selectors.searchstate.SearchState`.
    """

    def __init__(self, objective, k: int, rng: np.random.Generator, settings=None, *, starts: int = STARTS,
                 elite: int = ELITE, relink: float = RELINK, relink_batch: int = 256, **kw):
        super().__init__(objective, k, rng, ILS if settings is None else settings, **kw)
        self.starts = int(check_number("starts", starts, lo=1, integer=True))
        self.elite = int(check_number("elite", elite, lo=1, integer=True))
        self.relink_p = float(check_number("relink", relink, lo=0.0, hi=1.0))
        self.relink_batch = int(check_number("relink_batch", relink_batch, lo=1, integer=True))
        self.pool: list[tuple[float, bytes, np.ndarray]] = []  # (value, key, mask), best first
        self.relinks = 0

    def _enter(self, mask: np.ndarray, value: float) -> None:
        """Offer a local optimum to the elite pool (distinct selections, the best ``elite``)."""
        self._note(mask, value)
        key = mask_key(mask)
        if any(key == kk for _, kk, _ in self.pool) or not math.isfinite(value):
            return
        if len(self.pool) >= self.elite:
            if value >= self.pool[-1][0]:
                return
            self.pool.pop()
        self.pool.append((value, key, mask.copy()))
        self.pool.sort(key=lambda e: e[0])

    def relink(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float] | None:
        """The best selection strictly between ``a`` and ``b`` on a greedy swap path from ``a``
        towards ``b`` (see the class); None when they are one swap apart or less."""
        cur = a.copy()
        best: tuple[np.ndarray, float] | None = None
        while True:
            outs = np.flatnonzero(cur & ~b)
            ins = np.flatnonzero(b & ~cur)
            if outs.size <= 1:  # the next swap would reach b
                return best
            o = np.repeat(outs, ins.size)
            i = np.tile(ins, outs.size)
            if self.constraints is not None:
                keep = self.constraints.allowed_swaps(cur, o, i)
                o, i = o[keep], i[keep]
                if o.size == 0:
                    return best
            if o.size > self.relink_batch:
                pick = self.rng.choice(o.size, self.relink_batch, replace=False)
                o, i = o[pick], i[pick]
            cands, values = self.score_swaps(cur, o, i)
            j = int(np.argmin(values))
            cur = cands[j]
            if best is None or values[j] < best[1]:
                best = (cur.copy(), float(values[j]))

    def run(self, start) -> tuple[list[int], float]:
        """Search from ``start`` (element indices or a boolean mask) and ``starts - 1`` random
        selections; return the best selection and its Mean (see the class)."""
        mask = self._start_mask(start)
        if self.k in (0, self.n):
            value = float(self.score(mask[None])[0])
            self._note(mask, value)
            return [int(i) for i in np.flatnonzero(self.best_mask)], self.best_value
        for s in range(self.starts):
            m = mask if s == 0 else self._fresh_mask(self.rng)
            v = float(self.score(m[None])[0])
            self._note(m, v)
            m, v = self.descend(m, v)
            self.local_optima += 1
            self._enter(m, v)
        strength = max(1, self.perturb)
        stale = rounds = idle = 0
        while self.max_rounds is None or rounds < self.max_rounds:
            rounds += 1
            if self.objective.remaining() <= 0:
                break
            spent = self.scored
            best_before = self.best_value
            if not self.pool or (self.restart_after and stale >= self.restart_after):
                m, stale = self._fresh_mask(self.rng), 0  # (an empty pool: nothing finite scored yet)
                v = float(self.score(m[None])[0])
            elif len(self.pool) >= 2 and self.rng.random() < self.relink_p:
                i, j = self.rng.choice(len(self.pool), 2, replace=False)
                found = self.relink(self.pool[i][2], self.pool[j][2])
                self.relinks += 1
                if found is None:
                    idle = idle + 1 if self.scored == spent else 0
                    continue
                m, v = found
            else:
                half = max(1, (len(self.pool) + 1) // 2)
                base = self.pool[int(self.rng.integers(half))][2]
                m = (random_swaps(base, strength, self.rng) if self.constraints is None
                              else random_swaps(base, strength, self.rng, self.constraints))
                v = float(self.score(m[None])[0])
            m, v = self.descend(m, v)
            self.local_optima += 1
            self._enter(m, v)
            if self.best_value < best_before:
                stale, strength = 0, max(1, self.perturb)
            else:
                stale += 1
                strength = min(max(1, self.max_perturb), strength + 1)
            idle = idle + 1 if self.scored == spent else 0
            if idle >= self.MAX_IDLE_ROUNDS:
                break
        return [int(i) for i in np.flatnonzero(self.best_mask)], self.best_value
