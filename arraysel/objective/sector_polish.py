"""Polish a selection of a sector scene on its per-beam loss (``docs/sector.md``).

The search of a sector scene runs on the two-way beam pattern, which ranks selections only
roughly as their points' PSFs do (``benchmarks/results/sector-ranking``). With the sector fast
path (:meth:`~arraysel.objective.sector_objective.SectorObjective.point_images`) the per-beam
loss (:meth:`~arraysel.objective.sector_objective.SectorObjective.beam_loss`: the worst side lobe
over the points, plus a penalty on the mean -6 dB width past a cap) costs a fraction of a second a
selection, so a local search can run on it directly.

:func:`polish_on_beams` is that search: swap moves (one selected element out, one unselected in),
drawn at random in batches. Since the loss is the worst point's side lobe, each batch is first
screened on the point that sets it (one point's images, a sixth of the cost on the built-in
scene); the best screened moves are then scored on every point, and the best of them is taken
when it lowers the loss. The search stops at its time limit or after ``patience`` batches without
a gain.
"""
from __future__ import annotations

import time

import numpy as np

from arraysel.errors import ParameterError, check_number

__all__ = ["polish_on_beams"]


def _swaps(mask: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    on, off = np.flatnonzero(mask), np.flatnonzero(~mask)
    out = np.repeat(mask[None], n, axis=0)
    rows = np.arange(n)
    out[rows, rng.choice(on, n)] = False
    out[rows, rng.choice(off, n)] = True
    return out


def polish_on_beams(objective, mask, *, width_cap: float, seconds: float = 60.0, batch: int = 48, keep: int = 4,
                    patience: int = 20, width_weight: float = 100.0, seed: int = 0, points=None) -> dict:
    """Swap-move local search of ``mask`` (Ne,) bool on ``objective.beam_loss`` (module docstring).

    Parameters: ``width_cap`` (metres) and ``width_weight`` as :meth:`beam_loss`; ``seconds`` the
    time limit; ``batch`` moves drawn a round, ``keep`` of them scored on every point; ``patience``
    rounds without a gain before it stops; ``seed`` of the moves; ``points``: the loss over these
    points only (default all).

    Returns ``{"mask", "loss", "worst_PSL_dB", "mean_width_m", "start_loss", "rounds", "accepted",
    "evaluations" (selections scored on every point), "screened" (on one point), "seconds",
    "trace" [(seconds, loss)]}``.
    """
    m = np.asarray(mask, dtype=bool).reshape(-1)
    if m.shape[0] != objective.n_elements or not (0 < int(m.sum()) < m.shape[0]):
        raise ParameterError(f"mask must have {objective.n_elements} entries with at least one selected and one "
                             f"unselected element, got {m.shape[0]} entries, {int(m.sum())} selected")
    seconds = check_number("seconds", seconds, lo=0)
    batch = int(check_number("batch", batch, lo=1, hi=4096, integer=True))
    keep = int(check_number("keep", keep, lo=1, hi=batch, integer=True))
    patience = int(check_number("patience", patience, lo=1, integer=True))
    rng = np.random.default_rng(int(check_number("seed", seed, lo=0, integer=True)))
    t0 = time.perf_counter()
    pts = list(range(objective.n_points)) if points is None else [int(p) for p in points]
    loss, summ = objective.beam_loss(m[None], width_cap=width_cap, width_weight=width_weight, points=pts)
    best = float(loss[0])
    psl = summ["PSL_dB"][0]
    start, trace = best, [(0.0, best)]
    rounds = accepted = stale = screened = 0
    evaluations = 1
    while time.perf_counter() - t0 < seconds and stale < patience:
        rounds += 1
        cand = _swaps(m, batch, rng)
        worst = int(np.argmax(psl))
        scr = objective.beam_metrics(cand, points=[pts[worst]])["PSL_dB"][:, 0]
        screened += batch
        top = np.argsort(scr)[:keep]
        top = top[scr[top] < psl[worst] + 1e-9]
        if not len(top):
            stale += 1
            continue
        c_loss, c_sum = objective.beam_loss(cand[top], width_cap=width_cap, width_weight=width_weight, points=pts)
        evaluations += len(top)
        j = int(np.argmin(c_loss))
        if c_loss[j] < best - 1e-9:
            m, best, summ = cand[top[j]].copy(), float(c_loss[j]), {k: v[j:j + 1] for k, v in c_sum.items()}
            psl = summ["PSL_dB"][0]
            accepted += 1
            stale = 0
            trace.append((time.perf_counter() - t0, best))
        else:
            stale += 1
    return {"mask": m, "loss": best, "worst_PSL_dB": float(summ["worst_PSL_dB"][0]),
            "mean_width_m": float(summ["mean_width_m"][0]), "start_loss": start, "rounds": rounds,
            "accepted": accepted, "evaluations": evaluations, "screened": screened,
            "seconds": time.perf_counter() - t0, "trace": trace}
