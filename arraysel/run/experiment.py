"""Run selectors on an objective and compare them.

An :class:`Experiment` is (objective, selector, options, budget, seed);
:meth:`Experiment.run` returns one flat row with the fixed columns
:data:`ROW_COLUMNS` and never dies because of the selector: an exception
raised by the selector (or the objective it calls), or an invalid selection,
lands in the row's ``error`` column. It *does* raise
:class:`~arraysel.selectors.contract.BudgetExceededError` when the selector used more
objective evaluations than its budget plus one batch.

:func:`compare` runs every selector for every seed, adds the ``full``
reference row and writes, atomically and after each finished run, the
files described in ``docs/selectors.md`` (``runs.csv``, ``table1.csv``,
``trace.csv``, the IOHprofiler files under ``ioh/``, ``run.json``, then the figures).

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
"""
from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import json
import math
import os
import platform
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from arraysel.errors import ParameterError, check_number
from arraysel.objective.metrics import METRIC_NAMES
from arraysel.errors import SelectionError
from arraysel.selectors.contract import (Budget, BudgetedObjective, BudgetExceededError, BudgetExhausted, Recorder, Selector,
                       check_selection, indices_to_mask, is_legacy_selector, numpy_rng)

__all__ = [
    "METRICS", "ROW_COLUMNS", "TRACE_COLUMNS", "DEFAULT_SEEDS", "Experiment", "full_row",
    "config_label", "compare", "check_out_dir", "check_resume", "remove_results", "RESULT_FILES",
]

METRICS = METRIC_NAMES
#: columns of a run row, in this order
ROW_COLUMNS = ("config", "selector", "seed", "k", "n_elements", *METRICS, "seconds", "evaluations",
               "gradient_steps", "objective_seconds", "overhead_seconds", "elements", "options", "error")
#: columns of ``trace.csv``: one ``improvement`` row per new best, then one ``end`` row at the
#: run's last evaluation and time
TRACE_COLUMNS = ("config", "seed", "seconds", "evaluations", "gradient_steps", "best_Mean", "event")


def config_label(name: str, options: dict | None = None) -> str:
    """``name`` or ``name(key=value,...)`` for non-default options."""
    if not options:
        return name
    inner = ",".join(f"{k}={options[k]}" for k in sorted(options))
    return f"{name}({inner})"


def _fmt_elements(sel: Iterable[int] | None) -> str:
    return "" if not sel else " ".join(str(int(i)) for i in sel)


def _error_text(exc: BaseException) -> str:
    text = str(exc).strip().replace("\n", " ")
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _counters(objective) -> tuple[int, int, float]:
    return int(objective.evaluations), int(objective.gradient_steps), float(objective.seconds)


def _final_metrics(objective, selection: list[int]) -> dict[str, float]:
    """Headline metrics, then a several-point scene's per-point breakdown (``objective.breakdown_names``)."""
    mask = indices_to_mask(selection, int(objective.n_elements))[None, :]
    out = objective.evaluate(mask)
    names = METRICS + tuple(getattr(objective, "breakdown_names", ()))
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
        selector's plan, gradient steps, best Mean so far) on stderr

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
    progress: bool = False
    trace: list = dataclasses.field(default_factory=list, init=False)
    selection: list | None = dataclasses.field(default=None, init=False)

    def run(self) -> dict:
        """Run the selector once; return a row with the keys :data:`ROW_COLUMNS`."""
        obj = self.objective
        cls = _resolve(self.selector, self.registry)
        selector = cls(**self.options)
        n = int(obj.n_elements)
        k = int(obj.k if self.k is None else self.k)
        check_number("k", k, lo=1, hi=n, integer=True)
        seed = int(check_number("seed", self.seed, lo=0, integer=True))
        config = self.config or config_label(cls.name, self.options)

        e0, g0, s0 = _counters(obj)
        budget = self.budget.fresh().start(obj)
        recorder = Recorder(obj, budget)
        error = ""
        selection = None
        t0 = time.perf_counter()
        watch = _RunProgress(config, budget, recorder, selector.planned_evaluations(n, k)) if self.progress \
            else contextlib.nullcontext()
        polish = float(selector.options.get("polish") or 0.0)
        try:
            with watch:
                stage = _share_of(budget, obj, 1.0 - polish) if polish > 0 else budget
                result = _run_selector(selector, obj, k, stage, seed, recorder)
                if polish > 0:
                    result = _polish(obj, k, budget, seed, recorder, check_selection(result, n, k))
            selection = check_selection(result, n, k)
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
        if not error and is_legacy_selector(selector):
            error = _check_reported(obj, recorder, selection, metrics)
        self.selection = selection
        self.trace = [dict(r) for r in recorder.rows]
        obj_seconds = s1 - s0
        extra = _breakdown(metrics)
        return {
            "config": config, "selector": cls.name, "seed": seed, "k": k, "n_elements": n,
            **metrics,
            "seconds": wall, "evaluations": used, "gradient_steps": g1 - g0,
            "objective_seconds": obj_seconds, "overhead_seconds": max(0.0, wall - obj_seconds),
            "elements": _fmt_elements(selection),
            "options": json.dumps(self.options, sort_keys=True, default=str) if self.options else "",
            "error": error, **extra,
        }


_WARNED_LEGACY: set = set()


def _warn_legacy(cls) -> None:
    if cls in _WARNED_LEGACY:
        return
    _WARNED_LEGACY.add(cls)
    warnings.warn(
        f"selector {cls.name!r} ({cls.__module__}.{cls.__qualname__}) uses the legacy signature "
        f"select(objective, k, budget, seed, recorder); define select(self, objective, k, seed) instead and "
        f"drop the budget checks and recorder.report calls: the objective it receives counts, clips to "
        f"the budget and records the trace (see docs/selectors.md)", DeprecationWarning, stacklevel=3)


def _run_selector(selector, obj, k: int, budget: Budget, seed: int, recorder: Recorder):
    """Call ``selector.select`` under either contract; return what it returned (or, when the
    budget ended the search, the best selection recorded)."""
    if is_legacy_selector(selector):
        _warn_legacy(type(selector))
        return selector.select(obj, k, budget, seed, recorder)
    view = BudgetedObjective(obj, budget, recorder, k)
    try:
        return selector.select(view, k, seed)
    except BudgetExhausted:
        return _best_or_first(recorder)


def _check_reported(obj, recorder: Recorder, selection, metrics: dict) -> str:
    """A legacy plugin reports its own scores (``recorder.report``): check its best one against
    the objective (the new contract records what the objective returns, nothing to check).
    Returns an error text when they differ by more than float32 rounding, else ''."""
    if recorder.best is None or not math.isfinite(recorder.best_mean):
        return ""
    best = list(recorder.best)
    try:
        true = metrics["Mean"] if selection is not None and best == list(selection) else \
            _final_metrics(obj, best)["Mean"]
    except Exception as exc:  # a reported selection the objective cannot score
        return f"the plugin reported Mean {recorder.best_mean:.6g} for elements {best}, which the objective " \
               f"cannot score: {_error_text(exc)}"
    if not math.isfinite(true) or abs(true - recorder.best_mean) > 1e-3 * abs(true) + 1e-6:
        return (f"the plugin reported Mean {recorder.best_mean:.6g} for elements {best}, the objective gives "
                f"{true:.6g}: its trace cannot be trusted")
    return ""


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


def _polish(obj, k: int, budget: Budget, seed: int, recorder: Recorder, start: list[int]) -> list[int]:
    """First-improvement swap local search from ``start`` with what is left of ``budget``."""
    from arraysel.selectors.localsearch import SwapSearch

    view = BudgetedObjective(obj, budget, recorder, k)
    search = SwapSearch(view, k, numpy_rng(seed, stream=7))
    try:
        search.run(start)
    except BudgetExhausted:
        pass
    best = recorder.best
    return list(best) if best is not None else start


class _RunProgress:
    """A tqdm bar for one run, refreshed from the budget's counters by a background thread
    (selectors need no code for it): evaluations (of the budget's, else of the selector's
    planned number), rate, gradient steps and the best Mean so far."""

    def __init__(self, label: str, budget: Budget, recorder: Recorder, planned: int | None,
                 interval: float = 0.5):
        self.label, self.budget, self.recorder = label, budget, recorder
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
                        dynamic_ncols=True)
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
    """The ``full`` reference row: every element active, evaluated once."""
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
        "elements": _fmt_elements(range(n)), "options": "", "error": error, **extra,
    }


def _lost_row(objective, config: str, name: str, options: dict, seed: int, message: str) -> dict:
    """The row of a run that could not be completed on any worker."""
    return _failed_row(objective, config, name, options, seed, f"run lost: {message}")


def _failed_row(objective, config: str, name: str, options: dict, seed: int, message: str) -> dict:
    """The row of a run that has no result, with ``message`` as its error."""
    nan = math.nan
    return {
        "config": config, "selector": name, "seed": seed, "k": int(objective.k),
        "n_elements": int(objective.n_elements), **{m: nan for m in METRICS},
        "seconds": nan, "evaluations": nan, "gradient_steps": nan, "objective_seconds": nan,
        "overhead_seconds": nan, "elements": "",
        "options": json.dumps(options, sort_keys=True, default=str) if options else "",
        "error": message,
    }


# ---------------------------------------------------------------------------
# compare: the output folder, resuming, isolation
# ---------------------------------------------------------------------------

#: files ``compare`` writes in its folder (``--force`` removes these and nothing else)
RESULT_FILES = ("runs.csv", "table1.csv", "trace.csv", "trace_nevergrad.csv", "ioh", "run.json", "masks.png",
                "psfs.png", "profiles.png", "trace.png", "anytime.png")
#: fields of ``run.json`` that a resumed run must share with the new one
RESUME_FIELDS = ("scene", "n_elements", "k", "dtype", "budget")


def check_out_dir(out: str | os.PathLike, *, resume: bool = False, force: bool = False) -> dict | None:
    """Check ``out`` before any work: a folder (or creatable), writable, and not holding the
    results of another compare run unless ``resume`` (continue it) or ``force`` (replace it).

    Returns the old ``run.json`` content when resuming (``None`` otherwise, or when there is
    nothing to resume). Raises :class:`ParameterError` with a one-line message."""
    out = Path(out)
    if resume and force:
        raise ParameterError("--resume and --force exclude each other: --resume continues the run in --out, "
                             "--force replaces it")
    if out.exists() and not out.is_dir():
        raise ParameterError(f"--out {str(out)!r} is a file, not a folder")
    from arraysel.io.atomic import check_writable
    check_writable(out / "run.json", "--out")
    held = [n for n in ("runs.csv", "run.json", "table1.csv") if (out / n).exists()]
    if not held:
        return None
    meta = None
    if (out / "run.json").exists():
        try:
            meta = json.loads((out / "run.json").read_bytes().decode("utf-8"))
            if not isinstance(meta, dict):
                raise ValueError("not a JSON object")
        except (OSError, ValueError) as exc:
            if resume:
                raise ParameterError(f"--resume: {out / 'run.json'} is damaged ({_error_text(exc)}); rerun "
                                     f"with --force to start over, or choose another --out") from None
            meta = None
    if resume:
        if meta is None:
            raise ParameterError(f"--resume: {out} has no run.json describing its runs; rerun with --force to "
                                 f"start over, or choose another --out")
        return meta
    if force:
        return None
    status = (meta or {}).get("status", "unknown")
    raise ParameterError(f"--out {str(out)!r} already holds the results of a compare run (status: {status}); "
                         f"rerun with --resume to finish it, with --force to replace it, or choose another --out")


def _plain(value):
    """``value`` as ``run.json`` stores it (JSON round trip, ``default=str``)."""
    return json.loads(json.dumps(value, default=str))


def check_resume(old: dict, now: dict, out) -> None:
    """Refuse to resume when a field of :data:`RESUME_FIELDS` differs between ``old`` (run.json)
    and ``now``; the message names the field and both values (the first differing key of a
    scene)."""
    for field in RESUME_FIELDS:
        if field not in now:
            continue
        a, b = old.get(field), _plain(now[field])
        if a == b:
            continue
        detail = f"{a!r} in run.json, {b!r} now"
        if isinstance(a, dict) and isinstance(b, dict):
            keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
            if keys:
                detail = f"{field}.{keys[0]} is {a.get(keys[0])!r} in run.json, {b.get(keys[0])!r} now"
        raise ParameterError(f"--resume: the runs in {out} were made with a different {field} ({detail}); "
                             f"rerun with --force to start over, or choose another --out")


def remove_results(out: str | os.PathLike) -> None:
    """Remove the files of :data:`RESULT_FILES` from ``out`` (``--force``)."""
    import shutil

    for name in RESULT_FILES:
        path = Path(out) / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
            continue
        try:
            path.unlink()
        except FileNotFoundError:
            pass


def _make_isolator(objective, objective_factory, todo, classes):
    """An :class:`~arraysel.run.executors.IsolatedWorker` for the local runs, and the configs whose
    selector class cannot be sent to it (they run in this process)."""
    from arraysel.run import executors as _ex

    factory = objective_factory if objective_factory is not None else _ex.objective_factory_for(objective)
    in_process = set()
    for lab, name, opts, _seed in todo:
        try:
            _ex.compare_item(lab, classes[name], opts, Budget(evaluations=1), 0)
        except ParameterError as exc:
            print(f"arraysel compare: {lab} runs in this process, not isolated: {exc}", file=sys.stderr)
            in_process.add(lab)
    return _ex.IsolatedWorker(factory), in_process


def _run_isolated(isolator, objective, lab, cls, opts, budget, seed, grace) -> tuple[dict, list]:
    from arraysel.run import executors as _ex

    item = _ex.compare_item(lab, cls, opts, budget, seed)
    timeout = None if budget.seconds is None else budget.seconds + grace
    res = isolator.run(_ex.compare_task, item, timeout)
    if isinstance(res, _ex._Raise):
        if isinstance(res.exception, BudgetExceededError):
            return _failed_row(objective, lab, cls.name, opts, seed, _error_text(res.exception)), []
        raise res.exception
    if isinstance(res, _ex.TaskFailed):
        msg = res.message
        if msg.startswith("stopped after"):
            msg = (f"BudgetExceededError: {msg}; the budget was {budget.seconds:g} s and the grace "
                   f"period {grace:g} s")
        return _failed_row(objective, lab, cls.name, opts, seed, f"run failed: {msg}"), []
    return res["row"], res["trace"]


# ---------------------------------------------------------------------------
# compare
# ---------------------------------------------------------------------------

def _versions() -> dict:
    import numpy
    import torch

    from arraysel import __version__
    out = {"arraysel": __version__, "torch": torch.__version__, "numpy": numpy.__version__,
           "python": platform.python_version()}
    for mod in ("pluggy", "pandas", "matplotlib", "nlopt"):
        try:
            m = __import__(mod)
            out[mod] = getattr(m, "__version__", "unknown")
        except Exception:  # optional: absent or broken
            out[mod] = None
    return out


def _scene_info(objective) -> tuple[str, Any]:
    scene = getattr(objective, "scene", None)
    name = getattr(scene, "name", None)
    try:
        data = scene.to_dict() if scene is not None else None
    except Exception as exc:  # a scene that cannot describe itself must not stop the run
        data = {"error": _error_text(exc)}
    return name, data


def _normalise_selectors(selectors) -> list[tuple[str, dict]]:
    out = []
    for s in selectors:
        if isinstance(s, str):
            out.append((s, {}))
        else:
            name, opts = s
            out.append((name, dict(opts or {})))
    return out


#: seeds of a stochastic selector when ``compare`` is given none (a deterministic one runs with the first)
DEFAULT_SEEDS = (0, 1, 2, 3, 4)


def compare(objective, selectors: Sequence, *, out_dir: str | os.PathLike, seeds: Sequence[int] | None = None,
            budget: Budget | None = None, registry=None, resume: bool = False, progress: bool = True,
            figures: bool = True, command_line: Sequence[str] | None = None,
            info: dict | None = None, executor=None, objective_factory=None, force: bool = False,
            isolate: bool = False, grace_s: float | None = None):
    """Run each selector for each seed on ``objective``; write the report to ``out_dir``.

    Parameters
    ----------
    objective : object following the Objective contract (built by the caller)
    selectors : names, or ``(name, options)`` pairs
    out_dir : output folder (created)
    seeds : seeds; each selector runs once per seed. ``None`` (default): the
        :data:`DEFAULT_SEEDS` for stochastic selectors, and only the first of
        them for selectors whose ``deterministic`` flag says the seed does not matter
    budget : per-run limits (default: 120 s)
    registry : selector registry (default: the process-wide one)
    resume : keep the finished, error-free runs found in ``out_dir/runs.csv`` and run the rest
    progress : show a tqdm progress bar on stderr
    figures : write the PNG figures at the end
    command_line : recorded in ``run.json``
    info : extra entries for ``run.json``
    executor : an :class:`arraysel.run.executors.Executor` that runs the
        ``(selector, seed)`` runs (default: in this process, one after another).
        With a process pool or Dask, each worker builds its own objective from
        ``objective_factory``; the rows and traces are written in the same,
        deterministic order as a local run (the order of ``selectors`` x
        ``seeds``). A run whose worker kept dying gets its message in the
        ``error`` column and the others finish.
    objective_factory : picklable callable that builds the objective on a
        worker (default: :func:`arraysel.run.executors.objective_factory_for`)
    force : replace the results already in ``out_dir`` (without it, a folder that holds
        results of a compare run is refused unless ``resume``)
    isolate : run each ``(selector, seed)`` in a child process (built from ``objective_factory``)
        that is stopped ``grace_s`` seconds after its time budget: a selector that hangs, exits
        the process (``sys.exit``) or crashes it gets an error row and the other runs go on.
        A selector class that cannot be sent to a child process runs in this process.
    grace_s : seconds past the time budget before an isolated run is stopped (default
        :data:`arraysel.run.executors.DEFAULT_GRACE_S`)

    Returns
    -------
    pandas.DataFrame : the ``table1.csv`` table

    ``resume`` refuses (:class:`~arraysel.errors.ParameterError` naming the field) when the
    scene, ``k``, the number of elements, the dtype or the budget differ from ``run.json``;
    it may add seeds and selector configurations (``run.json`` then lists all of them). A
    run that exceeds its evaluation budget gets an error row (``BudgetExceededError``). The
    ``error_rows`` entry of ``run.json`` counts the rows with an error.

    On Ctrl-C (``KeyboardInterrupt``) or an error raised by a run, every
    finished row is already on disk; a message on stderr says how to resume,
    and the exception is re-raised.
    """
    import pandas as pd
    from tqdm.auto import tqdm

    from arraysel.report import tables as reporting
    from arraysel.selectors.registry import get_registry

    registry = get_registry() if registry is None else registry
    budget = Budget(seconds=120.0) if budget is None else budget
    sels = _normalise_selectors(selectors)
    default_seeds = seeds is None
    seeds = [int(check_number("seed", s, lo=0, integer=True)) for s in (DEFAULT_SEEDS if seeds is None else seeds)]
    if not sels:
        raise ParameterError("compare needs at least one selector")
    classes = {}
    for name, opts in sels:
        cls = registry[name]
        cls(**opts)  # validate options before anything runs
        classes[name] = cls
    labels = [config_label(name, opts) for name, opts in sels]
    if len(set(labels)) != len(labels):
        raise ParameterError(f"the same selector configuration is listed twice: {labels}")

    if budget.seconds is not None and not math.isfinite(budget.seconds):
        raise ParameterError(f"budget seconds = {budget.seconds} is not allowed; give a finite number of "
                             f"seconds > 0, or None with an evaluation budget")
    from arraysel.run.executors import DEFAULT_GRACE_S
    grace = DEFAULT_GRACE_S if grace_s is None else float(check_number("grace_s", grace_s, lo=0, hi=1e6))

    out = Path(out_dir)
    old_meta = check_out_dir(out, resume=resume, force=force)
    scene_name, scene_dict = _scene_info(objective)
    if old_meta is not None:
        check_resume(old_meta, {"scene": scene_dict, "n_elements": int(objective.n_elements),
                                "k": int(objective.k), "dtype": str(getattr(objective, "dtype", "")),
                                "budget": budget.to_dict()}, out)
    if force:
        remove_results(out)
    out.mkdir(parents=True, exist_ok=True)
    runs_path = out / "runs.csv"

    rows: list[dict] = []
    traces: list[dict] = []
    done: set[tuple[str, int]] = set()
    if resume and runs_path.exists():
        try:
            old = pd.read_csv(runs_path)
            missing = [c for c in ("config", "seed", "error", "options") if c not in old.columns]
            if missing:
                raise ValueError(f"no column(s) {missing}")
        except (ValueError, UnicodeDecodeError, pd.errors.ParserError) as exc:
            raise ParameterError(f"--resume: {runs_path} is damaged ({_error_text(exc)}); rerun with --force "
                                 f"to start over, or choose another --out") from None
        for rec in old.to_dict("records"):
            err = rec.get("error")
            if rec["config"] == "full" or (isinstance(err, str) and err.strip()):
                continue
            rec["seed"] = int(rec["seed"])
            rec["error"] = ""
            rec["options"] = rec["options"] if isinstance(rec.get("options"), str) else ""
            rows.append({**{c: rec.get(c, "") for c in ROW_COLUMNS},  # and a scene's per-point columns
                         **{c: v for c, v in rec.items() if c not in ROW_COLUMNS}})
            done.add((rec["config"], rec["seed"]))
        tpath = out / "trace.csv"
        if tpath.exists():
            try:
                t = pd.read_csv(tpath)
                traces = [r for r in t.to_dict("records") if (r["config"], int(r["seed"])) in done]
            except (ValueError, KeyError, UnicodeDecodeError, pd.errors.ParserError) as exc:
                raise ParameterError(f"--resume: {tpath} is damaged ({_error_text(exc)}); rerun with --force "
                                     f"to start over, or choose another --out") from None

    sel_meta = [{"config": lab, "selector": n, "options": o, "origin": registry.origin(n)}
                for lab, (n, o) in zip(labels, sels)]
    all_seeds = list(seeds)
    if old_meta is not None:  # a resumed run lists what it holds: the old runs and the new ones
        known = {d["config"] for d in sel_meta}
        sel_meta = [d for d in old_meta.get("selectors", []) if d.get("config") not in known] + sel_meta
        all_seeds = sorted(set(all_seeds) | {int(v) for v in old_meta.get("seeds", [])})
    meta = {
        "status": "running",
        "started": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "command_line": list(command_line) if command_line is not None else list(sys.argv),
        "scene_name": scene_name, "scene": scene_dict,
        "n_elements": int(objective.n_elements), "k": int(objective.k),
        "device": str(getattr(objective, "device", "")), "dtype": str(getattr(objective, "dtype", "")),
        "seeds": all_seeds, "budget": budget.to_dict(), "selectors": sel_meta,
        "versions": _versions(), "cpu_count": os.cpu_count(),
        "executor": executor.describe() if executor is not None else {"executor": "local", "workers": 1},
        **(info or {}),
    }
    reporting.write_json(out / "run.json", meta)

    full = full_row(objective)

    def save():
        reporting.write_runs(out, [full] + rows, traces, budget, problem=scene_name or "arraysel")

    def seeds_of(name):
        return seeds[:1] if default_seeds and classes[name].deterministic else seeds

    todo = [(lab, name, opts, seed) for lab, (name, opts) in zip(labels, sels) for seed in seeds_of(name)
            if (lab, seed) not in done]
    remote = executor is not None and not getattr(executor, "in_process", False)
    if remote:
        from arraysel.run import executors as _ex
        factory = objective_factory if objective_factory is not None else _ex.objective_factory_for(objective)
        items = [_ex.compare_item(lab, classes[name], opts, budget, seed) for lab, name, opts, seed in todo]
    isolator, in_process = None, set()
    if isolate and not remote and todo:
        isolator, in_process = _make_isolator(objective, objective_factory, todo, classes)
    save()
    bar = tqdm(total=len(todo), disable=not progress, desc="compare", unit="run", file=sys.stderr)
    finished = 0
    try:
        if not remote:
            for lab, name, opts, seed in todo:
                bar.set_postfix_str(f"{lab} seed {seed}")
                if isolator is not None and lab not in in_process:
                    row, trace = _run_isolated(isolator, objective, lab, classes[name], opts, budget, seed, grace)
                else:
                    exp = Experiment(objective, classes[name], options=opts, budget=budget, seed=seed,
                                     config=lab, progress=progress)
                    try:
                        row, trace = exp.run(), exp.trace
                    except BudgetExceededError as exc:
                        row, trace = _failed_row(objective, lab, classes[name].name, opts, seed,
                                                 _error_text(exc)), []
                rows.append(row)
                traces.extend({"config": lab, "seed": seed, **t} for t in trace)
                save()
                finished += 1
                bar.update(1)
        else:
            # results arrive in any order; rows and traces are kept in the order of `todo`
            kept_rows, kept_traces = list(rows), list(traces)
            results: dict[int, tuple[dict, list]] = {}
            with contextlib.closing(executor.run_tasks(factory, _ex.compare_task, items)) as tasks:
                for i, res in tasks:  # closing the generator cancels the rest on an exception
                    lab, name, opts, seed = todo[i]
                    if isinstance(res, _ex._Raise) and isinstance(res.exception, BudgetExceededError):
                        res = _ex.TaskFailed(_error_text(res.exception))
                    if isinstance(res, _ex._Raise):
                        raise res.exception
                    if isinstance(res, _ex.TaskFailed):
                        row, trace = _lost_row(objective, lab, classes[name].name, opts, seed, res.message), []
                    else:
                        row, trace = res["row"], res["trace"]
                    results[i] = (row, [{"config": lab, "seed": seed, **t} for t in trace])
                    rows[:] = kept_rows + [results[j][0] for j in sorted(results)]
                    traces[:] = kept_traces + [t for j in sorted(results) for t in results[j][1]]
                    save()
                    finished += 1
                    bar.set_postfix_str(f"{lab} seed {seed}")
                    bar.update(1)
    except BaseException as exc:
        bar.close()
        if isolator is not None:
            isolator.close()
        left = len(todo) - finished
        meta["status"] = "interrupted" if isinstance(exc, KeyboardInterrupt) else f"failed: {_error_text(exc)}"
        meta["finished"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        reporting.write_json(out / "run.json", meta)
        what = "interrupted" if isinstance(exc, KeyboardInterrupt) else f"stopped by {_error_text(exc)}"
        print(f"arraysel compare {what}: {len(rows)} finished run(s) are saved in {out}/runs.csv "
              f"and {out}/table1.csv; {left} run(s) left. Rerun the same command with --resume "
              f"to run only those.", file=sys.stderr)
        raise
    bar.close()
    if isolator is not None:
        isolator.close()

    table = reporting.table1(pd.DataFrame([full] + rows, columns=list(ROW_COLUMNS)))
    if figures:
        meta["figure_errors"] = reporting.make_figures(objective, table, pd.DataFrame(traces), out)
    failed = [f"{r['config']} seed {r['seed']}" for r in [full] + rows if str(r.get("error") or "").strip()]
    meta["error_rows"] = len(failed)
    meta["failed_runs"] = failed
    meta["status"] = "finished"
    meta["finished"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    reporting.write_json(out / "run.json", meta)
    return table
