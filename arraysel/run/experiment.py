"""Run selectors on an objective and compare them.

An :class:`Experiment` is (objective, selector, options, budget, seed);
:meth:`Experiment.run` returns one flat row with the fixed columns
:data:`ROW_COLUMNS` and never dies because of the selector: an exception
raised by the selector (or the objective it calls), or an invalid selection,
lands in the row's ``error`` column. It *does* raise
:class:`~arraysel.selectors.contract.BudgetExceededError` when the selector used more
objective evaluations than its budget plus one batch.

:func:`arraysel.run.compare.compare` runs every selector for every seed (one
:class:`Experiment` each) and writes the report; :data:`ROW_COLUMNS` is defined
in :mod:`arraysel.report.columns`.

The objective is passed in (dependency injection), so any object following
the Objective contract works, e.g. :class:`arraysel.objective.toy.ToyObjective`.

Example
-------
>>> from arraysel.objective.toy import ToyObjective
>>> from arraysel.run.experiment import Experiment
>>> from arraysel.selectors.contract import Budget
>>> row = Experiment(ToyObjective(16, 8), "uniform", budget=Budget(evaluations=10)).run()
>>> row["elements"]
'0 2 4 6 8 10 12 14'

:meth:`Experiment.execute` returns the same row with its ``elements`` as a
:class:`~arraysel.selection.Selection` (``None`` when the run has none): the form ``compare`` carries
to its files and figures; its text is formed where a row is written (:func:`arraysel.run.store.file_row`).
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import sys
import threading
import time
from typing import Any

import numpy as np

from arraysel.errors import ParameterError, SelectionError, check_number, error_text as _error_text
from arraysel.objective.contract import objective_info
from arraysel.report.columns import METRICS, ROW_COLUMNS, TRACE_COLUMNS  # noqa: F401  (re-exported)
from arraysel.run.sector_report import beam_polish_plan
from arraysel.selection import Selection
from arraysel.constraints import constraints_of
from arraysel.selectors.constrained import ConstrainedObjective
from arraysel.selectors.contract import (Budget, BudgetedObjective, BudgetExceededError, BudgetExhausted, Recorder,
                                         Selector, check_selection, indices_to_mask, numpy_rng)

__all__ = ["METRICS", "ROW_COLUMNS", "TRACE_COLUMNS", "Experiment", "full_row", "config_label", "budget_flag",
           "late_start_flag", "with_end_row"]


def config_label(name: str, options: dict | None = None) -> str:
    """``name`` or ``name(key=value,...)`` for non-default options."""
    if not options:
        return name
    inner = ",".join(f"{k}={options[k]}" for k in sorted(options))
    return f"{name}({inner})"


def _counters(objective) -> tuple[int, int, float]:
    return int(objective.evaluations), int(objective.gradient_steps), float(objective.seconds)


def _final_metrics(objective, selection: list[int]) -> dict[str, float]:
    """Headline metrics, then a several-point scene's per-point breakdown (``objective.breakdown_names``)."""
    mask = indices_to_mask(selection, int(objective.n_elements))[None, :]
    out = objective.evaluate(mask)
    names = METRICS + objective_info(objective).breakdown_names
    return {m: float(np.asarray(out[m], dtype=np.float64).reshape(-1)[0]) for m in names if m in out}


def _breakdown(metrics: dict) -> dict:
    """Pop the per-point columns out of ``metrics``: they go after :data:`ROW_COLUMNS` in a row."""
    return {k: metrics.pop(k) for k in [k for k in metrics if k not in METRICS]}


def _resolve(selector, registry) -> type[Selector]:
    if isinstance(selector, type) and issubclass(selector, Selector):
        return selector
    if registry is None:
        from arraysel.selectors.registry import get_registry
        registry = get_registry()
    return registry[selector]


@dataclasses.dataclass
class Experiment:
    """One selection run: (objective, selector, options, budget, seed).

    Parameters
    ----------
    objective : object following the Objective contract
    selector : registered name or a :class:`Selector` subclass
    options : option values for the selector (validated)
    budget : limits; a fresh copy is started for each :meth:`run`
    seed : int seed given to the selector
    k : elements to keep (default ``objective.k``)
    config : label in the tables (default from name and options)
    registry : where to look the name up (default: the process-wide registry)
    progress : show a progress bar of the run (evaluations against the budget or the
        selector's plan, gradient steps, best Mean so far) on stderr; None: only when stderr is
        a terminal (a redirected log gets no carriage-return frames)

    After :meth:`run`, ``trace`` holds the improvement rows and ``selection``
    the selected elements (or ``None``).
    """

    objective: Any
    selector: Any
    options: dict = dataclasses.field(default_factory=dict)
    budget: Budget = dataclasses.field(default_factory=Budget)
    seed: int = 0
    k: int | None = None
    config: str | None = None
    registry: Any = None
    progress: bool | None = False
    trace: list = dataclasses.field(default_factory=list, init=False)
    selection: list | None = dataclasses.field(default=None, init=False)

    def run(self) -> dict:
        """Run the selector once; return a row with the keys :data:`ROW_COLUMNS`, as a file holds it
        (``elements`` as text, ``"0 2 4"``)."""
        from arraysel.run.store import file_row

        return file_row(self.execute())

    def execute(self) -> dict:
        """Run the selector once; return its row with ``elements`` a :class:`Selection` (``None``
        when the run has no selection)."""
        obj = self.objective
        cls = _resolve(self.selector, self.registry)
        selector = cls(**self.options)
        n = int(obj.n_elements)
        k = int(obj.k if self.k is None else self.k)
        check_number("k", k, lo=1, hi=n, integer=True)
        seed = int(check_number("seed", self.seed, lo=0, integer=True))
        config = self.config or config_label(cls.name, self.options)
        constraints = constraints_of(obj)
        if constraints is not None and constraints.k != k:
            raise ParameterError(f"k = {k} differs from the k of the objective's constraints ({constraints.k})")

        e0, g0, s0 = _counters(obj)
        budget = self.budget.fresh().start(obj)
        recorder = Recorder(obj, budget)
        error = ""
        selection = None
        started: list[float] = []  # when the selector first called the objective
        t0 = time.perf_counter()
        watch = _RunProgress(config, budget, recorder, selector.planned_evaluations(n, k),
                             auto=self.progress is None) if self.progress is not False else contextlib.nullcontext()
        polish = float(selector.options.get("polish") or 0.0)
        beams = beam_polish_plan(obj, cls, self.options)  # a sector scene: polish on the per-beam loss
        if beams is not None:
            polish = beams.share
            beams.prepare(obj)
        try:
            with watch:
                result = _search(selector, obj, k, budget, seed, recorder, started, constraints, polish, beams)
            checked = check_selection(result, n, k)
            if constraints is not None:
                constraints.check(checked)  # names the constraint a selector's result breaks
            selection = checked
        except (KeyboardInterrupt, BudgetExceededError):
            raise
        except Exception as exc:  # the selector's (or objective's) failure goes in the row
            error = _error_text(exc)
        recorder.finish()
        wall = time.perf_counter() - t0
        e1, g1, s1 = _counters(obj)
        used = e1 - e0
        if budget.evaluations is not None:
            slack = max(1, int(selector.batch_size(n, k)))
            if used > budget.evaluations + slack:
                raise BudgetExceededError(
                    f"selector {cls.name!r} used {used} objective evaluations, more than its budget of "
                    f"{budget.evaluations} plus one batch ({slack})")

        metrics = {m: math.nan for m in METRICS}
        if selection is not None:
            try:
                metrics.update(_final_metrics(obj, selection))
            except (KeyboardInterrupt, BudgetExceededError):
                raise
            except Exception as exc:
                error = error or f"final evaluation failed: {_error_text(exc)}"
            if not error and not math.isfinite(metrics["Mean"]):
                error = (f"NumericalError: the objective returned NaN/Inf for the selected elements "
                         f"(Mean = {metrics['Mean']})")
        self.selection = selection
        self.trace = [dict(r) for r in recorder.rows]
        if self.trace and self.trace[-1].get("event") == "end" and recorder.best is not None:
            # the selection that scored the run's best Mean (the IOHprofiler files' best.x)
            self.trace[-1]["elements"] = Selection(tuple(recorder.best), n)
        obj_seconds = s1 - s0
        extra = _breakdown(metrics)
        return {
            "config": config, "selector": cls.name, "seed": seed, "k": k, "n_elements": n,
            **metrics,
            "seconds": wall, "evaluations": used, "gradient_steps": g1 - g0,
            "objective_seconds": obj_seconds, "overhead_seconds": max(0.0, wall - obj_seconds),
            "elements": None if selection is None else Selection(tuple(selection), n),
            "options": _options_text(self.options if beams is None else {**self.options, "polish": beams.share}),
            "error": error,
            "budget_flag": late_start_flag(started[0] if started else None, budget), **extra,
        }


def _options_text(options: dict) -> str:
    return json.dumps(options, sort_keys=True, default=str) if options else ""


def with_end_row(row: dict, trace: list[dict]) -> list[dict]:
    """``trace`` with the ``end`` row every finished run has: a run with a selection and a finite
    Mean (no error) whose trace has none (its selector returned a selection it never scored, or
    scored no ``k``-selection) gets its row's Mean, the selection scored again by the comparison,
    as its ``end`` row, at its seconds, evaluations and gradient steps."""
    sel = row.get("elements")
    mean = _number(row.get("Mean"))
    if any(t.get("event") == "end" for t in trace) or str(row.get("error") or "").strip() \
            or not isinstance(sel, Selection) or not len(sel) or not math.isfinite(mean):
        return trace
    seconds, evals, steps = (_number(row.get(c)) for c in ("seconds", "evaluations", "gradient_steps"))
    return [*trace, {"seconds": seconds if math.isfinite(seconds) else 0.0,
                     "evaluations": int(evals) if math.isfinite(evals) else 0,
                     "gradient_steps": int(steps) if math.isfinite(steps) else 0,
                     "best_Mean": mean, "event": "end", "elements": sel}]


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


#: a run whose first objective call comes after this share of its time budget is flagged
LATE_START_SHARE = 0.5


def late_start_flag(first_call_s: float | None, budget: Budget) -> str:
    """``late start: ...`` when a run's first objective call (``evaluate``, ``mask_loss`` or
    ``selection_loss``) came after more than :data:`LATE_START_SHARE` of its time budget (most of
    the budget went to work outside its search), else ``''``."""
    if budget.seconds is None or first_call_s is None or first_call_s <= LATE_START_SHARE * budget.seconds:
        return ""
    return f"late start: its first objective call came {first_call_s:.1f} s into its {budget.seconds:g} s budget"


def budget_flag(row: dict, budget: Budget, grace_s: float) -> str:
    """The ``budget_flag`` of a run's row: ``''`` when its time budget measured its search, else
    why not (``"; "``-joined): ``overran`` (it took more than its time budget plus ``grace_s``
    seconds, or was stopped at that deadline), and the row's own ``late start``
    (:func:`late_start_flag`, set where the run was made). Runs without a time budget are never
    flagged."""
    limit = budget.seconds
    if limit is None:
        return ""
    flags = []
    seconds = float(row.get("seconds", math.nan))
    error = str(row.get("error") or "")
    if math.isfinite(seconds) and seconds > limit + grace_s:
        flags.append(f"overran: {seconds:.1f} s of a {limit:g} s budget (grace {grace_s:g} s)")
    elif "BudgetExceededError: stopped after" in error:
        flags.append(f"overran: stopped at its deadline ({limit:g} s + {grace_s:g} s)")
    own = [f for f in str(row.get("budget_flag") or "").split("; ") if f.startswith("late start")]
    return "; ".join(flags + own[:1])


def _run_selector(selector, obj, k: int, budget: Budget, seed: int, recorder: Recorder, started: list,
                  constraints=None):
    """Call ``selector.select(objective, k, seed)`` on the budgeted view of ``obj``; return what it
    returned (or, when the budget ended the search, the best selection recorded). ``started``
    receives the seconds into the budget of the selector's first objective call (when it made one).
    Under ``constraints`` the selector runs on the reduced problem
    (:class:`~arraysel.selectors.constrained.ConstrainedObjective`) and its units are expanded to
    elements here."""
    view = BudgetedObjective(obj, budget, recorder, k, constraints=constraints)
    try:
        if constraints is None:
            return selector.select(view, k, seed)
        units = selector.select(ConstrainedObjective(view, constraints), constraints.k_units, seed)
        return constraints.expand_indices(check_selection(units, len(constraints.units), constraints.k_units))
    except BudgetExhausted:
        return _best_or_first(recorder)
    finally:
        view.close()  # a thread the selector left running can no longer count or record
        if view.first_call_s is not None:
            started.append(view.first_call_s)


def _search(selector, obj, k: int, budget: Budget, seed: int, recorder: Recorder, started: list, constraints,
            polish: float, beams) -> list[int]:
    """The selector's run on ``1 - polish`` of the budget, then its polish on the rest: on the per-beam
    loss with ``beams`` (a sector scene's :class:`~arraysel.run.sector_report.BeamPolish`), else a
    swap local search (:func:`_polish`)."""
    n = int(obj.n_elements)
    stage = _share_of(budget, obj, 1.0 - polish) if polish > 0 else budget
    result = _run_selector(selector, obj, k, stage, seed, recorder, started, constraints)
    if beams is not None:
        return beams.run(obj, budget, seed, check_selection(result, n, k))
    if polish > 0:
        return _polish(obj, k, budget, seed, recorder, check_selection(result, n, k), constraints)
    return result


def _best_or_first(recorder: Recorder) -> list[int]:
    if recorder.best is not None:
        return list(recorder.best)
    if recorder.first is not None:  # every score was NaN/Inf: the final scoring reports it
        return list(recorder.first)
    raise SelectionError("the budget ran out before the selector scored any selection of k elements")


def _share_of(budget: Budget, obj, fraction: float) -> Budget:
    """A budget of ``fraction`` of each limit of the started ``budget``, started at the same moment."""
    def part(v, integer):
        if v is None:
            return None
        return max(1, int(v * fraction)) if integer else max(1e-3, v * fraction)

    sub = Budget(part(budget.seconds, False), part(budget.evaluations, True),
                 part(budget.gradient_steps, True)).start(obj)
    sub._t0, sub._e0, sub._g0 = budget._t0, budget._e0, budget._g0
    return sub


def _polish(obj, k: int, budget: Budget, seed: int, recorder: Recorder, start: list[int],
            constraints=None) -> list[int]:
    """Swap local search from ``start`` with what is left of ``budget`` (the settings
    :data:`~arraysel.selectors.swapsettings.POLISH`: ``swap``'s, without a race)."""
    from arraysel.selectors.localsearch import SwapSearch
    from arraysel.selectors.swapsettings import POLISH

    view = BudgetedObjective(obj, budget, recorder, k, constraints=constraints)
    space, ks = view, k
    if constraints is not None:
        space, ks, start = ConstrainedObjective(view, constraints), constraints.k_units, constraints.reduce_indices(start)
    search = SwapSearch(space, ks, numpy_rng(seed, stream=7), POLISH)
    try:
        search.run(start)
    except BudgetExhausted:
        pass
    finally:
        view.close()
    best = recorder.best
    return list(best) if best is not None else start


class _RunProgress:
    """A tqdm bar for one run, refreshed from the budget's counters by a background thread
    (selectors need no code for it): evaluations (of the budget's, else of the selector's
    planned number), rate, gradient steps and the best Mean so far."""

    def __init__(self, label: str, budget: Budget, recorder: Recorder, planned: int | None,
                 interval: float = 0.5, auto: bool = False):
        self.label, self.budget, self.recorder, self.auto = label, budget, recorder, auto
        caps = [v for v in (budget.evaluations, planned) if v is not None]
        self.total = min(caps) if caps else None
        self.interval = interval
        self._stop = threading.Event()

    def _refresh(self, bar):
        used = self.budget.used_evaluations()
        bar.update(used - bar.n)
        text = f"steps {self.budget.used_gradient_steps()}"
        if math.isfinite(self.recorder.best_mean):
            text += f", best Mean {self.recorder.best_mean:.5g}"
        bar.set_postfix_str(text, refresh=False)

    def _loop(self, bar):
        while not self._stop.wait(self.interval):
            self._refresh(bar)
            bar.refresh()

    def __enter__(self):
        from tqdm.auto import tqdm

        self.bar = tqdm(total=self.total, desc=self.label, unit="eval", unit_scale=True, file=sys.stderr,
                        dynamic_ncols=True, disable=None if self.auto else False)  # auto: a terminal only
        self.thread = threading.Thread(target=self._loop, args=(self.bar,), daemon=True)
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self.thread.join()
        self._refresh(self.bar)
        self.bar.refresh()
        self.bar.close()
        return False


def full_row(objective) -> dict:
    """The ``full`` reference row: every element active, evaluated once (``elements``: their
    :class:`Selection`)."""
    n = int(objective.n_elements)
    e0, g0, s0 = _counters(objective)
    t0 = time.perf_counter()
    error = ""
    metrics = {m: math.nan for m in METRICS}
    try:
        metrics.update(_final_metrics(objective, list(range(n))))
    except KeyboardInterrupt:
        raise
    except Exception as exc:
        error = f"full-array evaluation failed: {_error_text(exc)}"
    wall = time.perf_counter() - t0
    e1, g1, s1 = _counters(objective)
    extra = _breakdown(metrics)
    return {
        "config": "full", "selector": "full", "seed": "", "k": n, "n_elements": n, **metrics,
        "seconds": wall, "evaluations": e1 - e0, "gradient_steps": g1 - g0,
        "objective_seconds": s1 - s0, "overhead_seconds": max(0.0, wall - (s1 - s0)),
        "elements": Selection(tuple(range(n)), n), "options": "", "error": error, "budget_flag": "", **extra,
    }
