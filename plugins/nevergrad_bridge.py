"""``nevergrad``: run any nevergrad optimizer on the selection problem (exact-k encodings).

Written as a third-party plugin would be: it uses only arraysel's public API
(``Selector``, ``Option``, ``hookimpl``, ``numpy_rng``, ``top_k``; the runner ends
it when the budget is spent) and imports nevergrad only when it runs
(``pip install arraysel[nevergrad]``).

Encodings (option ``encoding``), both exactly ``k`` elements for every point:

* ``keys`` (random keys): an ``Array`` of ``Ne`` reals in ``[0, 1]``; the
  selection is the ``k`` largest keys (ties to the lower index). Any
  continuous or discrete optimizer works on it (NGOpt, CMA, DE,
  DiscreteOnePlusOne, ...);
* ``binary``: ``Ne`` choices in ``{0, 1}`` (``Choice([0, 1], repetitions=Ne)``),
  repaired to ``k`` elements: surplus active elements are dropped, missing
  ones added, at random (from the run's generator, so the run stays
  reproducible). Option ``repair``:

  - ``lamarck`` (default): the optimizer is told the *repaired* point with its
    Mean (nevergrad's "tell not asked"), so its state holds only exact-k
    selections and a one-bit mutation of one becomes a random swap; for
    optimizers that cannot be told points they did not ask, the asked point
    is told instead;
  - ``random``: the asked point is told the Mean of its repaired selection
    (the same point may then score differently on another ask).

The optimizer is ``nevergrad.optimizers.registry[optimizer]`` built with
``num_workers = batch`` (1 for optimizers that cannot run in parallel); each
step asks ``num_workers`` points, scores them in one ``objective.evaluate``
call and tells the Means (NaN/Inf told as a large finite loss). nevergrad's own
budget is ``ng_budget`` (default: the run's evaluation limit, else 20000);
when it is used up before arraysel's budget a new optimizer starts (fresh
random stream). nevergrad's (and pycma's) warnings are silenced inside the run.
nevergrad's diagonal CMA, NGOpt's choice for a few hundred dimensions and
more, loses its mean-shift samples under parallel asks (nevergrad issue 1690:
"Mean shift samples are expected but missing"); the run then starts a fresh
optimizer, as at the end of its nevergrad budget, and says so in the log.
"""
from __future__ import annotations

import logging
import warnings

import numpy as np

from arraysel.constraints import group_constraints
from arraysel.errors import ParameterError
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.contract import Option, Selector, numpy_rng, top_k

_DEFAULT_NG_BUDGET = 20_000
#: the message of pycma's step-size adaptation when nevergrad's diagonal CMA loses its samples
_CMA_TPA = "Mean shift samples are expected but missing"

_log = logging.getLogger("arraysel")


def _nevergrad():
    try:
        import nevergrad as ng
    except ImportError as exc:
        raise ParameterError("the nevergrad selector needs the nevergrad package: "
                             "pip install 'arraysel[nevergrad]'") from exc
    return ng


def _tell_repaired(ng, opt, asked, mask: np.ndarray, loss: float) -> bool:
    """Tell ``opt`` the repaired selection ``mask`` (a point it did not ask) with
    ``loss``; an optimizer that refuses such points is told ``asked`` instead.
    Returns whether repaired points may be told from now on."""
    try:
        opt.tell(opt.parametrization.spawn_child(new_value=tuple(int(b) for b in mask)), loss)
        return True
    except ng.errors.TellNotAskedNotSupportedError:
        opt.tell(asked, loss)
        return False


class NevergradSelector(Selector):
    name = "nevergrad"
    description = "any nevergrad optimizer (NGOpt, DiscreteOnePlusOne, ...) with an exact-k encoding"
    options = {
        "optimizer": Option(str, "NGOpt", "name in nevergrad.optimizers.registry, e.g. NGOpt, "
                            "DiscreteOnePlusOne, PortfolioDiscreteOnePlusOne, CMA, TwoPointsDE"),
        "encoding": Option(str, "keys", "keys: top-k of Ne random keys; binary: Ne bits repaired to k",
                           choices=("keys", "binary")),
        "repair": Option(str, "lamarck", "binary encoding: random drops/adds to k, then tell the "
                         "repaired point (lamarck) or the asked one (random)", choices=("lamarck", "random")),
        "batch": Option(int, 32, "points asked per step (nevergrad num_workers), scored in one call", lo=1),
        "ng_budget": Option(int, None, "budget told to nevergrad (auto: the run's evaluation limit, "
                            f"else {_DEFAULT_NG_BUDGET})", lo=1),
    }
    deterministic = False
    requires = ("nevergrad",)
    extra = "nevergrad"

    def __init__(self, **options):
        super().__init__(**options)
        try:
            import nevergrad as ng
        except ImportError:
            return  # checked again, with the install hint, when the selector runs
        if self.options["optimizer"] not in ng.optimizers.registry:
            close = sorted(n for n in ng.optimizers.registry
                           if n.lower().startswith(self.options["optimizer"][:3].lower()))[:8]
            raise ParameterError(f"option nevergrad.optimizer = {self.options['optimizer']!r} is not a "
                                 f"nevergrad optimizer; e.g. NGOpt, DiscreteOnePlusOne, "
                                 f"PortfolioDiscreteOnePlusOne, CMA{'; similar: ' + ', '.join(close) if close else ''}")

    def _make(self, ng, n: int, budget: int, rng: np.random.Generator):
        if self.options["encoding"] == "keys":
            param = ng.p.Array(shape=(n,), lower=0.0, upper=1.0)
        else:
            param = ng.p.Choice([0, 1], repetitions=n)
        param.random_state = np.random.RandomState(int(rng.integers(2**31 - 1)))
        opt = ng.optimizers.registry[self.options["optimizer"]](parametrization=param, budget=budget,
                                                                 num_workers=self.options["batch"])
        if getattr(opt, "no_parallelization", False):
            opt = ng.optimizers.registry[self.options["optimizer"]](parametrization=param, budget=budget,
                                                                     num_workers=1)
        return opt

    def _decode(self, value, n: int, k: int, rng: np.random.Generator, gc=None) -> np.ndarray:
        if gc is not None:  # channel groups: the feasible selection the keys (or bits) prefer
            v = np.asarray(value, dtype=np.float64)
            return gc.select_units((v if self.options["encoding"] == "keys" else v + 0.5 * rng.random(n))[None])[0]
        mask = np.zeros(n, dtype=bool)
        if self.options["encoding"] == "keys":
            mask[top_k(np.asarray(value, dtype=np.float64), k)] = True
            return mask
        mask[np.asarray(value, dtype=np.int64) > 0] = True
        on, off = np.flatnonzero(mask), np.flatnonzero(~mask)
        if on.size > k:
            mask[rng.choice(on, on.size - k, replace=False)] = False
        elif on.size < k:
            mask[rng.choice(off, k - on.size, replace=False)] = True
        return mask

    def select(self, objective, k, seed):
        gc = group_constraints(objective)
        ng = _nevergrad()
        n = int(objective.n_elements)
        rng = numpy_rng(seed)
        repair = numpy_rng(seed, stream=1)
        lamarck = self.options["encoding"] == "binary" and self.options["repair"] == "lamarck"
        limit = objective.budget.evaluations
        ng_budget = self.options["ng_budget"] or (int(limit) if limit is not None else _DEFAULT_NG_BUDGET)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ng.errors.NevergradWarning)
            warnings.simplefilter("ignore", RuntimeWarning)
            warnings.filterwarnings("ignore", module="cma")
            while True:  # one optimizer per nevergrad budget
                opt = self._make(ng, n, ng_budget, rng)
                told = 0
                try:
                    while opt.num_ask < ng_budget:
                        lamarck = self._step(ng, opt, objective, n, k, ng_budget, repair, gc, lamarck)
                        told += 1
                except RuntimeError as exc:
                    # nevergrad's diagonal CMA (NGOpt's choice for a few hundred dimensions or more)
                    # loses its mean-shift samples under parallel asks (nevergrad issue 1690):
                    # start a fresh optimizer; the best selection so far is kept by the budget
                    if _CMA_TPA not in str(exc) or not told:
                        raise
                    _log.info("nevergrad: %s lost its state after %d steps (nevergrad issue 1690); "
                              "starting a fresh one", type(opt).__name__, told)

    def _step(self, ng, opt, objective, n: int, k: int, ng_budget: int, repair, gc, lamarck: bool) -> bool:
        """Ask ``num_workers`` points, score them in one call, tell their losses; returns whether
        the optimizer still takes repaired points (``lamarck``)."""
        todo = min(opt.num_workers, ng_budget - opt.num_ask)
        cands = [opt.ask() for _ in range(todo)]
        masks = np.stack([self._decode(c.value, n, k, repair, gc) for c in cands])
        values = objective.score(masks)
        worst = np.max(values[np.isfinite(values)], initial=1.0)
        for c, m, v in zip(cands, masks, values):
            loss = float(v) if np.isfinite(v) else float(10.0 * abs(worst) + 1e6)
            if lamarck and not np.array_equal(np.asarray(c.value) > 0, m):
                lamarck = _tell_repaired(ng, opt, c, m, loss)
            else:
                opt.tell(c, loss)
        return lamarck


@hookimpl
def arraysel_register_selectors(register):
    register(NevergradSelector)
