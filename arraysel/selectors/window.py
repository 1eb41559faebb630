"""Large-neighbourhood search: a window of elements freed and re-solved on the model of the loss.

A *window* is a set of ``w`` elements near one another (:meth:`WindowSearch.window`: the ``w``
elements nearest a random centre, or half of them near each of two random centres, by the
elements' positions, their grid or their index). Re-solving it (:meth:`WindowSearch.resolve`)
keeps every element outside the window and as many active elements inside it as before, so every
candidate has exactly ``k``; of the ``C(w, m)`` ways to place the window's ``m`` active elements,
all are ranked by the quadratic model of the loss at the selection
(:func:`~arraysel.selectors.lossmodel.move_changes`: exact on the model, by enumeration), and
the ``verify`` best predicted are scored exactly in one call, as moves from the selection
(:meth:`~arraysel.selectors.searchstate.SearchState.score_moved`, which drops those that leave
the channel groups); the best of them is taken when it improves. A window whose ``C(w, m)``
exceeds ``cap`` is narrowed to its nearest elements until it fits.

:class:`WindowSearch` is the swap engine (:class:`~arraysel.selectors.localsearch.SwapSearch`)
whose descents try windows at a local optimum of swaps and shifts: ``windows`` windows in a row
that do not improve declare a local optimum of the large neighbourhood; an improving window is
followed by a new swap descent. The race of first descents, the perturbations and restarts are
the engine's (``lns``'s settings: :data:`LNS`).
"""
from __future__ import annotations

import itertools
import math

import numpy as np

from arraysel.errors import check_number
from arraysel.objective.contract import element_layout
from arraysel.selection import mask_key
from arraysel.selectors.contract import Option
from arraysel.selectors.localsearch import SwapSearch
from arraysel.selectors.lossmodel import move_changes
from arraysel.selectors.swapsettings import SWAP

#: the window shapes: near one centre (``near``), near two (``two``), or the two in turn (``mixed``)
WINDOW_SHAPES = ("near", "two", "mixed")
#: a round's perturbation: the best verified placement of a random window, or random swaps
KICKS = ("window", "swaps")
#: ``lns``'s defaults: elements a window frees, the best predicted placements scored exactly, the
#: windows in a row without improvement that declare a local optimum, the most placements a
#: window may have
WIDTH, VERIFY, WINDOWS, CAP = 16, 32, 4, 50_000
#: the most swaps a placement may be from the window's current one (``radius``): the quadratic
#: model ranks moves of a few swaps well near a local optimum, and overrates larger ones
RADIUS = 3
#: ``lns``'s swap-engine settings: ``swap``'s, with a perturbation (a window kick's radius) that grows
#: by one swap a round without a new best, up to 6 swaps above ``perturb`` (at 120 s a run it lowered
#: the median of every 1-D scene: benchmarks/results/compare-search-lns-120s)
LNS = SWAP.replace(max_perturb=6)

__all__ = ["WINDOW_SHAPES", "KICKS", "RADIUS", "WIDTH", "VERIFY", "WINDOWS", "CAP", "LNS", "WindowSearch",
           "window_options", "placements", "element_coordinates"]


def window_options() -> dict[str, Option]:
    """The declared window options of ``lns`` (``width``, ``verify``, ``windows``, ``window``, ``kick``,
    ``radius``, ``cap``)."""
    return {
        "width": Option(int, WIDTH, "elements a window frees (the nearest to a random centre, or half near each "
                        "of two; fewer where C(width, active inside) exceeds cap)", lo=2),
        "verify": Option(int, VERIFY, "placements of a window's active elements scored exactly, the best the "
                         "quadratic model predicts (one call)", lo=1),
        "windows": Option(int, WINDOWS, "windows in a row without improvement before a local optimum of the "
                          "large neighbourhood is declared (0: no windows, the swap engine alone)", lo=0),
        "window": Option(str, "mixed", "window shape: near one random centre, two (half near each of two "
                         "centres: moves active elements between regions) or mixed (in turn)",
                         choices=WINDOW_SHAPES),
        "kick": Option(str, "window", "a round's perturbation of the best selection: the best verified placement "
                       "of a random window (window) or the engine's random swaps (swaps)", choices=KICKS),
        "radius": Option(int, RADIUS, "most swaps a placement may be from the window's current one (the model "
                         "overrates large moves; 0: every placement)", lo=0),
        "cap": Option(int, CAP, "most placements a window may have; a wider one is narrowed to its nearest "
                      "elements", lo=2),
    }


def placements(w: int, m: int) -> np.ndarray:
    """Every placement of ``m`` active elements in ``w`` places: bool ``(C(w, m), w)``, in the order of
    :func:`itertools.combinations`."""
    combos = np.array(list(itertools.combinations(range(w), m)), dtype=np.int64).reshape(-1, m)
    out = np.zeros((combos.shape[0], w), dtype=bool)
    np.put_along_axis(out, combos, True, axis=1)
    return out


def element_coordinates(objective) -> np.ndarray:
    """Where each element is, for choosing windows: its position where the objective declares
    them, else its ``(row, column)`` on the element grid, else its index: ``(Ne, d)`` float."""
    n = int(objective.n_elements)
    grid, pos = element_layout(objective)
    if pos is not None:
        return pos
    if grid is not None:
        return np.stack(np.divmod(np.arange(n), grid[1]), axis=1).astype(np.float64)
    return np.arange(n, dtype=np.float64)[:, None]


class WindowSearch(SwapSearch):
    """The swap engine with window re-solves at its local optima (see the module).

    ``WindowSearch(objective, k, rng, settings=LNS, *, width, verify, windows, window, cap, **kw)``;
    the other keywords as :class:`~arraysel.selectors.searchstate.SearchState`.
    """

    def __init__(self, objective, k: int, rng: np.random.Generator, settings=None, *, width: int = WIDTH,
                 verify: int = VERIFY, windows: int = WINDOWS, window: str = "mixed", cap: int = CAP,
                 kick: str = "window", radius: int = RADIUS, **kw):
        super().__init__(objective, k, rng, LNS if settings is None else settings, **kw)
        self.width = int(check_number("width", width, lo=2, integer=True))
        self.verify = int(check_number("verify", verify, lo=1, integer=True))
        self.windows = int(check_number("windows", windows, lo=0, integer=True))
        self.cap = int(check_number("cap", cap, lo=2, integer=True))
        self.radius = int(check_number("radius", radius, lo=0, integer=True))
        self.shape = WINDOW_SHAPES[WINDOW_SHAPES.index(window)]
        self.kick = KICKS[KICKS.index(kick)]
        self._xyz = element_coordinates(objective)
        self._placements: dict[tuple[int, int], np.ndarray] = {}
        self._tried: set[bytes] = set()  # (selection, window) re-solved without improvement
        self.windows_tried = 0
        self.window_moves = 0  # improving window re-solves taken

    def _descent(self, mask: np.ndarray, value: float):
        """The swap engine's descent, then windows at each of its local optima (see the module)."""
        while True:
            for mask, value in super()._descent(mask, value):
                yield mask, value
            found = self._window_step(mask, value) if self.windows and 0 < self.k < self.n else None
            if found is None:
                return
            mask, value = found
            self.window_moves += 1
            self.moves += 1
            self._note(mask, value)
            yield mask, value

    def _window_step(self, mask: np.ndarray, value: float) -> tuple[np.ndarray, float] | None:
        """The first of ``windows`` random windows whose re-solve improves on ``value``, or None."""
        for _ in range(self.windows):
            found = self.resolve(mask, value, self.window())
            if found is not None:
                return found
        return None

    def window(self) -> np.ndarray:
        """A random window: element indices, nearest first (see the module)."""
        self.windows_tried += 1
        two = self.shape == "two" or (self.shape == "mixed" and self.windows_tried % 2 == 0)
        centres = self.rng.choice(self.n, 2 if two and self.n > 1 else 1, replace=False)
        orders = [np.argsort(((self._xyz - self._xyz[c]) ** 2).sum(axis=1), kind="stable") for c in centres]
        if len(orders) == 1:
            return orders[0][:self.width]
        taken, out = set(), []
        for e in itertools.chain.from_iterable(zip(*orders)):  # near each centre in turn
            if len(out) == self.width:
                break
            if int(e) not in taken:
                taken.add(int(e))
                out.append(int(e))
        return np.asarray(out, dtype=np.int64)

    def fitted(self, mask: np.ndarray, window: np.ndarray) -> np.ndarray:
        """``window`` narrowed to its first elements until its placements number at most ``cap``."""
        w = window.size
        while w > 2 and math.comb(w, int(mask[window[:w]].sum())) > self.cap:
            w -= 1
        return window[:w]

    def resolve(self, mask: np.ndarray, value: float, window: np.ndarray) -> tuple[np.ndarray, float] | None:
        """The best placement of ``window``'s active elements among those verified
        (:meth:`verified`) and its Mean when it improves on ``value``, else None (see the module)."""
        tried = mask_key(mask) + np.sort(window).astype(np.int32).tobytes()
        if tried in self._tried:
            return None
        cands, values = self.verified(mask, window)
        i = int(np.argmin(values)) if values.size else 0
        if values.size and values[i] < value:
            return cands[i].copy(), float(values[i])
        if len(self._tried) >= self.cache_size:
            self._tried.clear()
        self._tried.add(tried)
        return None

    def verified(self, mask: np.ndarray, window: np.ndarray,
                 radius: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The placements of ``window``'s active elements (other than ``mask``'s) the model of the
        loss at ``mask`` predicts best, scored exactly in one call (:meth:`score_moved`): among the
        ``4 verify`` best predicted, the ``verify`` best not scored before and every one scored
        before (free); all of them in a random order without a model. Only placements within
        ``radius`` swaps (default :attr:`radius`; 0: all). ``(masks, Means)``, both empty when the
        window is all active or all inactive."""
        window = np.sort(self.fitted(mask, window))
        inside = mask[window]
        m, w = int(inside.sum()), window.size
        if m in (0, w):
            return np.zeros((0, self.n), dtype=bool), np.zeros(0)
        if (w, m) not in self._placements:
            self._placements[(w, m)] = placements(w, m)
        d = self._placements[(w, m)].astype(np.int8) - inside
        size = np.abs(d).sum(axis=1) // 2  # swaps a placement is from the current one (0: itself)
        radius = self.radius if radius is None else radius
        d = d[(size > 0) & ((size <= radius) | (radius == 0))]
        order = self._ranked(mask, window, d, 4 * self.verify)
        cands = np.repeat(mask[None], order.size, axis=0)
        cands[:, window] = d[order] + inside > 0
        seen = np.array([mask_key(c) in self._cache for c in cands], dtype=bool)
        keep = seen | (np.cumsum(~seen) <= self.verify)
        cands = cands[keep]
        return cands, self.score_moved(mask, cands)

    def _ranked(self, mask: np.ndarray, window: np.ndarray, d: np.ndarray, most: int) -> np.ndarray:
        """The ``most`` moves of ``d`` (rows of changes at ``window``) the model of the loss at
        ``mask`` predicts best, best first (a random order without a model)."""
        model = self._model(mask) if self.loss_model is not None else None
        if model is None:
            return self.rng.permutation(d.shape[0])[:most]
        pred = move_changes(model[0], model[1], np.broadcast_to(window, d.shape), d)
        take = min(most, pred.size)
        top = np.argpartition(pred, take - 1)[:take] if take < pred.size else np.arange(pred.size)
        return top[np.lexsort((top, pred[top]))]

    def perturbed(self, base: np.ndarray, strength: int) -> np.ndarray:
        """With ``kick = window``, the best verified placement of a random window of ``base``
        (:meth:`verified`; ``radius`` grown by as many swaps as ``strength`` has grown above
        ``perturb``), which differs from it (random swaps when the window offers none); else the
        engine's ``strength`` random swaps."""
        if self.kick == "window" and 0 < self.k < self.n:
            radius = self.radius + max(0, strength - self.perturb) if self.radius else 0
            cands, values = self.verified(base, self.window(), radius)
            if values.size and np.isfinite(values).any():
                return cands[int(np.argmin(values))].copy()
        return super().perturbed(base, strength)
