"""Polish a selection of a sector scene on its per-beam loss (``docs/sector.md``).

The search of a sector scene runs on the two-way beam pattern, which ranks selections only
roughly as their points' PSFs do (``benchmarks/results/sector-ranking``). With the sector fast
path (:meth:`~arraysel.objective.sector_objective.SectorObjective.point_images`) the per-beam
loss (:meth:`~arraysel.objective.sector_objective.SectorObjective.beam_loss`: the worst side lobe
over the points, plus a penalty on the mean -6 dB width past a cap) costs a fraction of a second a
selection, so a local search can run on it directly.

:func:`polish_on_beams` is that search: swap moves (one selected element out, one unselected in),
drawn at random in batches. Each batch is first screened on the points whose side lobe lies within
``screen_db`` of the worst (``screen_db = 0``: the worst point alone, a sixth of the cost on the
built-in scene; a polished selection has its points' side lobes within a fraction of a dB of each
other, and a move screened on one point then mostly raises another); the best ``keep`` screened
moves are scored on every point, and the best of them is taken when it lowers the search's loss.
A move's images come from the fast path's sums of the current selection (``base``: its receive
sums change by two elements' rows, not by all of them).

The search's loss is the per-beam loss, or, with ``soft_db > 0``, its smooth maximum over the
points: ``soft_db * log(sum_p exp(PSL_p / soft_db))`` in place of the worst ``PSL_p`` (a move that
lowers every point but the worst, and leaves that one where it was, then counts as a gain; with
the hard maximum such plateaus stop the search). The selection returned is the best by the
per-beam loss itself. The search stops at its time limit, at ``evaluations`` (selections scored,
each point counted: a selection scored on six points counts six; a round that would end past the
time limit, by the latest round's time, is not started), when ``stop()`` says so, or after
``patience`` batches without a gain.

With ``guide > 0``, that share of each batch's moves is not drawn at random but proposed by the
gradient of a smooth worst side lobe over the screened points (:class:`_Guide`: one backward pass
through the fast path a new selection): the swaps it predicts to lower the side lobes most,
each tried once a selection. The screening and the scoring are as for the random moves.
"""
from __future__ import annotations

import time

import numpy as np

from arraysel.errors import ParameterError, check_number

__all__ = ["polish_on_beams", "GUIDE_DB"]

#: the temperature (dB) of the guide's smooth maxima over the side-lobe pixels and over the points
GUIDE_DB = 0.5


def _swaps(mask: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    on, off = np.flatnonzero(mask), np.flatnonzero(~mask)
    out = np.repeat(mask[None], n, axis=0)
    rows = np.arange(n)
    out[rows, rng.choice(on, n)] = False
    out[rows, rng.choice(off, n)] = True
    return out


def _proposals(mask, batch: int, rng, guider, on: list[int], guide: float, width_weight: float) -> np.ndarray:
    """A round's ``batch`` swaps of ``mask``: ``round(guide * batch)`` from ``guider`` (the untried
    ones it predicts best), the rest drawn at random."""
    guided = (guider.moves(mask, on, int(round(guide * batch)), width_weight) if guider is not None
              else mask[None][:0])
    return np.concatenate([guided, _swaps(mask, batch - len(guided), rng)]) if len(guided) < batch else guided


class _Guide:
    """Swaps proposed by the gradient of a smooth worst side lobe (module docstring, ``guide``).

    At a selection, the points within ``screen_db`` of the worst are imaged with the selection's
    weights as a differentiable input; each point's side lobes (its surface less its main lobe,
    found as :func:`~arraysel.objective.lobes.lobe_metrics` finds it) give the smooth maximum of
    their level over the peak in dB (temperature :data:`GUIDE_DB`), the points' smooth maximum
    (the same temperature) is differentiated, and a swap (``e`` out, ``f`` in) is predicted to change
    it by ``g_f - g_e``. The moves offered are the untried pairs of the ``top`` elements of each side
    with the lowest predicted change; the gradient is taken again only after the selection changes.
    """

    def __init__(self, objective, top: int = 24):
        self.obj = getattr(objective, "beams", objective)   # an Objective's per-beam view, else the view itself
        self.top = int(top)
        self.key, self.pairs, self.tried = None, None, set()
        xy = self.obj.setup.probe.element_positions()[:, :2]
        self.r2 = (xy ** 2).sum(1)

    def _gradient(self, mask: np.ndarray, on: list[int]) -> np.ndarray:
        import torch

        from arraysel.objective.lobes import main_lobe_regions

        obj = self.obj
        w = torch.as_tensor(mask, dtype=obj.dtype, device=obj.device)[None].requires_grad_(True)
        levels = []
        for i in on:
            ps = obj.imagers[i].image(w)
            (name, img), = ps.images.items()
            reg = main_lobe_regions({name: img.detach()}, ps.coords, target=obj.points[i])
            power = (img.abs() ** 2)[0].double()
            side = torch.ones_like(power, dtype=torch.bool)
            i0, i1, j0, j1 = reg.box[name]
            side[i0:i1, j0:j1] &= ~reg.main_box[name][0]
            r, c = (int(v) for v in reg.seed[name][0])
            db = 10 * torch.log10(power[side] / power[r, c] + 1e-30)
            levels.append(GUIDE_DB * torch.logsumexp(db / GUIDE_DB, 0))
        total = GUIDE_DB * torch.logsumexp(torch.stack(levels) / GUIDE_DB, 0)
        (g,) = torch.autograd.grad(total, w)
        return g[0].double().cpu().numpy()

    def moves(self, mask: np.ndarray, on: list[int], n: int, width_weight: float = 0.0) -> np.ndarray:
        """Up to ``n`` untried swaps of ``mask`` (n', Ne), the lowest predicted change first;
        ``width_weight`` > 0 (at the width cap) adds that many dB per unit of the main lobe's
        predicted relative widening (the aperture's mean square radius: a swap that moves an element
        inwards by ``d(r^2)`` widens it by about ``-d(r^2) / (2 sum r^2)``)."""
        key = mask.tobytes()
        if key != self.key:
            g = self._gradient(mask, on)
            ins, outs = np.flatnonzero(~mask), np.flatnonzero(mask)
            ins = ins[np.argsort(g[ins])[:self.top]]          # adding f changes the level by about g_f
            outs = outs[np.argsort(-g[outs])[:self.top]]      # removing e by about -g_e
            pred = g[ins][None, :] - g[outs][:, None]
            if width_weight > 0:
                r2 = self.r2
                wider = -(r2[ins][None, :] - r2[outs][:, None]) / (2 * r2[mask].sum())
                pred = pred + width_weight * np.maximum(wider, 0)
            order = np.argsort(pred, axis=None)
            self.pairs = [(int(outs[a]), int(ins[b])) for a, b in zip(*np.unravel_index(order, pred.shape))]
            self.key, self.tried = key, set()
        pick = [p for p in self.pairs if p not in self.tried][:n]
        self.tried.update(pick)
        out = np.repeat(mask[None], len(pick), axis=0)
        for row, (e, f) in enumerate(pick):
            out[row, e], out[row, f] = False, True
        return out


class _Scores:
    """The per-beam scores of a polish: the hard loss, the search's (soft) loss, the counters."""

    def __init__(self, objective, pts, cap, weight, soft):
        self.obj, self.pts, self.cap, self.weight, self.soft = objective, pts, cap, weight, soft
        self.scored = 0   # selection-points scored

    def full(self, masks, base=None):
        loss, summ = self.obj.beam_loss(masks, width_cap=self.cap, width_weight=self.weight, points=self.pts,
                                        base=base)
        self.scored += len(masks) * len(self.pts)
        return loss, self.search(summ["PSL_dB"], loss - summ["worst_PSL_dB"]), summ

    def search(self, psl: np.ndarray, penalty: np.ndarray) -> np.ndarray:
        if self.soft <= 0:
            return psl.max(1) + penalty
        top = psl.max(1, keepdims=True)
        return (top[:, 0] + self.soft * np.log(np.exp((psl - top) / self.soft).sum(1))) + penalty

    def screen(self, masks, on: list[int], base) -> np.ndarray:
        bm = self.obj.beam_metrics(masks, points=[self.pts[j] for j in on], base=base)
        self.scored += len(masks) * len(on)
        return bm["PSL_dB"].max(1)


def polish_on_beams(objective, mask, *, width_cap: float, seconds: float = 60.0, batch: int = 48, keep: int = 4,
                    patience: int = 20, width_weight: float = 100.0, seed: int = 0, points=None,
                    screen_db: float = 0.0, soft_db: float = 0.0, evaluations: int | None = None,
                    stop=None, guide: float = 0.0) -> dict:
    """Swap-move local search of ``mask`` (Ne,) bool on ``objective.beam_loss`` (module docstring).

    Parameters: ``width_cap`` (metres) and ``width_weight`` as :meth:`beam_loss`; ``seconds`` the
    time limit; ``batch`` moves drawn a round, ``keep`` of them scored on every point; ``patience``
    rounds without a gain before it stops; ``seed`` of the moves; ``points``: the loss over these
    points only (default all); ``screen_db`` [0, inf]: screen on the points within this many dB of
    the worst; ``soft_db`` [0, 10]: the smooth maximum's temperature (0: the worst point's side lobe);
    ``evaluations``: the most selection-points scored; ``stop``: a callable, True to stop;
    ``guide`` [0, 1]: the share of each batch proposed by the gradient (module docstring).

    Returns ``{"mask", "loss", "worst_PSL_dB", "mean_width_m", "start_loss", "rounds", "accepted",
    "evaluations" (selections scored on every point), "screened" (before that), "scored"
    (selection-points in all), "seconds", "trace" [(seconds, loss)]}``; ``loss`` is the per-beam loss.
    """
    m = np.asarray(mask, dtype=bool).reshape(-1)
    if m.shape[0] != objective.n_elements or not (0 < int(m.sum()) < m.shape[0]):
        raise ParameterError(f"mask must have {objective.n_elements} entries with at least one selected and one "
                             f"unselected element, got {m.shape[0]} entries, {int(m.sum())} selected")
    seconds = check_number("seconds", seconds, lo=0)
    batch = int(check_number("batch", batch, lo=1, hi=4096, integer=True))
    keep = int(check_number("keep", keep, lo=1, hi=batch, integer=True))
    patience = int(check_number("patience", patience, lo=1, integer=True))
    screen_db = check_number("screen_db", screen_db, lo=0)
    soft = check_number("soft_db", soft_db, lo=0, hi=10)
    guide = check_number("guide", guide, lo=0, hi=1)
    limit = None if evaluations is None else int(check_number("evaluations", evaluations, lo=1, integer=True))
    rng = np.random.default_rng(int(check_number("seed", seed, lo=0, integer=True)))
    t0 = time.perf_counter()
    pts = list(range(objective.n_points)) if points is None else [int(p) for p in points]
    sc = _Scores(objective, pts, width_cap, width_weight, soft)
    guider = _Guide(objective) if guide > 0 else None
    loss, cur, summ = sc.full(m[None])
    cur, psl, width = float(cur[0]), summ["PSL_dB"][0], float(summ["mean_width_m"][0])
    best = {"mask": m, "loss": float(loss[0]), "summary": {k: v[0] for k, v in summ.items()}}
    start, trace = best["loss"], [(0.0, best["loss"])]
    rounds, accepted, stale, screened, evals = 0, 0, 0, 0, 1

    def more() -> bool:  # a round that would end past the time limit is not started
        return (time.perf_counter() - t0 + last[0] < seconds and stale < patience and not (stop is not None and stop())
                and (limit is None or sc.scored + batch * len(pts) <= limit))

    last = [0.0]   # the latest round's seconds
    while more():
        t_round = time.perf_counter()
        rounds += 1
        on = [j for j in range(len(pts)) if psl[j] >= psl.max() - screen_db - 1e-9]
        cand = _proposals(m, batch, rng, guider, [pts[j] for j in on], guide,
                          width_weight if width >= 0.99 * width_cap else 0.0)
        if len(on) < len(pts):
            scr = sc.screen(cand, on, m)
            screened += batch
            top = np.argsort(scr)[:keep]
            top = top[scr[top] < psl.max() + 1e-9]
            if not len(top):
                stale += 1
                last[0] = time.perf_counter() - t_round
                continue
            cand = cand[top]
        c_loss, c_search, c_sum = sc.full(cand, m)
        evals += len(cand)
        j = int(np.argmin(c_search))
        if c_search[j] < cur - 1e-9:
            m, cur, psl, width = cand[j].copy(), float(c_search[j]), c_sum["PSL_dB"][j], float(c_sum["mean_width_m"][j])
            accepted, stale = accepted + 1, 0
            if c_loss[j] < best["loss"] - 1e-9:
                best = {"mask": m, "loss": float(c_loss[j]), "summary": {k: v[j] for k, v in c_sum.items()}}
                trace.append((time.perf_counter() - t0, best["loss"]))
        else:
            stale += 1
        last[0] = time.perf_counter() - t_round
    s = best["summary"]
    return {"mask": best["mask"], "loss": best["loss"], "worst_PSL_dB": float(s["worst_PSL_dB"]),
            "mean_width_m": float(s["mean_width_m"]), "start_loss": start, "rounds": rounds,
            "accepted": accepted, "evaluations": evals, "screened": screened, "scored": sc.scored,
            "seconds": time.perf_counter() - t0, "trace": trace}
