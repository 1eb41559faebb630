"""``nlopt``: NLopt on the continuous relaxation ``w in [0, 1]^Ne``.

* ``MMA`` / ``SLSQP`` (gradient-based): minimise ``objective.mask_loss(w)``
  with its torch-autograd gradient under ``sum(w) = k`` (SLSQP: an equality
  constraint; MMA, which takes only inequalities and stalls on the pair
  ``sum(w) <= k``, ``sum(w) >= k``: ``sum(w) <= k``, active at the optimum
  because every loss prefers more active aperture).
* ``CRS2`` / ``ISRES`` / ``DIRECT`` (derivative-free, global): minimise
  ``mask_loss(project(w))`` where ``project`` is the Euclidean projection onto
  ``{0 <= w <= 1, sum(w) = k}``.

Each point NLopt asks for is rounded to its ``k`` largest weights; new
rounded selections are scored with ``objective.evaluate`` and the best one is
returned. The first run starts from ``k / Ne`` (jittered); a local optimiser
converges long before a usual budget ends, so up to ``restarts`` further runs
start from random points of ``{0 <= w <= 1, sum(w) = k}`` while the budget
lasts. NLopt's stochastic algorithms draw from NLopt's own generator, seeded
with ``nlopt.srand(seed)`` at the start of the selector's run; the start
points come from the run's seed, so a run is reproducible.
``nlopt`` is imported only when this selector runs.
"""
from __future__ import annotations

import math

import numpy as np

from arraysel.constraints import group_constraints, refuse_groups
from arraysel.errors import NumericalError
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.contract import Option, Selector, indices_to_mask, numpy_rng, top_k as _top_k

_GRADIENT = ("MMA", "SLSQP")
_ALGORITHMS = {"MMA": "LD_MMA", "SLSQP": "LD_SLSQP", "CRS2": "GN_CRS2_LM", "ISRES": "GN_ISRES",
               "DIRECT": "GN_DIRECT_L"}


class NLoptSelector(Selector):
    name = "nlopt"
    description = "NLopt on soft weights w in [0,1]^Ne (MMA/SLSQP with sum(w)=k, or CRS2/ISRES/DIRECT), top-k rounding"
    options = {
        "algorithm": Option(str, "MMA", "NLopt algorithm", choices=tuple(_ALGORITHMS)),
        "maxeval": Option(int, 5000, "most objective calls made by NLopt (the budget may stop earlier)", lo=1),
        "xtol_rel": Option(float, 1e-6, "NLopt relative tolerance on w", lo=0.0),
        "init_jitter": Option(float, 0.05, "random perturbation of the start point k/Ne", lo=0.0, hi=1.0),
        "restarts": Option(int, 1000, "further runs from random start points while the budget lasts "
                           "(only under a time or evaluation budget; 0: one run from k/Ne)", lo=0),
    }
    uses_gradients = True
    deterministic = False

    def select(self, objective, k, seed):
        gc = group_constraints(objective)
        if gc is not None and gc.group_mode != "exactly-one":
            refuse_groups(objective, self.name)
        import nlopt
        import torch  # here, not at the top: `arraysel list` loads the plugin without torch

        project_capped_simplex, top_k = _grouped(gc)

        budget = objective.budget
        n = int(objective.n_elements)
        alg = self.options["algorithm"]
        gradient = alg in _GRADIENT
        device, dtype = objective.device, objective.dtype
        scored: set[tuple] = set()
        state: dict = {"last": None}

        def score(idx):
            key = tuple(idx)
            if key in scored or objective.remaining() < 1:
                return
            scored.add(key)
            objective.evaluate(indices_to_mask(key, n)[None, :])

        def f(x, grad):
            if objective.remaining() < 2:
                raise nlopt.ForcedStop()
            w = torch.tensor(np.asarray(x), dtype=dtype, device=device, requires_grad=gradient)
            w_eff = w if gradient else project_capped_simplex(w, float(k))
            try:
                total, _ = objective.mask_loss(w_eff[None, :])
            except NumericalError:
                if grad.size > 0:
                    grad[:] = 0.0
                return 1e30
            value = float(total[0].detach())
            if gradient and grad.size > 0:
                g = torch.autograd.grad(total[0], w)[0] if w.requires_grad and total.requires_grad else None
                grad[:] = 0.0 if g is None else np.nan_to_num(g.detach().double().cpu().numpy(),
                                                              nan=0.0, posinf=0.0, neginf=0.0)
            idx = top_k(w_eff.detach(), k)
            state["last"] = idx
            score(idx)
            return value if math.isfinite(value) else 1e30

        def run_once(x0):
            opt = nlopt.opt(getattr(nlopt, _ALGORITHMS[alg]), n)
            opt.set_lower_bounds(np.zeros(n))
            opt.set_upper_bounds(np.ones(n))
            opt.set_min_objective(f)
            opt.set_maxeval(self.options["maxeval"])
            if self.options["xtol_rel"] > 0:
                opt.set_xtol_rel(self.options["xtol_rel"])
            if budget.seconds is not None:
                opt.set_maxtime(max(1e-3, budget.remaining_seconds()))
            if gradient:
                _constrain_sums(opt, alg, k, gc)
            try:
                opt.optimize(x0)
            except (nlopt.ForcedStop, nlopt.RoundoffLimited):
                pass  # budget reached, or no further progress possible: keep the best so far

        nlopt.srand(int(seed))
        rng = numpy_rng(seed)
        x0 = k / n + self.options["init_jitter"] * rng.uniform(-1.0, 1.0, n)
        x0 = project_capped_simplex(torch.tensor(x0, dtype=torch.float64), float(k)).numpy()
        first = x0
        limited = any(v is not None for v in (budget.seconds, budget.evaluations, budget.gradient_steps))
        for run in range(1 + (self.options["restarts"] if limited else 0)):
            if run and objective.remaining() < 2:  # the same test as in f(); 0 once any limit is reached
                break
            if run:  # a random point of the capped simplex
                x0 = project_capped_simplex(torch.tensor(rng.uniform(0.0, 2.0 * k / n, n)), float(k)).numpy()
            run_once(x0)
        if objective.best is not None:
            return objective.best
        return state["last"] if state["last"] is not None else top_k(first, k)


def _grouped(gc):
    """``(project, round)`` of soft weights: onto ``{0 <= w <= 1, sum(w) = k}`` and to the ``k``
    largest, or with exactly-one channel groups ``gc`` (counts included) onto each group's count
    and to the feasible selection the weights prefer."""
    from arraysel.selectors.relax import project_groups

    def project(w, k):
        return project_groups(w, k) if gc is None else project_groups(w, k, gc.unit_groups, gc.unit_group_counts)

    def round_(w, k):
        if gc is None:
            return _top_k(w, k)
        return [int(i) for i in np.flatnonzero(gc.select_units(np.asarray(w, dtype=np.float64)[None])[0])]

    return project, round_


def _constrain_sums(opt, alg: str, k: int, gc) -> None:
    """:func:`_constrain_sum` of all the weights to ``k``, or of each channel group's to its count."""
    if gc is None:
        return _constrain_sum(opt, alg, k)
    g, counts = gc.unit_groups, gc.unit_group_counts
    for grp in np.unique(g):
        _constrain_sum(opt, alg, 1 if counts is None else int(counts[grp]), np.flatnonzero(g == grp))


def _constrain_sum(opt, alg: str, k: int, idx=None) -> None:
    """Constrain ``sum(w)`` (over the elements ``idx``, default all) to ``k``: an equality for SLSQP;
    for MMA, which takes inequalities only and whose dual solver stalls on the pair ``sum(w) <= k``,
    ``sum(w) >= k``, the inequality ``sum(w) <= k`` (the losses prefer more active weight, so it is
    active at the optimum)."""
    tol = 1e-6 * max(1, k)
    sel = slice(None) if idx is None else idx

    def over(x, grad):
        if grad.size > 0:
            grad[:] = 0.0
            grad[sel] = 1.0
        return float(np.sum(np.asarray(x)[sel]) - k)

    if alg == "SLSQP":
        opt.add_equality_constraint(over, tol)
    else:
        opt.add_inequality_constraint(over, tol)


@hookimpl
def arraysel_register_selectors(register):
    register(NLoptSelector)
