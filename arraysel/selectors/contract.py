"""The selector contract: :class:`Selector`, its declared :class:`Option` s, the
:class:`Budget` of a run (and the :class:`Recorder` of its trace, both in
:mod:`arraysel.selectors.budget`) and the :class:`BudgetedObjective` through which the
runner does the bookkeeping.

A selector chooses which ``k`` of the objective's ``Ne`` elements stay active.
It is built from validated options (``SelectorClass(**options)``) and run by

    ``selector.select(objective, k, seed) -> list[int]``

where

* ``objective`` is a :class:`BudgetedObjective`: it follows the Objective
  contract (``evaluate``, ``mask_loss``, ``selection_loss``, ``n_elements``,
  ``device``, ``dtype`` and the counters, see ``docs/selectors.md``), counts
  what the selector spends against the run's budget, records every hard
  ``k``-selection it scores (the best-so-far trace) and raises
  :class:`BudgetExhausted` once the budget is used up. A selector therefore
  holds only its search: it needs no budget arithmetic and no trace code;
  ``objective.best`` is the best selection scored so far and
  ``objective.budget`` the run's started :class:`Budget` (for schedules);
* ``seed`` is an ``int``; build generators from it with :func:`numpy_rng` and
  :func:`torch_rng` (never use global random state).

The returned list must hold exactly ``k`` distinct ints in ``[0, Ne)``. When
:class:`BudgetExhausted` ends ``select`` the runner takes ``objective.best``.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

if TYPE_CHECKING:  # torch is imported where it is used: `arraysel list` and `report` start without it
    import torch

from arraysel.errors import ArrayselError, ParameterError, SelectionError, check_choice, check_number  # noqa: F401
from arraysel.objective.contract import loss_model_of, objective_info
from arraysel.objective.neighbours import check_moves, check_swaps, move_masks, neighbourhood_of
from arraysel.selection import check_selection, indices_to_mask, mask_to_indices  # noqa: F401  (one home; plugins import them from here)
from arraysel.selectors.budget import (Budget, BudgetExceededError, BudgetExhausted, BudgetGate,  # noqa: F401
                                       Recorder, _is_tensor)  # (their home: arraysel.selectors.budget)
from arraysel.selectors.capabilities import BudgetedLossModel, BudgetedNeighbourhood, say_without

__all__ = [
    "Option", "Selector", "Budget", "Recorder", "BudgetExceededError", "BudgetExhausted",
    "BudgetedObjective", "POLISH_OPTION",
    "numpy_rng", "torch_rng", "check_selection", "indices_to_mask", "mask_to_indices",
    "top_k", "finite_or_inf",
]


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
# the objective a selector sees: counting, clipping, recording
# ---------------------------------------------------------------------------

class BudgetedObjective:
    """The objective as a selector sees it: the runner's bookkeeping around the real one.

    The budget is spent through one small interface, the run's
    :class:`~arraysel.selectors.budget.BudgetGate` (:attr:`gate`): every method and capability that
    scores masks goes through :meth:`~arraysel.selectors.budget.BudgetGate.masks` (counted, clipped
    to the budget in pieces, every mask with exactly ``k`` active elements recorded in the
    best-so-far trace at its own evaluation count), every loss through
    :meth:`~arraysel.selectors.budget.BudgetGate.losses`, and every call through
    :meth:`~arraysel.selectors.budget.BudgetGate.enter` (once the run has ended, :meth:`close`,
    called by the runner, every call raises :class:`~arraysel.errors.ArrayselError`).

    What it charges (the documented selector contract, ``docs/plugins.md``):

    * ``evaluate(masks)`` scores hard masks (booleans, or numbers that are all 0 or 1; other
      weights are refused with a :class:`ParameterError` naming ``masks``: soft weights go to
      ``mask_loss``). When the budget does not allow the whole batch, the allowed first masks are
      scored and recorded, then :class:`BudgetExhausted` is raised: a call either returns every
      score asked for or ends the search (it never returns a shortened array);
    * ``mask_loss`` / ``selection_loss`` raise :class:`BudgetExhausted` when the
      budget does not allow the call (soft weights are counted, not recorded);
    * capabilities, asked from the wrapped objective once and charged by wrapping them
      (:mod:`arraysel.selectors.capabilities`): :meth:`neighbourhood` (its neighbours of a
      selection scored in one call) and :meth:`loss_model` (the loss's gradient and Hessian); None
      where it has none, said once in the log;
    * every other attribute (``n_elements``, ``device``, ``dtype``, ``scene``,
      ``kernels``, the counters ``evaluations``/``gradient_steps``/``seconds``)
      is the wrapped objective's: the contract gives a selector the objective's description, and
      :func:`~arraysel.objective.contract.objective_info` reads its optional attributes through
      this view.

    Helpers, built on the above (they charge nothing of their own): :meth:`score` (``Mean`` of
    masks, NaN as ``+inf``), :meth:`score_indices`, :meth:`evaluate_swaps` / :meth:`evaluate_moves`
    and :meth:`score_swaps` / :meth:`score_moves` (neighbours of a selection: :meth:`neighbourhood`
    where the objective has one, else their masks), :meth:`mask_hessian` (:meth:`loss_model`),
    :meth:`fallback` (the selection the run returns when the budget ends before any
    ``k``-selection is scored), ``best`` / ``best_mean`` (best recorded so far), ``budget`` (the
    started budget; ``budget.fraction()`` for schedules) and :meth:`remaining` (evaluations the
    budget allows now).
    """

    def __init__(self, objective, budget: Budget, recorder: Recorder, k: int, piece: int | None = None,
                 constraints=None):
        self._inner = objective
        #: the run's :class:`~arraysel.constraints.Constraints` (None: none): only the masks that
        #: meet them are recorded, so ``best`` is always a selection the scanner can drive
        self.constraints = constraints
        self.budget = budget
        self.recorder = recorder
        self.k = int(k)
        self.n_elements = int(objective.n_elements)
        default = int(objective_info(objective).chunk or 256)
        #: the one interface the budget is spent through
        self.gate = BudgetGate(budget, recorder, self.k, piece if piece is not None else min(default, 256),
                               constraints)
        self._capabilities: dict = {}  # the wrapped objective's neighbourhood and loss model, asked once

    def __getattr__(self, name):  # everything not defined here is the wrapped objective's
        if name.startswith("__") or name in ("_inner", "gate", "constraints", "_capabilities"):
            raise AttributeError(name)
        self.gate.check_open()
        return getattr(self._inner, name)

    @property
    def piece(self) -> int:
        """The most masks scored in one call of the wrapped objective."""
        return self.gate.piece

    @property
    def first_call_s(self) -> float | None:
        """Seconds into the budget at which the run first called the objective (``evaluate``,
        ``evaluate_swaps``, ``evaluate_moves``, ``mask_loss`` or ``selection_loss``); None before that."""
        return self.gate.first_call_s

    def close(self) -> None:
        """End the run: later calls (from a thread the selector left running) raise instead of
        counting against, or recording in, a run that is over. The runner calls it."""
        self.gate.close()

    # -- bookkeeping -----------------------------------------------------------
    @property
    def best(self) -> list[int] | None:
        return None if self.recorder.best is None else list(self.recorder.best)

    @property
    def best_mean(self) -> float:
        return self.recorder.best_mean

    def fallback(self, selection) -> None:
        """Name ``selection`` (``k`` element indices) as what the run returns when its budget ends
        before any ``k``-selection was scored (a search's start, say); nothing is scored or
        counted, and a scored selection always takes precedence."""
        self.gate.check_open()
        if self.recorder.first is None:
            self.recorder.first = check_selection(selection, self.n_elements, self.k)

    def remaining(self) -> int | float:
        """Evaluations the budget allows now (``math.inf`` when only time limits it, 0 when spent)."""
        if self.budget.exhausted():
            return 0
        return self.budget.remaining_evaluations()

    # -- the Objective contract -----------------------------------------------
    def evaluate(self, masks, **kwargs) -> dict[str, np.ndarray]:
        self.gate.enter()
        if _is_tensor(masks):
            masks = masks.detach().cpu().numpy()
        masks = np.asarray(masks)
        if masks.ndim == 1:
            masks = masks[None, :]
        hard = _hard_masks(masks)
        if int(masks.shape[0]) == 0:
            return self._inner.evaluate(masks, **kwargs)
        return self.gate.masks(int(hard.shape[0]), lambda sl: self._inner.evaluate(hard[sl], **kwargs),
                               lambda sl: hard[sl])

    def evaluate_swaps(self, mask, out, into) -> dict[str, np.ndarray]:
        """:func:`arraysel.objective.neighbours.evaluate_swaps` of the wrapped objective (its own
        neighbourhood scoring where it has one), counted, clipped and recorded like
        :meth:`evaluate` of the neighbour masks."""
        m, a, b = check_swaps(mask, out, into)
        return self.evaluate_moves(m, a[:, None], b[:, None])

    def evaluate_moves(self, mask, out, into) -> dict[str, np.ndarray]:
        """:func:`arraysel.objective.neighbours.evaluate_moves` of the wrapped objective: the
        neighbours of ``mask`` that switch the elements ``out[i]`` off and ``into[i]`` on
        (``(B, m)`` each), counted, clipped and recorded like :meth:`evaluate` of their masks;
        scored by :meth:`neighbourhood` where the objective has one."""
        self.gate.enter()
        m, a, b = check_moves(mask, out, into)
        if a.shape[0] == 0:
            return self._inner.evaluate(np.zeros((0, m.size), dtype=bool))
        nb = self.neighbourhood()
        if nb is not None:
            return nb.evaluate(m, a, b)
        return self.gate.masks(a.shape[0], lambda sl: self._inner.evaluate(move_masks(m, a[sl], b[sl])),
                               lambda sl: move_masks(m, a[sl], b[sl]))

    # -- the objective's capabilities, charged to the budget -------------------
    def _capability(self, name: str, ask):
        """The wrapped objective's capability ``name``, asked once (``ask(objective)``); said once
        in the log when it has none (:func:`~arraysel.selectors.capabilities.say_without`)."""
        if name not in self._capabilities:
            got = ask(self._inner)
            if got is None:
                say_without(self._inner, name)
            self._capabilities[name] = got
        return self._capabilities[name]

    def neighbourhood(self) -> BudgetedNeighbourhood | None:
        """The wrapped objective's :class:`~arraysel.objective.contract.Neighbourhood` (asked once,
        :func:`~arraysel.objective.contract.neighbourhood_of`), its scoring counted, clipped and
        recorded by this budget; None when it has none (said once in the log)."""
        self.gate.check_open()
        nb = self._capability("neighbourhood", neighbourhood_of)
        return None if nb is None else BudgetedNeighbourhood(self.gate, nb)

    def loss_model(self) -> BudgetedLossModel | None:
        """The wrapped objective's :class:`~arraysel.objective.contract.LossModel` (asked once,
        :func:`~arraysel.objective.contract.loss_model_of`), each gradient and Hessian checked
        against this budget; None when it has none (said once in the log)."""
        self.gate.check_open()
        model = self._capability("loss model", loss_model_of)
        return None if model is None else BudgetedLossModel(self.gate, model, self.n_elements)

    def score_swaps(self, mask, out, into) -> np.ndarray:
        """``Mean`` of the one-swap neighbours ``(out[i], into[i])`` of ``mask`` (:meth:`evaluate_swaps`),
        float64 with NaN/Inf as ``+inf``."""
        return finite_or_inf(self.evaluate_swaps(mask, out, into)["Mean"])

    def score_moves(self, mask, out, into) -> np.ndarray:
        """``Mean`` of the neighbours of ``mask`` that switch ``out[i]`` off and ``into[i]`` on
        (:meth:`evaluate_moves`), float64 with NaN/Inf as ``+inf``."""
        return finite_or_inf(self.evaluate_moves(mask, out, into)["Mean"])

    def score(self, masks) -> np.ndarray:
        """``Mean`` of each mask ``(B, Ne)`` as float64, NaN/Inf replaced by ``+inf``."""
        return finite_or_inf(self.evaluate(masks)["Mean"])

    def score_indices(self, selections) -> np.ndarray:
        """:meth:`score` of ``(B, k)`` element indices."""
        sel = np.asarray(selections, dtype=np.int64).reshape(-1, self.k) if self.k else \
            np.zeros((0, 0), dtype=np.int64)
        masks = np.zeros((sel.shape[0], self.n_elements), dtype=bool)
        np.put_along_axis(masks, sel, True, axis=1)
        return self.score(masks)

    def mask_loss(self, weights, *args, **kwargs):
        self.gate.enter()
        b = int(weights.shape[0]) if getattr(weights, "ndim", 1) == 2 else 1
        self.gate.losses(b, f"mask_loss of {b} weight vectors")
        return self._inner.mask_loss(weights, *args, **kwargs)

    def mask_hessian(self, mask):
        """``(g, H)`` of ``mask_loss`` at ``mask`` (:class:`~arraysel.objective.contract.HasHessian`):
        the model of :meth:`loss_model`; ``Ne`` evaluations."""
        self.gate.check_open()
        model = self.loss_model()
        if model is None:
            raise ParameterError("mask_hessian: this objective has no model of its loss (no mask_loss)")
        return model.model(mask)

    def selection_loss(self, P, P_soft, *args, **kwargs):
        self.gate.enter()
        self.gate.losses(1, "selection_loss")
        return self._inner.selection_loss(P, P_soft, *args, **kwargs)


def _hard_masks(masks: np.ndarray) -> np.ndarray:
    """``masks`` as booleans; refuses weights other than 0 and 1 (what ``evaluate`` scores and
    records must be the selection it names: soft weights go through ``mask_loss``)."""
    if masks.dtype == bool:
        return masks
    if masks.dtype.kind not in "biuf":
        raise ParameterError(f"masks must be boolean or 0/1 numbers, got dtype {masks.dtype}")
    hard = masks != 0
    if not np.array_equal(hard, masks == 1):
        bad = masks[(masks != 0) & (masks != 1)].reshape(-1)[0]
        raise ParameterError(f"masks must hold only 0 and 1 (hard selections), got the weight {bad!r}; "
                             f"score soft weights with objective.mask_loss(weights)")
    return hard


# ---------------------------------------------------------------------------
# selector base class
# ---------------------------------------------------------------------------

#: the option every selector has (added to each subclass's ``options``)
POLISH_OPTION = Option(float, 0.0, "fraction of the budget kept for a final swap local search (swap's "
                       "settings without a race) started from this selector's result; 0: none", lo=0.0, hi=0.9)


class Selector:
    """Base class of every selection strategy (built-in or third-party).

    Class attributes
    ----------------
    name : registry key (lower case letters, digits, ``_`` and ``-``)
    description : one line for ``arraysel list``
    options : ``{name: Option}`` declared options, validated on construction
    uses_gradients : calls ``mask_loss``/``selection_loss`` with gradients
    deterministic : the result does not depend on the seed (``compare`` runs it
        once instead of once per seed). Every selector, deterministic or not,
        must be reproducible: the same (objective, k, seed) under the same
        evaluation budget gives the same result
    needs_evaluations : spends objective evaluations (False only for fixed layouts)
    scores_neighbourhoods : scores one-swap neighbourhoods (``score_swaps``/``evaluate_swaps``):
        the runner prepares the objective for them before the budget starts
        (``prepare_neighbourhoods``, :mod:`arraysel.objective.neighbours`)
    requires : Python packages (import names) the selector needs beyond arraysel's own
        dependencies; a selector whose packages are missing is refused before a run starts
        (:meth:`missing`, :meth:`install_hint`) and ``arraysel list`` marks it
    extra : the arraysel extra that installs ``requires`` (``pip install 'arraysel[extra]'``);
        None: install the packages themselves
    baseline : a reference layout or sampler (``uniform``, ``spiral``, ``random``), not a search: a
        scene's default polish (``sector.polish``) leaves its selections as they are

    Subclasses implement :meth:`select`. Options are available as
    ``self.options`` (a dict holding every declared option). Every subclass
    also has the option ``polish`` (:data:`POLISH_OPTION`), carried out by the
    runner: the selector runs on ``1 - polish`` of the budget and a swap local
    search from its result (:data:`arraysel.selectors.swapsettings.POLISH`) spends the rest.
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    options: ClassVar[dict[str, Option]] = {}
    uses_gradients: ClassVar[bool] = False
    deterministic: ClassVar[bool] = False
    needs_evaluations: ClassVar[bool] = True
    scores_neighbourhoods: ClassVar[bool] = False
    requires: ClassVar[tuple[str, ...]] = ()
    extra: ClassVar[str | None] = None
    baseline: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if "polish" not in cls.options:
            cls.options = {**cls.options, "polish": POLISH_OPTION}

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
    def missing(cls) -> list[str]:
        """The packages of :attr:`requires` that cannot be imported here (found, not imported)."""
        import importlib.util

        out = []
        for name in cls.requires:
            try:
                found = importlib.util.find_spec(name) is not None
            except (ImportError, ValueError):
                found = False
            if not found:
                out.append(name)
        return out

    @classmethod
    def install_hint(cls) -> str:
        """The pip command that installs :attr:`requires`."""
        return f"pip install 'arraysel[{cls.extra}]'" if cls.extra else "pip install " + " ".join(cls.requires)

    @classmethod
    def check_available(cls) -> None:
        """Raise :class:`ParameterError` naming the missing packages and the pip command that
        installs them, when some of :attr:`requires` are missing."""
        missing = cls.missing()
        if missing:
            raise ParameterError(f"selector {cls.name!r} needs {', '.join(missing)}, which "
                                 f"{'is' if len(missing) == 1 else 'are'} not installed; install it with: "
                                 f"{cls.install_hint()}")

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

    def select(self, objective: "BudgetedObjective", k: int, seed: int) -> list[int]:
        """Search; return ``k`` distinct element indices (see the module docstring)."""
        raise NotImplementedError


# ---------------------------------------------------------------------------
# helpers for selector authors
# ---------------------------------------------------------------------------

def numpy_rng(seed: int, stream: int = 0) -> np.random.Generator:
    """A numpy Generator for ``seed`` (independent ``stream`` s for several uses)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(stream)]))


def torch_rng(seed: int, device: torch.device | str = "cpu", stream: int = 0) -> torch.Generator:
    """A torch Generator on ``device`` seeded from ``seed`` and ``stream``."""
    import torch

    g = torch.Generator(device=torch.device(device))
    g.manual_seed(int(np.random.SeedSequence([int(seed), int(stream)]).generate_state(1, np.uint64)[0]
                      & 0x7FFF_FFFF_FFFF_FFFF))
    return g


def top_k(weights, k: int) -> list[int]:
    """Indices of the ``k`` largest weights (ties broken by the lower index), sorted.

    Non-finite weights rank last.
    """
    if _is_tensor(weights):
        weights = weights.detach().cpu().double().numpy()
    w = np.asarray(weights, dtype=np.float64).copy()
    w[~np.isfinite(w)] = -np.inf
    order = np.lexsort((np.arange(w.size), -w))  # by -w, then by index
    return sorted(int(i) for i in order[:k])


def finite_or_inf(values) -> np.ndarray:
    """``values`` as float64 with NaN/Inf replaced by +inf (for argmin)."""
    v = np.asarray(values, dtype=np.float64)
    return np.where(np.isfinite(v), v, np.inf)
