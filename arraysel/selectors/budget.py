"""The budget of a selector's run and the trace of its improvements.

A :class:`Budget` holds the limits of one run (seconds, objective evaluations, gradient steps),
measured on the objective's own counters from the moment it is started; a :class:`Recorder`
logs every improvement of the best ``k``-selection scored (the trace). The runner gives a
selector both through :class:`~arraysel.selectors.contract.BudgetedObjective`; the names are
importable from :mod:`arraysel.selectors.contract` too.
"""
from __future__ import annotations

import math
import sys
import time
from typing import TYPE_CHECKING, Iterable

import numpy as np

if TYPE_CHECKING:  # torch is imported where it is used: `arraysel list` and `report` start without it
    import torch

from arraysel.errors import ArrayselError, check_number
from arraysel.selection import mask_to_indices

__all__ = ["Budget", "Recorder"]


class Budget:
    """Limits of one selection run, measured on the objective's own counters.

    Parameters
    ----------
    seconds : wall-clock seconds (``None``: unlimited)
    evaluations : objective evaluations, i.e. masks scored by ``evaluate`` plus
        masks passed to ``mask_loss``/``selection_loss`` (``None``: unlimited)
    gradient_steps : calls of ``mask_loss``/``selection_loss`` with gradients
        (``None``: unlimited)

    A budget is *started* on an objective (:meth:`start`), which records the
    objective's counters and the time; the queries below are relative to that
    point. A budget that is queried before being started starts itself on the
    objective given to :meth:`start` later, so always start it first
    (the runner does).

    Example
    -------
    >>> b = Budget(evaluations=100)          # doctest: +SKIP
    >>> b.start(objective)
    >>> while not b.exhausted():
    ...     n = min(32, b.remaining_evaluations())
    """

    def __init__(self, seconds: float | None = None, evaluations: int | None = None,
                 gradient_steps: int | None = None):
        if seconds is not None:
            seconds = check_number("budget seconds", seconds, lo=0, lo_open=True)
        if evaluations is not None:
            evaluations = check_number("budget evaluations", evaluations, lo=1, integer=True)
        if gradient_steps is not None:
            gradient_steps = check_number("budget gradient_steps", gradient_steps, lo=1, integer=True)
        self.seconds = seconds
        self.evaluations = evaluations
        self.gradient_steps = gradient_steps
        self._objective = None
        self._t0 = 0.0
        self._e0 = 0
        self._g0 = 0

    def __repr__(self) -> str:
        return (f"Budget(seconds={self.seconds}, evaluations={self.evaluations}, "
                f"gradient_steps={self.gradient_steps})")

    def to_dict(self) -> dict:
        return {"seconds": self.seconds, "evaluations": self.evaluations,
                "gradient_steps": self.gradient_steps}

    def fresh(self) -> "Budget":
        """A new, unstarted budget with the same limits."""
        return Budget(self.seconds, self.evaluations, self.gradient_steps)

    @property
    def unlimited(self) -> bool:
        return self.seconds is None and self.evaluations is None and self.gradient_steps is None

    # -- state --------------------------------------------------------------
    def start(self, objective) -> "Budget":
        """Record the objective's counters and the time; return ``self``."""
        self._objective = objective
        self._t0 = time.perf_counter()
        self._e0 = int(objective.evaluations)
        self._g0 = int(objective.gradient_steps)
        return self

    def _need_started(self):
        if self._objective is None:
            raise ArrayselError("Budget queried before start(objective) was called")

    def elapsed(self) -> float:
        """Seconds since :meth:`start`."""
        self._need_started()
        return time.perf_counter() - self._t0

    def used_evaluations(self) -> int:
        self._need_started()
        return int(self._objective.evaluations) - self._e0

    def used_gradient_steps(self) -> int:
        self._need_started()
        return int(self._objective.gradient_steps) - self._g0

    def remaining_evaluations(self) -> int | float:
        """Evaluations left (``math.inf`` when unlimited; never negative)."""
        if self.evaluations is None:
            return math.inf
        return max(0, self.evaluations - self.used_evaluations())

    def remaining_seconds(self) -> float:
        if self.seconds is None:
            return math.inf
        return max(0.0, self.seconds - self.elapsed())

    def allowed(self, n: int) -> int:
        """How many of ``n`` evaluations may be spent now (0 when exhausted)."""
        if self.exhausted():
            return 0
        return int(min(n, self.remaining_evaluations()))

    def exhausted(self) -> bool:
        """True once any limit is reached."""
        self._need_started()
        if self.seconds is not None and self.elapsed() >= self.seconds:
            return True
        if self.evaluations is not None and self.used_evaluations() >= self.evaluations:
            return True
        if self.gradient_steps is not None and self.used_gradient_steps() >= self.gradient_steps:
            return True
        return False

    def fraction(self) -> float:
        """Largest used fraction over the set limits, in [0, 1] (0 when unlimited)."""
        self._need_started()
        parts = [0.0]
        if self.seconds is not None:
            parts.append(self.elapsed() / self.seconds)
        if self.evaluations is not None:
            parts.append(self.used_evaluations() / self.evaluations)
        if self.gradient_steps is not None:
            parts.append(self.used_gradient_steps() / self.gradient_steps)
        return float(min(1.0, max(parts)))


# ---------------------------------------------------------------------------
# trace recorder
# ---------------------------------------------------------------------------

class Recorder:
    """Logs every improvement of the best evaluated ``k``-selection.

    Each trace row holds ``seconds`` (since the budget started),
    ``evaluations`` and ``gradient_steps`` (used so far by this run),
    ``best_Mean`` and ``event`` (``"improvement"``, or ``"end"`` for the row
    :meth:`finish` adds at the run's last evaluation and time). ``best`` is the
    best selection reported so far (sorted list) or ``None``; selectors may
    return it directly. ``first`` is the first selection reported, finite or not.
    """

    def __init__(self, objective, budget: Budget):
        self.objective = objective
        self.budget = budget
        self.rows: list[dict] = []
        self.best: list[int] | None = None
        self.best_mean: float = math.inf
        self.first: list[int] | None = None
        self.reports = 0

    def _indices(self, elements) -> list[int]:
        if _looks_like_mask(elements, self.objective.n_elements):
            return mask_to_indices(elements, self.objective.n_elements)
        return sorted(int(i) for i in elements)

    def report(self, elements: Iterable[int] | np.ndarray | torch.Tensor, mean: float, *,
               evaluations: int | None = None) -> bool:
        """Report an evaluated selection and its ``Mean``; return True if it improved.

        ``elements`` is a list of indices or a boolean mask of length ``Ne``.
        NaN/Inf values are ignored (never an improvement). ``evaluations``: the
        run's evaluation count at which this selection was scored (default: the
        count used so far).
        """
        self.reports += 1
        mean = float(mean)
        if self.first is None:
            self.first = self._indices(elements)
        if not math.isfinite(mean) or mean >= self.best_mean:
            return False
        self.best = self._indices(elements)
        self.best_mean = mean
        used = self.budget.used_evaluations()
        self.rows.append({
            "seconds": self.budget.elapsed(),
            "evaluations": used if evaluations is None else min(int(evaluations), used),
            "gradient_steps": self.budget.used_gradient_steps(),
            "best_Mean": mean,
            "event": "improvement",
        })
        return True

    def report_batch(self, selections: np.ndarray, means: np.ndarray) -> bool:
        """Report a batch (``(B, k)`` indices or ``(B, Ne)`` masks) at once; only its best counts."""
        means = np.asarray(means, dtype=np.float64)
        if means.size == 0:
            return False
        finite = np.where(np.isfinite(means), means, np.inf)
        i = int(np.argmin(finite))
        if not math.isfinite(finite[i]):
            self.reports += 1
            if self.first is None:
                self.first = self._indices(selections[0])
            return False
        return self.report(selections[i], finite[i])

    def finish(self) -> None:
        """Add the ``end`` row: the best Mean so far at the run's last evaluation and time
        (nothing when no finite Mean was reported)."""
        if not math.isfinite(self.best_mean):
            return
        self.rows.append({
            "seconds": self.budget.elapsed(),
            "evaluations": self.budget.used_evaluations(),
            "gradient_steps": self.budget.used_gradient_steps(),
            "best_Mean": self.best_mean,
            "event": "end",
        })



def _is_tensor(x) -> bool:
    """``x`` is a torch tensor (False without looking when torch was never imported: none can exist)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def _looks_like_mask(elements, n_elements) -> bool:
    if _is_tensor(elements):
        elements = elements.detach().cpu().numpy()
    if isinstance(elements, np.ndarray):
        return elements.dtype == bool or (elements.ndim == 1 and elements.shape[0] == n_elements
                                          and elements.dtype.kind == "f")
    return False

