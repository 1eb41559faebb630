"""The budget of a selector's run and the trace of its improvements.

A :class:`Budget` holds the limits of one run (seconds, objective evaluations, gradient steps),
measured on the objective's own counters from the moment it is started; a :class:`Recorder`
logs every improvement of the best ``k``-selection scored (the trace). :class:`BudgetGate` is the
one small interface through which a run spends its budget: :meth:`BudgetGate.masks` scores masks
in the pieces the budget allows and records them, :meth:`BudgetGate.losses` admits loss
evaluations (a gradient, a Hessian, soft weights), :meth:`BudgetGate.enter` refuses a run that has
ended. The runner gives a selector all of them through
:class:`~arraysel.selectors.contract.BudgetedObjective`, whose every charged method and capability
(:mod:`arraysel.selectors.capabilities`) goes through the gate; the names are importable from
:mod:`arraysel.selectors.contract` too.
"""
from __future__ import annotations

import math
import sys
import time
from typing import Callable
from typing import TYPE_CHECKING, Iterable

import numpy as np

if TYPE_CHECKING:  # torch is imported where it is used: `arraysel list` and `report` start without it
    import torch

from arraysel.errors import ArrayselError, check_number
from arraysel.selection import mask_to_indices

__all__ = ["Budget", "Recorder", "BudgetGate", "BudgetExhausted", "BudgetExceededError"]


class BudgetExceededError(ArrayselError, RuntimeError):
    """A selector used more objective evaluations than its budget allowed."""


class BudgetExhausted(ArrayselError):
    """Raised by :class:`~arraysel.selectors.contract.BudgetedObjective` when the run's budget is
    used up.

    It ends the selector's search: the runner catches it and takes the best
    ``k``-selection scored so far (``objective.best``). A selector may catch it
    itself to return something else, but must not call the objective again.
    """


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


# ---------------------------------------------------------------------------
# the gate a run's budget is spent through
# ---------------------------------------------------------------------------

class BudgetGate:
    """The one interface through which a run spends its budget (module docstring).

    Parameters: ``budget`` (started), ``recorder`` (its trace), ``k`` (only masks of ``k`` active
    elements, meeting ``constraints`` when given, are recorded), ``piece`` (the most masks scored
    in one call of the objective).

    * :meth:`masks` scores ``total`` masks in pieces: at most ``piece`` masks, and under a time
      limit no more than the time left allows at the measured cost per mask; the budget is
      checked before each piece, so a time limit stops a large batch early. When the budget does
      not allow them all, the allowed first masks are scored and recorded, then
      :class:`BudgetExhausted` is raised: a call either returns every score asked for or ends the
      search;
    * :meth:`losses` raises :class:`BudgetExhausted` unless the budget allows ``n`` evaluations
      now (they are counted by the objective itself);
    * :meth:`enter` raises :class:`~arraysel.errors.ArrayselError` once :meth:`close` was called
      (a thread the selector left running cannot score, count or record anything for the runs
      that follow) and notes the time of the run's first call (:attr:`first_call_s`).
    """

    def __init__(self, budget: Budget, recorder: Recorder, k: int, piece: int, constraints=None):
        self.budget = budget
        self.recorder = recorder
        self.k = int(k)
        self.piece = max(1, int(piece))
        self.constraints = constraints
        #: seconds into the budget at which the run first called the objective; None before that
        self.first_call_s: float | None = None
        self.closed = False
        self._per_mask = 0.0  # running estimate of the seconds one mask costs

    def close(self) -> None:
        """End the run: every later :meth:`enter` raises."""
        self.closed = True

    def check_open(self) -> None:
        """Raise once the run has ended (:meth:`close`)."""
        if self.closed:
            raise ArrayselError("this run has ended: its objective can no longer be used (a thread the "
                                "selector started is still calling it; stop such threads before select "
                                "returns)")

    def enter(self) -> None:
        """:meth:`check_open`, and note the time of the run's first call."""
        self.check_open()
        if self.first_call_s is None:
            self.first_call_s = float(self.budget.elapsed())

    def exhausted(self, what: str) -> BudgetExhausted:
        """The :class:`BudgetExhausted` that ends the search, saying ``what`` was asked."""
        return BudgetExhausted(f"the run's budget ({self.budget!r}) is used up ({what})")

    def losses(self, n: int, what: str) -> None:
        """Admit ``n`` loss evaluations (``what``: for the message), or raise :class:`BudgetExhausted`."""
        if self.budget.allowed(n) < n:
            raise self.exhausted(f"{what}")

    def masks(self, total: int, call: Callable, masks_of: Callable, piece: int | None = None) -> dict[str, np.ndarray]:
        """Score ``total`` masks by ``call(slice) -> {name: (n,)}`` in the pieces the budget allows
        (of ``piece`` masks at most, default :attr:`piece`), recording the masks ``masks_of(slice)``
        (bool ``(n, Ne)``) with their ``Mean``; the scores of all of them, or
        :class:`BudgetExhausted` after the allowed first ones."""
        parts: list[dict] = []
        done = 0
        piece = self.piece if piece is None else int(piece)
        while done < total:
            want = min(piece, total - done)
            if self.budget.seconds is not None and self._per_mask > 0:
                # under a time limit, a piece must fit in the time left (at least one mask)
                want = max(1, min(want, int(self.budget.remaining_seconds() / self._per_mask)))
            allowed = self.budget.allowed(want)
            if allowed <= 0:
                raise self.exhausted(f"{done} of {total} masks of this call scored")
            before = self.budget.used_evaluations()
            t0 = time.perf_counter()
            sl = slice(done, done + allowed)
            out = call(sl)
            per_mask = (time.perf_counter() - t0) / allowed
            self._per_mask = per_mask if self._per_mask == 0 else 0.7 * self._per_mask + 0.3 * per_mask
            self._record(masks_of(sl), np.asarray(out["Mean"], dtype=np.float64), before)
            parts.append(out)
            done += allowed
            if allowed < want:
                raise self.exhausted(f"{done} of {total} masks of this call scored")
        if len(parts) == 1:
            return parts[0]
        return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}

    def _record(self, masks: np.ndarray, means: np.ndarray, before: int) -> None:
        ok = masks.sum(axis=1) == self.k
        if self.constraints is not None:
            ok &= self.constraints.feasible_rows(masks)
        if not ok.any():
            return
        finite = np.where(ok & np.isfinite(means), means, np.inf)
        i = int(np.argmin(finite))
        if self.recorder.first is None:
            self.recorder.first = mask_to_indices(masks[int(np.flatnonzero(ok)[0])])
        if math.isfinite(finite[i]) and finite[i] < self.recorder.best_mean:
            self.recorder.report(masks[i], float(finite[i]), evaluations=before + i + 1)
        else:
            self.recorder.reports += 1
