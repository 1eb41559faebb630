"""The run modes of ``compare`` as interchangeable runners.

A runner makes the ``(selector, seed)`` runs of a comparison, each a :class:`RunSpec`; they share
one small interface (:class:`Runner`): :meth:`~Runner.prepare` before the first run's clock
starts (build what the runs need; warm this process's objective when runs go here),
:meth:`~Runner.run` yields ``(i, row, trace)`` for ``todo[i]`` as each run finishes (in any
order), :meth:`~Runner.warm_ups` lists the workers' one-off work for ``run.json``, and
:meth:`~Runner.close` ends them. The three:

* :class:`InProcessRunner` -- one after another in this process (``--in-process``);
* :class:`IsolatedRunner` -- each in a fresh child process forked from a warm template
  (:mod:`arraysel.run.isolation`, :mod:`arraysel.run.template`; the default);
* :class:`ExecutorRunner` -- on an executor, again each in a fresh process
  (:mod:`arraysel.run.executors`: a process pool or Dask).

A row's ``elements`` is the run's :class:`~arraysel.selection.Selection` (``None`` without
one). A run without a result gets its row from :func:`failure_row`, the one place such rows
are made.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import time
from typing import Callable, Iterator

import numpy as np

from arraysel.errors import ArrayselError, error_text as _error_text
from arraysel.objective.contract import WorkerFactory, objective_info
from arraysel.objective.neighbours import neighbourhood_of
from arraysel.report.columns import METRICS
from arraysel.run.compare_task import _Raise, compare_item, compare_task
from arraysel.run.deadline import RunStopped, call_with_deadline
from arraysel.run.guard import Reductions, describe
from arraysel.run.experiment import Experiment, _final_metrics
from arraysel.run.workers import TaskFailed, objective_factory_for
from arraysel.selection import indices_to_mask
from arraysel.selectors.contract import Budget, BudgetExceededError

__all__ = ["RunSpec", "Runner", "InProcessRunner", "IsolatedRunner", "ExecutorRunner", "make_runner", "check_isolated",
           "failure_row"]


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """One ``(selector, seed)`` run of a comparison: its config label, selector class and options;
    ``origin``: the registry's origin of the selector (how a run's process finds a class that does
    not pickle by name, :func:`~arraysel.run.compare_task.compare_item`)."""

    config: str
    selector: type
    options: dict
    seed: int
    origin: str | None = None

    def item(self, budget: Budget) -> dict:
        """The run as a task for another process (:func:`~arraysel.run.compare_task.compare_item`)."""
        return compare_item(self.config, self.selector, self.options, budget, self.seed, origin=self.origin)


def failure_row(objective, spec: RunSpec, failure: BaseException | TaskFailed, budget: Budget, grace: float,
                lost: bool = False) -> dict:
    """The row of a run without a result, ``error`` saying why: the
    :class:`~arraysel.selectors.contract.BudgetExceededError` it raised, or the
    :class:`~arraysel.run.workers.TaskFailed` of its process (stopped at its deadline: ``run failed:
    BudgetExceededError: ...``; died or failed: ``run failed: ...``; with ``lost``, a run an executor
    could not complete on any worker: ``run lost: ...``)."""
    if isinstance(failure, BaseException):
        if not lost:
            return _error_row(objective, spec, _error_text(failure))
        failure = TaskFailed(_error_text(failure))
    msg = failure.message
    if failure.kind == "timeout" and budget.seconds is None:
        return _error_row(objective, spec, f"run failed: BudgetExceededError: {msg}; the run had no time budget "
                                           f"and a limit of {grace:g} s (the grace period)")
    if failure.kind == "timeout":
        return _error_row(objective, spec, f"run failed: BudgetExceededError: {msg}; the budget was "
                                           f"{budget.seconds:g} s and the grace period {grace:g} s")
    return _error_row(objective, spec, f"run lost: {msg}" if lost else f"run failed: {msg}")


def _error_row(objective, spec: RunSpec, message: str) -> dict:
    nan = math.nan
    return {
        "config": spec.config, "selector": spec.selector.name, "seed": spec.seed, "k": int(objective.k),
        "n_elements": int(objective.n_elements), **{m: nan for m in METRICS},
        "seconds": nan, "evaluations": nan, "gradient_steps": nan, "objective_seconds": nan,
        "overhead_seconds": nan, "elements": None,
        "options": json.dumps(spec.options, sort_keys=True, default=str) if spec.options else "",
        "error": message, "budget_flag": "",
    }


def _timeout(budget: Budget, grace: float) -> float:
    """Seconds a run may take: its time budget plus the grace period (without a time budget, the
    grace period alone)."""
    return grace if budget.seconds is None else budget.seconds + grace


def _report_rtol(objective) -> float:
    """How far (relative) a row's Mean may be from its selection scored again here: float32 sums
    round differently with the number of threads (a worker's one against this process's several;
    a paper-scene selection measured 0.00533887 on one thread and 0.00533881 on two, 1.1e-5
    apart), so 1e-4 for a float32 objective, 1e-5 otherwise."""
    import torch

    return 1e-4 if objective_info(objective).dtype in (torch.float32, torch.float16, torch.bfloat16) else 1e-5


def _checked(objective, row: dict, trace: list) -> tuple[dict, list]:
    """A row made in another process, checked here: its selection is scored again on this
    process's objective, which no plugin has touched. A Mean that differs (a selector that
    patched ``evaluate`` in its own process, say) is replaced by the true one, the row gets an
    error naming both, and its trace, recorded in that process, is left out."""
    selection = row.get("elements")
    if not selection or str(row.get("error") or "").strip():
        return row, trace
    try:
        true = _final_metrics(objective, list(selection.indices))
    except Exception as exc:  # its selection cannot be scored here: the row cannot be trusted
        return {**row, "error": f"its selection could not be scored again: {_error_text(exc)}"}, []
    got, want = float(row.get("Mean", math.nan)), float(true.get("Mean", math.nan))
    if got == want or abs(got - want) <= _report_rtol(objective) * abs(want):
        return row, trace
    return {**row, **true, "error": f"the run reported Mean {got:.6g} for its selection, which scores {want:.6g}: "
                                    f"the selector changed the objective in its own process (its trace is "
                                    f"left out)"}, []


class Runner:
    """The interface of a run mode (see the module's text); a runner makes each run at most once."""

    def prepare(self, todo: list[RunSpec]) -> dict | None:
        """Get ready for ``todo`` before the first run's clock starts; the warm-up of this
        process's objective for ``run.json`` when runs go here, else ``None``."""
        return None

    def run(self, todo: list[RunSpec], on_start: Callable[[RunSpec], None] | None = None
            ) -> Iterator[tuple[int, dict, list]]:
        """``(i, row, trace)`` of ``todo[i]``, as each run finishes."""
        raise NotImplementedError

    def warm_ups(self) -> list[dict]:
        """Each worker's one-off work (objective build, basis check, compiled code), never
        charged to a run."""
        return []

    def close(self) -> None:
        """End the workers (a runner that has none does nothing)."""


class InProcessRunner(Runner):
    """The runs one after another in this process, on ``objective`` itself (warmed first), each
    with ``threads`` threads (torch, numba, BLAS; :func:`~arraysel.run.template.thread_counts`,
    restored after it; ``None``: as they are), each stopped ``grace`` seconds after its time
    budget as an isolated run is (:func:`~arraysel.run.deadline.call_with_deadline`). After each,
    the objective must be as it was (:class:`_Fingerprint`), and so must the functions the tables
    are computed with (:class:`~arraysel.run.guard.Reductions`; those a run replaced are put back
    before its row is saved): a run that changed either is yielded with an error, then the
    comparison stops (:class:`~arraysel.errors.ArrayselError`)."""

    def __init__(self, objective, budget: Budget, grace: float, full_mean: float, progress: bool | None = False,
                 threads: int | None = None):
        self.objective, self.budget, self.grace = objective, budget, grace
        self.full_mean, self.progress, self.threads = full_mean, progress, threads
        self.fingerprint: _Fingerprint | None = None
        self.reductions: Reductions | None = None

    def prepare(self, todo: list[RunSpec]) -> dict | None:
        from arraysel.run.template import thread_counts, warm_objective

        with thread_counts(self.threads):  # warmed as the runs will use it
            warm = warm_objective(self.objective) if todo else None
            if warm is not None and any(scores_neighbourhoods(s) for s in todo):
                warm["neighbourhoods_s"] = prepare_neighbourhoods(self.objective)
        self.fingerprint = _Fingerprint(self.objective, self.full_mean)  # taken once warm
        self.reductions = Reductions()
        return warm

    def run(self, todo, on_start=None):
        for i, spec in enumerate(todo):
            if on_start is not None:
                on_start(spec)
            row, trace, why = self.run_one(spec)
            yield i, row, trace
            if why:
                raise ArrayselError(f"{spec.config} seed {spec.seed}: {why}")

    def run_one(self, spec: RunSpec) -> tuple[dict, list, str]:
        """``(row, trace, why)``: ``why`` is ``''`` unless the run changed the objective (then
        its row holds the error too)."""
        from arraysel.run.template import thread_counts

        exp = Experiment(self.objective, spec.selector, options=spec.options, budget=self.budget, seed=spec.seed,
                         config=spec.config, progress=self.progress)
        limit = _timeout(self.budget, self.grace)
        try:
            with thread_counts(self.threads):
                row = call_with_deadline(exp.execute, limit)
                trace = exp.trace
        except BudgetExceededError as exc:
            row, trace = failure_row(self.objective, spec, exc, self.budget, self.grace), []
        except RunStopped as exc:  # its deadline, as a child process is killed at it
            failure = TaskFailed(f"stopped after {getattr(exc, 'elapsed', limit):.1f} s (its limit was {limit:.1f} s): "
                                 f"the run did not return in time", kind="timeout")
            row, trace = failure_row(self.objective, spec, failure, self.budget, self.grace), []
        why = self._changes()
        if not why:
            return row, trace, ""
        # its numbers, and those of every later run here, cannot be trusted
        why = f"{why}; run it isolated (without --in-process)"
        return {**row, "error": "; ".join(e for e in (str(row.get("error") or ""), why) if e)}, trace, why

    def _changes(self) -> str:
        """What the last run changed in this process ('' when nothing): the objective, or the
        functions the tables use (put back here, before its row is saved)."""
        parts = []
        changed = self.fingerprint.changed() if self.fingerprint is not None else ""
        if changed:
            parts.append(f"the selector changed the objective it was given ({changed})")
        replaced = self.reductions.restore() if self.reductions is not None else []
        if replaced:
            parts.append(f"the selector replaced {describe(replaced)} in this process (put back before any table "
                         f"was written)")
        return "; ".join(parts)


class IsolatedRunner(Runner):
    """Each run in a fresh child process forked from a warm template
    (:class:`~arraysel.run.isolation.IsolatedWorker`), stopped ``grace`` seconds after its time
    budget. A selector class that can reach a child neither pickled by name nor through its
    plugin is refused before any run (:func:`check_isolated`), never run here instead."""

    def __init__(self, objective, factory, budget: Budget, grace: float, threads: int | None = None,
                 verify: str | None = None):
        self.objective, self.factory, self.budget, self.grace = objective, factory, budget, grace
        self.threads, self.verify = threads, verify
        self.worker = None

    def prepare(self, todo):
        from arraysel.run.isolation import IsolatedWorker

        check_isolated(todo)
        self.worker = IsolatedWorker(self.factory, threads=self.threads, verify=self.verify)
        return None

    def run(self, todo, on_start=None):
        for i, spec in enumerate(todo):
            if on_start is not None:
                on_start(spec)
            res = self.worker.run(compare_task, spec.item(self.budget), _timeout(self.budget, self.grace))
            if isinstance(res, _Raise) and not isinstance(res.exception, BudgetExceededError):
                raise res.exception
            if isinstance(res, (_Raise, TaskFailed)):
                failure = res.exception if isinstance(res, _Raise) else res
                yield i, failure_row(self.objective, spec, failure, self.budget, self.grace), []
            else:
                yield (i, *_checked(self.objective, res["row"], res["trace"]))

    def warm_ups(self):
        return [] if self.worker is None else self.worker.warm_ups

    def close(self):
        if self.worker is not None:
            self.worker.close()


class ExecutorRunner(Runner):
    """The runs on an :class:`~arraysel.run.executors.Executor`, each in a fresh process stopped at
    its deadline; results arrive in any order. A run that kept failing gets a ``run lost`` row."""

    def __init__(self, objective, factory, executor, budget: Budget, grace: float, verify: str | None = None):
        self.objective, self.factory, self.executor = objective, factory, executor
        self.budget, self.grace, self.verify = budget, grace, verify
        self.items: list[dict] = []

    def prepare(self, todo):
        self.items = [s.item(self.budget) for s in todo]
        return None

    def run(self, todo, on_start=None):
        tasks = self.executor.run_tasks(self.factory, compare_task, self.items, fresh=True,
                                        timeout=_timeout(self.budget, self.grace), verify=self.verify)
        with contextlib.closing(tasks):  # closing the generator cancels the rest on an exception
            for i, res in tasks:
                if isinstance(res, _Raise) and not isinstance(res.exception, BudgetExceededError):
                    raise res.exception
                if isinstance(res, (_Raise, TaskFailed)):
                    failure = res.exception if isinstance(res, _Raise) else res
                    yield i, failure_row(self.objective, todo[i], failure, self.budget, self.grace, lost=True), []
                else:
                    yield (i, *_checked(self.objective, res["row"], res["trace"]))

    def warm_ups(self):
        return self.executor.worker_warm_ups() if hasattr(self.executor, "worker_warm_ups") else []


def prepare_neighbourhoods(objective) -> float:
    """Prepare ``objective``'s neighbourhood (``prepare()``,
    :func:`~arraysel.objective.neighbours.neighbourhood_of`) before a run's budget starts, or say
    once in the log that its searches run without one (in the process that builds the objective:
    the runs forked from it, or run in it, then say nothing again); returns the seconds it took."""
    from arraysel.selectors.capabilities import say_without

    t0 = time.perf_counter()
    nb = neighbourhood_of(objective)
    if nb is None:
        say_without(objective, "neighbourhood")
    else:
        nb.prepare()
    return time.perf_counter() - t0


@dataclasses.dataclass(frozen=True)
class PreparedForNeighbourhoods(WorkerFactory):
    """The objective of ``inner`` (a worker factory), prepared for one-swap neighbourhoods
    (:func:`prepare_neighbourhoods`) as it is built on a worker, so
    that no run's budget pays for it."""

    inner: object

    def __call__(self):
        objective = self.inner()
        prepare_neighbourhoods(objective)
        return objective


def scores_neighbourhoods(spec: RunSpec) -> bool:
    """Whether the run ``spec`` scores one-swap neighbourhoods: its selector says so
    (``scores_neighbourhoods``) or it is polished by a swap search (option ``polish``)."""
    return bool(getattr(spec.selector, "scores_neighbourhoods", False)) or \
        float(spec.options.get("polish") or 0) > 0


def make_runner(objective, budget: Budget, grace: float, full_mean: float, *, executor=None, objective_factory=None,
                isolate: bool = False, threads: int | None = None, progress: bool | None = False,
                neighbourhoods: bool = False) -> Runner:
    """The runner of a comparison: on ``executor`` (unless it runs in this process), else isolated
    child processes (``isolate``), else this process. A run that scores one-swap neighbourhoods
    (:func:`scores_neighbourhoods`) gets an objective prepared for them
    (:func:`prepare_neighbourhoods`) before its clock starts: here
    by :meth:`InProcessRunner.prepare`, on workers by the recipe :class:`PreparedForNeighbourhoods`
    when ``neighbourhoods`` (some run of the comparison scores them)."""
    remote = executor is not None and not getattr(executor, "in_process", False)
    if not remote and not isolate:
        return InProcessRunner(objective, budget, grace, full_mean, progress, threads)
    factory = objective_factory if objective_factory is not None else objective_factory_for(objective)
    if neighbourhoods:
        factory = PreparedForNeighbourhoods(factory)
    # the children load the cache entries this process has just loaded and checked: sizes suffice
    verify = "size" if objective_factory is None else None
    if remote:
        return ExecutorRunner(objective, factory, executor, budget, grace, verify)
    return IsolatedRunner(objective, factory, budget, grace, threads, verify)


def check_isolated(todo: list[RunSpec]) -> None:
    """Refuse (:class:`ParameterError` naming the selector and ``--in-process``) a run whose
    selector class can reach another process neither pickled by name nor through the plugin that
    registered it (:func:`~arraysel.run.compare_task.compare_item`)."""
    for spec in {s.config: s for s in todo}.values():
        spec.item(Budget(evaluations=1))


#: the objective's counters (they change with every call; ``fallbacks``: masks its fast path
#: handed to the exact one)
_COUNTERS = ("evaluations", "gradient_steps", "seconds", "fallbacks")


class _Fingerprint:
    """What a run in this process must leave as it found it: the objective's attributes and the
    methods of its class and of :class:`~arraysel.selectors.contract.BudgetedObjective` (by
    identity: a replaced or wrapped ``evaluate`` shows), and the full array's Mean (an attribute
    edited in place, such as ``metric_kw["r_main"]``, shows there)."""

    def __init__(self, objective, full_mean: float):
        self.objective = objective
        self.full_mean = float(full_mean)
        self.ids = self._ids()

    def _ids(self) -> dict:
        from arraysel.selectors.contract import BudgetedObjective

        out = {}
        try:
            own = vars(self.objective)
        except TypeError:  # an objective without a __dict__ (slots)
            own = {}
        for where, mapping in (("objective", own),
                               ("its class", vars(type(self.objective))),
                               ("BudgetedObjective", vars(BudgetedObjective))):
            for key, value in mapping.items():
                if where == "objective" and key in _COUNTERS:
                    continue
                scalar = value is None or isinstance(value, (bool, int, float, str))
                out[(where, key)] = ("value", value) if scalar else ("id", id(value))
        return out

    def changed(self) -> str:
        """'' when nothing changed, else what did (one phrase)."""
        now = self._ids()
        keys = sorted(k for k in set(now) | set(self.ids) if now.get(k) != self.ids.get(k))
        if keys:
            where, key = keys[0]
            return f"{key!r} of {where} was replaced, added or removed"
        want = self.full_mean
        if not math.isfinite(want):
            return ""
        n = int(self.objective.n_elements)
        try:
            out = self.objective.evaluate(indices_to_mask(list(range(n)), n)[None])
            got = float(np.asarray(out["Mean"], dtype=np.float64).reshape(-1)[0])
        except Exception as exc:
            return f"scoring the full array now fails ({_error_text(exc)})"
        if got == want or abs(got - want) <= 1e-9 * abs(want):
            return ""
        return f"the full array's Mean was {want:.6g} before it and is {got:.6g} after it"
