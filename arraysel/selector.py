"""The selector contract: :class:`Selector`, its declared :class:`Option` s, the
:class:`Budget` it must respect and the :class:`Recorder` that logs its trace.

A selector chooses which ``k`` of the objective's ``Ne`` elements stay active.
It is built from validated options (``SelectorClass(**options)``) and run by

    ``selector.select(objective, k, budget, seed, recorder) -> list[int]``

where

* ``objective`` follows the Objective contract (``evaluate``, ``mask_loss``,
  ``selection_loss`` and the counters ``evaluations``, ``gradient_steps``,
  ``seconds``), see ``docs/selectors.md``;
* ``budget`` is a started :class:`Budget`: ask ``budget.exhausted()`` and
  ``budget.remaining_evaluations()`` before spending, never exceed it by more
  than one batch (:meth:`Selector.batch_size`);
* ``seed`` is an ``int``; build generators from it with :func:`numpy_rng` and
  :func:`torch_rng` (never use global random state);
* ``recorder`` is a :class:`Recorder`; call ``recorder.report(elements, mean)``
  each time a hard selection of ``k`` elements has been evaluated.

The returned list must hold exactly ``k`` distinct ints in ``[0, Ne)``.
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, ClassVar, Iterable, Sequence

import numpy as np
import torch

from .errors import ArrayselError, ParameterError, SelectionError, check_choice, check_number

__all__ = [
    "Option", "Selector", "Budget", "Recorder", "BudgetExceededError",
    "numpy_rng", "torch_rng", "check_selection", "indices_to_mask", "mask_to_indices",
    "top_k", "finite_or_inf",
]


class BudgetExceededError(ArrayselError, RuntimeError):
    """A selector used more objective evaluations than its budget allowed."""


# ---------------------------------------------------------------------------
# declared options
# ---------------------------------------------------------------------------

_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


@dataclasses.dataclass(frozen=True)
class Option:
    """One declared option of a selector.

    Parameters
    ----------
    type : one of ``int``, ``float``, ``str``, ``bool``
    default : the value used when the option is not given (``None`` allowed:
        it then means "automatic", and the selector documents what it does)
    help : one line shown by ``arraysel list -v`` and in the docs
    choices : allowed values (for ``str`` options)
    lo, hi : inclusive bounds for numbers (``None``: unbounded)
    """

    type: type
    default: Any
    help: str
    choices: tuple | None = None
    lo: float | None = None
    hi: float | None = None

    def parse(self, name: str, text: str) -> Any:
        """Convert the string of ``-o key=value`` and validate it."""
        text = text.strip()
        if text.lower() in ("none", "auto") and self.default is None:
            return None
        try:
            if self.type is bool:
                low = text.lower()
                if low in _TRUE:
                    value: Any = True
                elif low in _FALSE:
                    value = False
                else:
                    raise ValueError(text)
            elif self.type is int:
                value = int(float(text)) if float(text).is_integer() else int(text)
            elif self.type is float:
                value = float(text)
            else:
                value = text
        except ValueError:
            raise ParameterError(f"option {name} = {text!r} is not a valid {self.type.__name__}") from None
        return self.validate(name, value)

    def validate(self, name: str, value: Any) -> Any:
        """Return ``value`` converted to the option's type, or raise :class:`ParameterError`."""
        if value is None:
            if self.default is None:
                return None
            raise ParameterError(f"option {name} must not be None")
        if self.type is bool:
            if not isinstance(value, (bool, np.bool_)):
                raise ParameterError(f"option {name} must be true or false, got {value!r}")
            return bool(value)
        if self.type in (int, float):
            value = check_number(f"option {name}", value, lo=self.lo, hi=self.hi,
                                 integer=self.type is int)
            return self.type(value)
        if not isinstance(value, str):
            raise ParameterError(f"option {name} must be a string, got {value!r}")
        if self.choices is not None:
            check_choice(f"option {name}", value, self.choices)
        return value

    def describe(self) -> str:
        """Short text: type, default, choices/range and help."""
        extra = ""
        if self.choices:
            extra = f", one of {'|'.join(map(str, self.choices))}"
        elif self.lo is not None or self.hi is not None:
            extra = f", in [{'-inf' if self.lo is None else self.lo}, {'inf' if self.hi is None else self.hi}]"
        default = "auto" if self.default is None else self.default
        return f"{self.type.__name__}, default {default}{extra}: {self.help}"


# ---------------------------------------------------------------------------
# budget
# ---------------------------------------------------------------------------

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
    ``evaluations`` and ``gradient_steps`` (used so far by this run) and
    ``best_Mean``. ``best`` is the best selection reported so far (sorted list)
    or ``None``; selectors may return it directly.
    """

    def __init__(self, objective, budget: Budget):
        self.objective = objective
        self.budget = budget
        self.rows: list[dict] = []
        self.best: list[int] | None = None
        self.best_mean: float = math.inf
        self.reports = 0

    def report(self, elements: Iterable[int] | np.ndarray | torch.Tensor, mean: float) -> bool:
        """Report an evaluated selection and its ``Mean``; return True if it improved.

        ``elements`` is a list of indices or a boolean mask of length ``Ne``.
        NaN/Inf values are ignored (never an improvement).
        """
        self.reports += 1
        mean = float(mean)
        if not math.isfinite(mean) or mean >= self.best_mean:
            return False
        self.best = mask_to_indices(elements, self.objective.n_elements) \
            if _looks_like_mask(elements, self.objective.n_elements) else sorted(int(i) for i in elements)
        self.best_mean = mean
        self.rows.append({
            "seconds": self.budget.elapsed(),
            "evaluations": self.budget.used_evaluations(),
            "gradient_steps": self.budget.used_gradient_steps(),
            "best_Mean": mean,
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
            return False
        return self.report(selections[i], finite[i])


def _looks_like_mask(elements, n_elements) -> bool:
    if isinstance(elements, torch.Tensor):
        elements = elements.detach().cpu().numpy()
    if isinstance(elements, np.ndarray):
        return elements.dtype == bool or (elements.ndim == 1 and elements.shape[0] == n_elements
                                          and elements.dtype.kind == "f")
    return False


# ---------------------------------------------------------------------------
# selector base class
# ---------------------------------------------------------------------------

class Selector:
    """Base class of every selection strategy (built-in or third-party).

    Class attributes
    ----------------
    name : registry key (lower case letters, digits, ``_`` and ``-``)
    description : one line for ``arraysel list``
    options : ``{name: Option}`` declared options, validated on construction
    uses_gradients : calls ``mask_loss``/``selection_loss`` with gradients
    deterministic : result depends on nothing but (objective, k, budget, seed);
        under a pure evaluation budget, a time limit may cut runs at different points
    needs_evaluations : spends objective evaluations (False only for fixed layouts)

    Subclasses implement :meth:`select`. Options are available as
    ``self.options`` (a dict holding every declared option).
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    options: ClassVar[dict[str, Option]] = {}
    uses_gradients: ClassVar[bool] = False
    deterministic: ClassVar[bool] = True
    needs_evaluations: ClassVar[bool] = True

    def __init__(self, **options: Any):
        declared = type(self).options
        unknown = sorted(set(options) - set(declared))
        if unknown:
            known = ", ".join(sorted(declared)) or "(none)"
            raise ParameterError(f"selector {self.name!r} has no option {', '.join(unknown)}; "
                                 f"its options are: {known}")
        values = {}
        for key, opt in declared.items():
            values[key] = opt.validate(f"{self.name}.{key}", options[key]) if key in options else opt.default
        # instance attribute shadows the class-level declarations
        self.options = values  # type: ignore[misc]

    @classmethod
    def parse_options(cls, pairs: dict[str, str]) -> dict[str, Any]:
        """Convert ``{key: text}`` from ``-o key=value`` to validated values."""
        out = {}
        for key, text in pairs.items():
            if key not in cls.options:
                known = ", ".join(sorted(cls.options)) or "(none)"
                raise ParameterError(f"selector {cls.name!r} has no option {key!r}; its options are: {known}")
            out[key] = cls.options[key].parse(f"{cls.name}.{key}", text)
        return out

    def batch_size(self, n_elements: int, k: int) -> int:
        """Most evaluations this selector may spend in one step (used as overrun slack)."""
        return max(1, n_elements)

    def planned_evaluations(self, n_elements: int, k: int) -> int | None:
        """Evaluations the selector means to spend when the budget allows (for progress
        displays); None when it does not know in advance."""
        return None

    def select(self, objective, k: int, budget: Budget, seed: int, recorder: Recorder) -> list[int]:
        raise NotImplementedError


# ---------------------------------------------------------------------------
# helpers for selector authors
# ---------------------------------------------------------------------------

def numpy_rng(seed: int, stream: int = 0) -> np.random.Generator:
    """A numpy Generator for ``seed`` (independent ``stream`` s for several uses)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(stream)]))


def torch_rng(seed: int, device: torch.device | str = "cpu", stream: int = 0) -> torch.Generator:
    """A torch Generator on ``device`` seeded from ``seed`` and ``stream``."""
    g = torch.Generator(device=torch.device(device))
    g.manual_seed(int(np.random.SeedSequence([int(seed), int(stream)]).generate_state(1, np.uint64)[0]
                      & 0x7FFF_FFFF_FFFF_FFFF))
    return g


def check_selection(selection: Any, n_elements: int, k: int) -> list[int]:
    """Return ``selection`` as a sorted list of ints after checking it holds exactly
    ``k`` distinct indices in ``[0, n_elements)``; raise :class:`SelectionError`."""
    if isinstance(selection, torch.Tensor):
        selection = selection.detach().cpu().tolist()
    elif isinstance(selection, np.ndarray):
        selection = selection.tolist()
    if not isinstance(selection, Sequence) or isinstance(selection, (str, bytes)):
        raise SelectionError(f"a selection must be a list of element indices, got {type(selection).__name__}")
    out = []
    for x in selection:
        if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, np.integer)):
            raise SelectionError(f"selection holds a non-integer entry {x!r}")
        out.append(int(x))
    bad = [i for i in out if not 0 <= i < n_elements]
    if bad:
        raise SelectionError(f"selection holds indices outside [0, {n_elements}): {bad[:5]}")
    if len(set(out)) != len(out):
        raise SelectionError(f"selection repeats elements: {sorted(out)}")
    if len(out) != k:
        raise SelectionError(f"selection holds {len(out)} elements, expected k = {k}")
    return sorted(out)


def indices_to_mask(indices: Iterable[int], n_elements: int) -> np.ndarray:
    """Boolean mask ``(Ne,)`` with ``True`` at ``indices``."""
    m = np.zeros(n_elements, dtype=bool)
    m[list(indices)] = True
    return m


def mask_to_indices(mask, n_elements: int | None = None) -> list[int]:
    """Sorted active indices of a mask (bool or 0/1)."""
    if isinstance(mask, torch.Tensor):
        mask = mask.detach().cpu().numpy()
    return [int(i) for i in np.flatnonzero(np.asarray(mask) > 0.5)]


def top_k(weights, k: int) -> list[int]:
    """Indices of the ``k`` largest weights (ties broken by the lower index), sorted.

    Non-finite weights rank last.
    """
    if isinstance(weights, torch.Tensor):
        weights = weights.detach().cpu().double().numpy()
    w = np.asarray(weights, dtype=np.float64).copy()
    w[~np.isfinite(w)] = -np.inf
    order = np.lexsort((np.arange(w.size), -w))  # by -w, then by index
    return sorted(int(i) for i in order[:k])


def finite_or_inf(values) -> np.ndarray:
    """``values`` as float64 with NaN/Inf replaced by +inf (for argmin)."""
    v = np.asarray(values, dtype=np.float64)
    return np.where(np.isfinite(v), v, np.inf)
