"""Local models of the loss that order a descent's moves: which to score first.

At a selection ``w`` the loss of a move to ``w + d`` is predicted by its gradient
(``linear``: ``d.g``, :func:`loss_gradient`) or by its gradient and Hessian (``quadratic``:
``d.g + d.H.d / 2``, :func:`loss_quadratic`): for every one-swap neighbour at once
(:func:`swap_changes`), for moves of a few elements such as segment shifts
(:func:`move_changes`), and for the two-swaps predicted best (:func:`best_pair_swaps`).
:class:`GuidedOrder` takes a share of each chunk of scored neighbours in the predicted order and
adapts that share to where the improving moves come from. The predictions only order the moves:
every move taken is scored exactly.
"""
from __future__ import annotations

import numpy as np

from arraysel.errors import NumericalError
from arraysel.objective.contract import loss_model_of
from arraysel.selectors.contract import Option

#: how a first-improvement descent predicts the change of a swap: by the loss's gradient
#: (``linear``) or by its gradient and Hessian (``quadratic``, :func:`loss_quadratic`)
MODEL_CHOICES = ("linear", "quadratic")
#: the automatic model (``model`` None): quadratic on arrays of at most this many elements (a
#: Hessian costs ``Ne`` evaluations and ``Ne^2`` memory), linear on larger ones
QUADRATIC_MAX_ELEMENTS = 256
#: active and inactive elements a two-swap step draws its moves from (:func:`best_pair_swaps`)
PAIR_WIDTH = 64
#: the gradient of a quadratic model's predictions between Hessians: the loss's own at each
#: selection (``exact``), or the model's carried along the moves (``update``: ``g + H d``)
GRADIENT_CHOICES = ("exact", "update")
#: the most elements (switched off, as many on) a selection may be from the last gradient for
#: ``gradient = update`` to carry it there; farther (a segment shift, another descent's turn)
#: the loss's gradient is taken
GRADIENT_UPDATE_MAX = 2

__all__ = ["MODEL_CHOICES", "QUADRATIC_MAX_ELEMENTS", "PAIR_WIDTH", "GRADIENT_CHOICES", "GRADIENT_UPDATE_MAX",
           "model_options", "loss_gradient", "loss_quadratic", "model_gradient", "model_quadratic", "swap_changes",
           "move_changes", "best_pair_swaps", "GuidedOrder"]


def model_options() -> dict[str, Option]:
    """The declared options ``model`` and ``refresh`` of a search whose descents order swaps by a
    model of the loss (:meth:`~arraysel.selectors.localsearch.SwapSearch._predict`)."""
    return {
        "model": Option(str, None, "how swaps are ranked: by the loss's gradient (linear) or by its gradient "
                        "and Hessian (quadratic; a Hessian costs Ne evaluations); auto: quadratic up to "
                        f"{QUADRATIC_MAX_ELEMENTS} elements, linear above", choices=MODEL_CHOICES),
        "refresh": Option(int, 8, "quadratic model: moves between Hessians", lo=1),
        "gradient": Option(str, "update", "quadratic model: the gradient at each move between Hessians: exact "
                           "(the loss's, one backward pass) or update (the model's, g + H d, carried from "
                           f"the last one up to {GRADIENT_UPDATE_MAX} swaps away; no backward pass)",
                           choices=GRADIENT_CHOICES),
    }


def model_gradient(model, mask: np.ndarray) -> np.ndarray | None:
    """The gradient (Ne,) float64 of a :class:`~arraysel.objective.contract.LossModel` at the 0/1
    selection ``mask`` (one evaluation and one gradient step of the budget), or ``None`` where
    ``model`` is None, the loss is not finite there
    (:class:`~arraysel.errors.NumericalError`) or the gradient is zero or not finite. Every
    other error propagates (:class:`~arraysel.selectors.contract.BudgetExhausted` included)."""
    if model is None:
        return None
    try:
        g = np.asarray(model.gradient(np.asarray(mask, dtype=np.float64)), dtype=np.float64)
    except NumericalError:
        return None
    if not np.isfinite(g).all() or not np.any(g):
        return None
    return g


def model_quadratic(model, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The gradient ``(Ne,)`` and the Hessian ``(Ne, Ne)`` (float64, symmetrised) of a
    :class:`~arraysel.objective.contract.LossModel` at the 0/1 selection ``mask`` (``Ne``
    evaluations of the budget), or ``None`` where ``model`` is None, the loss is not finite there
    (:class:`~arraysel.errors.NumericalError`) or a result is not finite. Every other error
    propagates (:class:`~arraysel.selectors.contract.BudgetExhausted` included)."""
    if model is None:
        return None
    mask = np.asarray(mask, dtype=bool)
    n = mask.shape[0]
    try:
        g, H = model.model(mask)
    except NumericalError:
        return None
    g, H = np.asarray(g, dtype=np.float64), np.asarray(H, dtype=np.float64)
    if g.shape != (n,) or H.shape != (n, n) or not (np.isfinite(g).all() and np.isfinite(H).all()):
        return None
    return g, 0.5 * (H + H.T)


def loss_gradient(objective, mask: np.ndarray) -> np.ndarray | None:
    """:func:`model_gradient` of the objective's loss model
    (:func:`~arraysel.objective.contract.loss_model_of`, asked at this call: a search asks once
    and keeps it)."""
    return model_gradient(loss_model_of(objective), mask)


def loss_quadratic(objective, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`model_quadratic` of the objective's loss model
    (:func:`~arraysel.objective.contract.loss_model_of`, asked at this call: a search asks once
    and keeps it): its own Hessian where it has one, else
    :func:`~arraysel.objective.contract.hessian_by_rows` of its ``mask_loss``."""
    return model_quadratic(loss_model_of(objective), mask)


def swap_changes(g: np.ndarray, H: np.ndarray | None, out: np.ndarray, into: np.ndarray) -> np.ndarray:
    """The change of the loss that the quadratic model ``g``, ``H`` (:func:`loss_quadratic`; ``H``
    None: the linear model) predicts for each swap ``(out[i], into[i])``:
    ``g[into] - g[out] + (H[out, out] + H[into, into]) / 2 - H[out, into]``."""
    d = g[into] - g[out]
    if H is not None:
        diag = np.diagonal(H)
        d = d + 0.5 * (diag[out] + diag[into]) - H[out, into]
    return d


def move_changes(g: np.ndarray, H: np.ndarray | None, at: np.ndarray, d: np.ndarray,
                 block: int = 4096) -> np.ndarray:
    """The change of the loss that the quadratic model ``g``, ``H`` (``H`` None: the linear model)
    predicts for each move ``i`` that changes the selection by ``d[i, j]`` (+1 on, -1 off, 0
    nothing) at element ``at[i, j]``: ``d.g + d.H.d / 2`` over the elements it changes (a swap:
    :func:`swap_changes`). Entries at ``Ne`` or beyond are padding (``d`` 0 there). A few entries
    a move, so a move costs ``L^2`` (``L`` entries), not ``Ne^2``."""
    n = g.shape[0]
    at = np.asarray(at, dtype=np.int64)
    d = np.asarray(d, dtype=np.float64)
    at = np.where(at < n, at, n)
    gx = np.append(np.asarray(g, dtype=np.float64), 0.0)
    out = (d * gx[at]).sum(axis=1)
    if H is not None:
        Hx = np.zeros((n + 1, n + 1))
        Hx[:n, :n] = H
        for s in range(0, len(at), block):
            a, w = at[s:s + block], d[s:s + block]
            out[s:s + block] += 0.5 * np.einsum("bi,bij,bj->b", w, Hx[a[:, :, None], a[:, None, :]], w)
    return out


def best_pair_swaps(g: np.ndarray, H: np.ndarray, mask: np.ndarray, m: int, width: int = PAIR_WIDTH,
                    block: int = 256) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``m`` two-swap moves of ``mask`` (two active elements off, two inactive ones on) whose
    change the quadratic model ``g``, ``H`` predicts lowest, best first: ``(out (m', 2), into
    (m', 2), predicted (m',))``, ``m' = min(m, moves)``.

    A two-swap ``d = e_b1 + e_b2 - e_a1 - e_a2`` is predicted to change the loss by
    ``d.g + d.H.d / 2 = S[a1, b1] + S[a2, b2] + H[a1, a2] + H[b1, b2] - H[a1, b2] - H[a2, b1]``,
    ``S`` the one-swap predictions (:func:`swap_changes`), whichever way the two swaps are paired.
    The moves are drawn from the ``width`` active elements and the ``width`` inactive ones whose
    best one-swap prediction is lowest (all of them when there are no more), so a call costs at
    most ``(width (width - 1) / 2)^2`` predictions, formed ``block`` pairs of active elements at a
    time."""
    mask = np.asarray(mask, dtype=bool)
    act, ina = np.flatnonzero(mask), np.flatnonzero(~mask)
    if act.size < 2 or ina.size < 2 or m < 1:
        return np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64), np.zeros(0)
    S = swap_changes(g, H, act[:, None], ina[None, :])  # (active, inactive)
    if act.size > width:
        keep = np.sort(np.argpartition(S.min(axis=1), width - 1)[:width])
        act, S = act[keep], S[keep]
    if ina.size > width:
        keep = np.sort(np.argpartition(S.min(axis=0), width - 1)[:width])
        ina, S = ina[keep], S[:, keep]
    Hab, Haa, Hbb = H[np.ix_(act, ina)], H[np.ix_(act, act)], H[np.ix_(ina, ina)]
    ii, jj = np.triu_indices(act.size, 1)
    pp, qq = np.triu_indices(ina.size, 1)
    cross = Hbb[pp, qq][None, :]
    best_v, best_i = np.zeros(0), np.zeros(0, np.int64)
    for s in range(0, ii.size, block):
        i, j = ii[s:s + block, None], jj[s:s + block, None]
        v = S[i, pp] + S[j, qq] + Haa[i, j] + cross - Hab[i, qq] - Hab[j, pp]
        flat = v.ravel()
        take = min(m, flat.size)
        top = np.argpartition(flat, take - 1)[:take] if take < flat.size else np.arange(flat.size)
        best_v = np.concatenate([best_v, flat[top]])
        best_i = np.concatenate([best_i, top + s * pp.size])
        if best_v.size > 4 * m:
            keep = np.argpartition(best_v, m - 1)[:m]
            best_v, best_i = best_v[keep], best_i[keep]
    order = np.lexsort((best_i, best_v))[:m]
    best_v, best_i = best_v[order], best_i[order]
    a, b = best_i // pp.size, best_i % pp.size
    out = np.stack([act[ii[a]], act[jj[a]]], axis=1)
    into = np.stack([ina[pp[b]], ina[qq[b]]], axis=1)
    return out, into, best_v


def _chunk_sizes(chunk: int, lead: int):
    """``lead``, ``2 lead``, ... up to ``chunk``, then ``chunk`` for ever (``lead`` 0: ``chunk``)."""
    size = chunk if lead <= 0 else min(lead, chunk)
    while True:
        yield size
        size = min(2 * size, chunk)


class GuidedOrder:
    """Which one-swap neighbours a first-improvement descent scores next, chunk by chunk.

    The swaps ``(out[i], into[i])`` come in a random order. With a predicted change of each swap
    (:meth:`~arraysel.selectors.localsearch.SwapSearch._predict`: the gradient's first-order
    change ``g[into] - g[out]``, or the quadratic model's), each chunk takes
    ``round(share * chunk)`` swaps in the order of that prediction (most improving first) and the
    rest in the random order, no swap twice. :meth:`credit` moves ``share`` by ``step`` towards
    the part that held the chunk's best improving move, within ``[0, hi]``; at share 0 the
    gradient is only computed every ``probe`` moves (:meth:`wants_gradient`), with share
    ``probe_share`` for that move, so a gradient that stops predicting costs little and one that
    predicts again is found back.
    """

    def __init__(self, share: float, step: float = 0.125, hi: float = 0.875, probe: int = 8,
                 probe_share: float = 0.5):
        self.share = float(share)
        self.step, self.hi, self.probe, self.probe_share = float(step), float(hi), int(probe), float(probe_share)
        self.moves = 0
        self.guided_hits = 0
        self.random_hits = 0

    def wants_gradient(self) -> bool:
        return self.share > 0 or self.moves % self.probe == 0

    def chunks(self, a: np.ndarray, b: np.ndarray, pred: np.ndarray | None, chunk: int, limit: int,
               lead: int = 0):
        """Yield ``(index array into a/b, number of them taken from the prediction)`` per chunk,
        ``limit`` swaps in all; ``pred`` the predicted change of each swap (None: random order).
        With ``lead`` above 0 the first chunk holds ``lead`` swaps and each next one twice as
        many, up to ``chunk``."""
        n = min(limit, a.size)
        sizes = _chunk_sizes(chunk, lead)
        if pred is None:
            s = 0
            while s < n:
                e = min(s + next(sizes), n)
                yield np.arange(s, e), 0
                s = e
            return
        share = self.share if self.share > 0 else self.probe_share
        ranked = np.argsort(pred, kind="stable")
        taken = np.zeros(a.size, dtype=bool)
        gi = ri = done = 0
        while done < n:
            size = min(next(sizes), n - done)
            ng = min(size, int(round(share * size)))
            pick = []
            while len(pick) < ng and gi < ranked.size:
                j = ranked[gi]
                gi += 1
                if not taken[j]:
                    taken[j] = True
                    pick.append(j)
            ng = len(pick)
            while len(pick) < size and ri < a.size:
                if not taken[ri]:
                    taken[ri] = True
                    pick.append(ri)
                ri += 1
            done += len(pick)
            yield np.asarray(pick, dtype=np.int64), ng

    def credit(self, guided: bool | None) -> None:
        """After a move: ``guided`` whether its swap came from the prediction (None: the move was
        made without a gradient)."""
        self.moves += 1
        if guided is None:
            return
        if guided:
            self.guided_hits += 1
            self.share = self.probe_share if self.share == 0 else min(self.hi, self.share + self.step)
        else:
            self.random_hits += 1
            self.share = max(0.0, self.share - self.step)

