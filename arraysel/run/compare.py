"""``compare``: run every selector for every seed on one objective and write the report.

It adds the ``full`` reference row, makes the runs with a runner (:mod:`arraysel.run.runners`:
one after another in this process, each in a fresh child process, or on an executor, again each
in a fresh process, so a plugin cannot change another run's numbers) and writes, through its store
(:class:`arraysel.run.store.CompareStore`, atomically, after each finished run), the files described
in ``docs/selectors.md`` (``runs.csv``, ``table1.csv``, ``stats.csv``, ``trace.csv``, the
IOHprofiler files under ``ioh/``, ``run.json``, then the figures). It returns a
:class:`CompareResult`. The folder is locked for the whole run
(:func:`arraysel.run.outdir.lock_out_dir`); each save writes the traces before the rows that name
them, so a run killed at any point and resumed lists every run in ``runs.csv`` with its trace.

A run's selection stays a :class:`~arraysel.selection.Selection` from the selector's run to the
store (its text is formed there, :func:`arraysel.run.store.file_row`) and to the figures.
"""
from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import math
import os
import platform
import sys
from pathlib import Path
from typing import Any, Sequence

from arraysel.errors import ArrayselError, ParameterError, check_number, error_text as _error_text
from arraysel.objective.contract import missing_members, objective_info
from arraysel.report import tables as reporting
from arraysel.run.experiment import budget_flag, config_label, full_row, with_end_row
from arraysel.run.isolation import DEFAULT_GRACE_S, UNTIMED_LIMIT_S
from arraysel.run.outdir import check_out_dir, check_resume, lock_out_dir
from arraysel.run.runners import Runner, RunSpec, check_isolated, make_runner, scores_neighbourhoods
from arraysel.run.sector_report import beam_source, prepare_beam_polish
from arraysel.run.store import CompareStore, write_figures
from arraysel.selection import Selection
from arraysel.selectors.contract import Budget

__all__ = ["DEFAULT_SEEDS", "CompareResult", "compare", "write_figures"]


@dataclasses.dataclass(frozen=True)
class CompareResult:
    """What :func:`compare` returns: the tables it wrote and the selections it made.

    table : ``table1.csv`` (one row per configuration, ``full`` first: the metrics of its listed
        selection, the run with the best Mean over its seeds)
    runs : ``runs.csv`` (one row per (configuration, seed) run; text columns as text, ``seed`` whole
        numbers, :func:`arraysel.report.tables.typed_runs`)
    trace : ``trace.csv`` (improvements of the best Mean over time)
    stats : ``stats.csv`` (one row per configuration: the statistics of its Means over seeds)
    selections : configuration -> the :class:`~arraysel.selection.Selection` ``table`` lists
        (``full`` included; an empty one when no run of it has a selection)
    run_selections : ``(configuration, seed)`` -> the run's :class:`~arraysel.selection.Selection`
        (runs without one left out)
    failures : the runs with an error, ``"<config> seed <seed>"`` (``run.json``'s ``failed_runs``)
    out_dir : the folder that holds the files
    figures : name -> matplotlib Figure, where the caller collected them (:func:`arraysel.api.compare`)
    figure_errors : the figures that could not be drawn, and why
    """

    table: Any
    runs: Any
    trace: Any
    stats: Any
    selections: dict
    run_selections: dict
    failures: tuple
    out_dir: str
    figures: dict = dataclasses.field(default_factory=dict)
    figure_errors: tuple = ()

    def _repr_html_(self) -> str:  # a notebook shows the table
        return self.table._repr_html_()




#: seeds of a stochastic selector when ``compare`` is given none (a deterministic one runs with the first)
DEFAULT_SEEDS = (0, 1, 2, 3, 4)


@dataclasses.dataclass(frozen=True)
class _Plan:
    """What :func:`compare` was asked to run, checked."""

    sels: list          # (name, options) per configuration
    labels: list        # their config labels
    classes: dict       # name -> selector class
    seeds: list
    budget: Budget
    grace: float
    registry: Any

    @classmethod
    def of(cls, selectors, seeds, budget, registry, grace_s) -> "_Plan":
        from arraysel.selectors.registry import get_registry

        registry = get_registry() if registry is None else registry
        budget = Budget(seconds=120.0) if budget is None else budget
        sels = _normalise_selectors(selectors)
        seeds = _checked_seeds(DEFAULT_SEEDS if seeds is None else seeds)
        if not sels:
            raise ParameterError("compare needs at least one selector")
        classes = {}
        for name, opts in sels:
            sel_cls = registry[name]
            sel_cls.check_available()  # its packages are installed (else the pip command)
            sel_cls(**opts)  # validate options before anything runs
            classes[name] = sel_cls
        labels = [config_label(name, opts) for name, opts in sels]
        if len(set(labels)) != len(labels):
            raise ParameterError(f"the same selector configuration is listed twice: {labels}")
        if budget.unlimited:
            raise ParameterError("the budget has no limit: give a time budget (budget_s, --budget-s) or an "
                                 "evaluation budget (budget_evals, --budget-evals)")
        if budget.seconds is not None and not math.isfinite(budget.seconds):
            raise ParameterError(f"budget seconds = {budget.seconds} is not allowed; give a finite number of "
                                 f"seconds > 0, or None with an evaluation budget")
        if grace_s is None:  # without a time budget, the grace period is the run's whole limit
            grace = DEFAULT_GRACE_S if budget.seconds is not None else UNTIMED_LIMIT_S
        else:
            grace = float(check_number("grace_s", grace_s, lo=0, hi=1e6))
        return cls(sels, labels, classes, seeds, budget, grace, registry)

    def todo(self, done: set) -> list[RunSpec]:
        """The runs to make: each configuration once per seed (a deterministic one with the first
        seed), less those ``done``."""
        return [RunSpec(lab, self.classes[name], opts, seed, self.origin(name))
                for lab, (name, opts) in zip(self.labels, self.sels)
                for seed in (self.seeds[:1] if self.classes[name].deterministic else self.seeds)
                if (lab, seed) not in done]

    def origin(self, name: str) -> str | None:
        """The registry's origin of the selector ``name`` (None when the registry cannot say)."""
        try:
            return self.registry.origin(name)
        except Exception:  # a registry of another kind
            return None

    def selectors_meta(self) -> list[dict]:
        return [{"config": lab, "selector": n, "options": o, "origin": self.registry.origin(n),
                 "deterministic": bool(self.classes[n].deterministic)}
                for lab, (n, o) in zip(self.labels, self.sels)]


def compare(objective, selectors: Sequence, *, out_dir: str | os.PathLike, seeds: Sequence[int] | None = None,
            budget: Budget | None = None, registry=None, resume: bool = False, progress: bool | None = True,
            figures: bool = True, command_line: Sequence[str] | None = None,
            info: dict | None = None, executor=None, objective_factory=None, force: bool = False,
            isolate: bool = False, grace_s: float | None = None, threads: int | None = None) -> CompareResult:
    """Run each selector for each seed on ``objective``; write the report to ``out_dir``.

    Parameters
    ----------
    objective : object following the Objective contract (built by the caller)
    selectors : names, or ``(name, options)`` pairs
    out_dir : output folder (created)
    seeds : seeds; each stochastic selector runs once per seed (``None``, the default:
        :data:`DEFAULT_SEEDS`); a selector whose ``deterministic`` flag says the seed does
        not matter runs once, with the first seed, whether the seeds are given or not
    budget : per-run limits (default: 120 s)
    registry : selector registry (default: the process-wide one)
    resume : keep the finished, error-free runs found in ``out_dir/runs.csv`` and run the rest
    progress : show tqdm progress bars on stderr (True), none (False), or only when stderr is a
        terminal (None, the command line's choice: a redirected log gets no carriage-return frames)
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
        worker (default: :func:`arraysel.run.workers.objective_factory_for`)
    force : replace the results already in ``out_dir`` (without it, a folder that holds
        results of a compare run is refused unless ``resume``)
    isolate : run each ``(selector, seed)`` in a child process (built from ``objective_factory``)
        that is stopped ``grace_s`` seconds after its time budget: a selector that hangs, exits
        the process (``sys.exit``) or crashes it gets an error row and the other runs go on.
        A selector class that can reach a child process neither pickled by name nor through the
        plugin that registered it is refused (:class:`~arraysel.errors.ParameterError`, before
        anything is written); run it with ``isolate=False``. Runs in this process are stopped at
        the same deadline (:mod:`arraysel.run.deadline`).
    grace_s : seconds past the time budget before a run is stopped (default
        :data:`arraysel.run.isolation.DEFAULT_GRACE_S`); without a time budget (an evaluation
        budget only), the seconds a run may take (default
        :data:`arraysel.run.isolation.UNTIMED_LIMIT_S`)
    threads : threads of each local run (torch, numba, BLAS): an isolated run's child has them;
        with ``isolate=False`` they are set in this process for each run (and its warm-up) and
        restored after it (default: an isolated run gets this process's torch threads, a run in
        this process the counts as they are); an executor sets its own (``threads=`` of
        :func:`arraysel.run.executors.make_executor`)

    Returns
    -------
    :class:`CompareResult` : the tables as written (``table1.csv``: each configuration's best run;
    ``stats.csv``: the statistics over seeds, :func:`arraysel.report.stats.stats_table`;
    ``runs.csv``; ``trace.csv``), each configuration's :class:`~arraysel.selection.Selection`, the
    failed runs and the folder

    ``resume`` refuses (:class:`~arraysel.errors.ParameterError` naming the field) when the
    scene, ``k``, the number of elements, the dtype or the budget differ from ``run.json``;
    it may add seeds and selector configurations (``run.json`` then lists all of them). A
    run that exceeds its evaluation budget gets an error row (``BudgetExceededError``). The
    ``error_rows`` entry of ``run.json`` counts the rows with an error.

    On Ctrl-C (``KeyboardInterrupt``) or an error raised by a run, every
    finished row is already on disk; a message on stderr says how to resume,
    and the exception is re-raised.
    """
    _check_objective(objective)
    plan = _Plan.of(selectors, seeds, budget, registry, grace_s)
    out = Path(out_dir)
    if resume and force:
        check_out_dir(out, resume=resume, force=force)  # refused before a folder is made
    with lock_out_dir(out):  # one compare at a time in a folder, for the whole run
        return _compare_locked(objective, out, plan, resume=resume, force=force, progress=progress, figures=figures,
                               command_line=command_line, info=info, executor=executor,
                               objective_factory=objective_factory, isolate=isolate, threads=threads)


def _compare_locked(objective, out: Path, plan: _Plan, *, resume, force, progress, figures, command_line, info,
                    executor, objective_factory, isolate, threads) -> CompareResult:
    """The body of :func:`compare`, once ``out`` is locked."""
    from tqdm.auto import tqdm

    old_meta = check_out_dir(out, resume=resume, force=force)
    scene_name, scene_dict = _scene_info(objective)
    if old_meta is not None:
        check_resume(old_meta, {"scene": scene_dict, "n_elements": int(objective.n_elements),
                                "k": int(objective.k), "dtype": _text(objective_info(objective).dtype),
                                "budget": plan.budget.to_dict()}, out)
    if isolate or (executor is not None and not getattr(executor, "in_process", False)):
        check_isolated(plan.todo(set()))  # refused before anything is written
    store = CompareStore(out, plan.budget, scene_name)
    store.start(force)
    rows, traces = store.previous(int(objective.n_elements)) if resume else ([], [])
    meta = _meta(objective, plan, old_meta, scene_name, scene_dict, command_line, info, executor)
    store.write_meta(meta)

    full = full_row(objective)
    todo = plan.todo({(r["config"], r["seed"]) for r in rows})
    runner = make_runner(objective, plan.budget, plan.grace, float(full.get("Mean", math.nan)), executor=executor,
                         objective_factory=objective_factory, isolate=isolate, threads=threads, progress=progress,
                         neighbourhoods=any(scores_neighbourhoods(s) for s in todo))
    fast_s = prepare_beam_polish(objective, todo)   # a sector scene's fast models, before any run's clock
    warm = runner.prepare(todo)
    if fast_s:
        meta["sector_fast_s"] = fast_s
    if warm is not None:  # runs made here: this process's objective warmed before the first clock starts
        meta["warm_up"] = warm
    store.save([full] + rows, traces)
    # progress None: on a terminal only (disable=None), a redirected log gets no carriage-return frames
    bar = tqdm(total=len(todo), disable=None if progress is None else not progress, desc="compare", unit="run",
               file=sys.stderr)
    results: dict[int, tuple[dict, list]] = {}
    try:
        _run_all(runner, todo, full, rows, traces, store, plan, bar, results)
    except BaseException as exc:
        bar.close()
        _close(runner, meta)
        _stopped(store, meta, exc, len(rows), len(todo) - len(results))
        raise
    bar.close()
    _close(runner, meta)
    return _finish(objective, store, meta, full, rows, traces, figures)


def _run_all(runner: Runner, todo: list[RunSpec], full: dict, rows: list, traces: list, store: CompareStore,
             plan: _Plan, bar, results: dict) -> None:
    """Make the runs of ``todo``; after each, its row and trace join ``rows`` and ``traces`` (in
    the order of ``todo``, after the runs kept from a resumed folder, whatever order they finish
    in) and the store saves them. ``results`` collects them by position."""
    kept_rows, kept_traces = list(rows), list(traces)
    with contextlib.closing(runner.run(todo, on_start=lambda s: bar.set_postfix_str(f"{s.config} seed {s.seed}"))
                            ) as runs:
        for i, row, trace in runs:
            spec = todo[i]
            row = {**row, "budget_flag": budget_flag(row, plan.budget, plan.grace)}
            results[i] = (row, [{"config": spec.config, "seed": spec.seed, **t} for t in with_end_row(row, trace)])
            rows[:] = kept_rows + [results[j][0] for j in sorted(results)]
            traces[:] = kept_traces + [t for j in sorted(results) for t in results[j][1]]
            store.save([full] + rows, traces)
            bar.set_postfix_str(f"{spec.config} seed {spec.seed}")
            bar.update(1)


def _close(runner: Runner, meta: dict) -> None:
    """End the runner's workers; ``run.json``'s ``worker_warm_ups``: each worker's one-off work
    (objective build, basis check, compiled code, plans), timed once per worker, never charged
    to a run."""
    runner.close()
    found = runner.warm_ups()
    if found:
        meta["worker_warm_ups"] = [{k: (round(v, 4) if isinstance(v, float) else v) for k, v in w.items()}
                                   for w in found]


def _stopped(store: CompareStore, meta: dict, exc: BaseException, saved: int, left: int) -> None:
    """``run.json`` and the message of a comparison stopped by ``exc`` (Ctrl-C or an error)."""
    out = store.out
    meta["status"] = "interrupted" if isinstance(exc, KeyboardInterrupt) else f"failed: {_error_text(exc)}"
    meta["finished"] = _now()
    try:
        store.write_meta(meta)
    except ArrayselError:  # a full disk: the error that stopped the comparison says so already
        pass
    what = "interrupted" if isinstance(exc, KeyboardInterrupt) else f"stopped by {_error_text(exc)}"
    print(f"arraysel compare {what}: {saved} finished run(s) are saved in {out}/runs.csv "
          f"and {out}/table1.csv; {left} run(s) left. Rerun the same command with --resume "
          f"to run only those.", file=sys.stderr)


def _finish(objective, store: CompareStore, meta: dict, full: dict, rows: list, traces: list,
            figures: bool) -> CompareResult:
    """The figures, the final ``run.json`` and the result."""
    import pandas as pd

    n = int(objective.n_elements)
    # each config's selection, from the run the table keeps
    selections = {config: row["elements"] if row.get("elements") is not None else Selection((), n)
                  for config, row in reporting.best_rows([full] + rows).items()}
    tables = store.tables
    if figures:
        meta["figure_errors"] = store.write_figures(objective, selections, tables.table, pd.DataFrame(traces))
    beams = beam_source(objective)
    if beams is not None:  # a sector scene, or a 1-D scene scored per beam: beams.csv, pareto.csv, pareto.png
        try:
            found = store.write_sector(beams, [full] + rows, figures)
        except Exception as exc:  # scoring on the points must never lose the tables
            found = [f"beams.csv/pareto.csv: {type(exc).__name__}: {exc}"]
        if found:
            meta["figure_errors"] = list(meta.get("figure_errors", [])) + found
    failed = [f"{r['config']} seed {r['seed']}" for r in [full] + rows if str(r.get("error") or "").strip()]
    meta["error_rows"] = len(failed)
    meta["failed_runs"] = failed
    meta["status"] = "finished"
    meta["finished"] = _now()
    store.write_meta(meta)
    return CompareResult(
        table=tables.table, runs=reporting.typed_runs(tables.runs), trace=tables.trace, stats=tables.stats,
        selections=selections, run_selections={(r["config"], r["seed"]): r["elements"] for r in rows
                                               if r.get("elements") is not None},
        failures=tuple(failed), out_dir=os.fspath(store.out), figure_errors=tuple(meta.get("figure_errors", ())))


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _meta(objective, plan: _Plan, old_meta, scene_name, scene_dict, command_line, info, executor) -> dict:
    """``run.json`` as a comparison starts (a resumed run lists what it holds: the old runs and the new ones)."""
    sel_meta = plan.selectors_meta()
    all_seeds = list(plan.seeds)
    if old_meta is not None:
        known = {d["config"] for d in sel_meta}
        sel_meta = [d for d in old_meta.get("selectors", []) if d.get("config") not in known] + sel_meta
        all_seeds = sorted(set(all_seeds) | {int(v) for v in old_meta.get("seeds", [])})
    return {
        "status": "running", "started": _now(),
        "command_line": list(command_line) if command_line is not None else list(sys.argv),
        "scene_name": scene_name, "scene": scene_dict,
        "n_elements": int(objective.n_elements), "k": int(objective.k),
        **({"aperture_events": objective_info(objective).aperture_events}
           if objective_info(objective).aperture_mode == "per-transmit" else {}),
        "device": _text(objective_info(objective).device), "dtype": _text(objective_info(objective).dtype),
        "seeds": all_seeds, "budget": plan.budget.to_dict(), "selectors": sel_meta,
        "versions": _versions(), "cpu_count": os.cpu_count(),
        "executor": executor.describe() if executor is not None else {"executor": "local", "workers": 1},
        **(info or {}),
    }


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


def _text(value) -> str:
    """An objective's ``device`` or ``dtype`` as run.json writes it ("" when it says none)."""
    return "" if value is None else str(value)


def _scene_info(objective) -> tuple[str, Any]:
    info = objective_info(objective)
    scene, name = info.scene, info.scene_name
    try:
        data = scene.to_dict() if scene is not None else None
    except Exception as exc:  # a scene that cannot describe itself must not stop the run
        data = {"error": _error_text(exc)}
    return name, data


def _normalise_selectors(selectors) -> list[tuple[str, dict]]:
    """``[(name, options)]`` of ``selectors``: names, ``(name, options)`` pairs, or one string of
    comma-separated names (as ``--selectors`` takes them)."""
    if isinstance(selectors, str):
        selectors = [s.strip() for s in selectors.split(",") if s.strip()]
    if isinstance(selectors, (bytes, dict)) or not hasattr(selectors, "__iter__"):
        raise ParameterError(f"selectors must be a list of selector names or (name, options) pairs, got "
                             f"{type(selectors).__name__}")
    out = []
    for s in selectors:
        if isinstance(s, str):
            out.append((s, {}))
        elif isinstance(s, (tuple, list)) and len(s) == 2 and isinstance(s[1], (dict, type(None))):
            out.append((s[0], dict(s[1] or {})))
        else:
            raise ParameterError(f"selectors: {s!r} is neither a selector name nor a (name, options) pair")
    return out


def _checked_seeds(seeds) -> list[int]:
    """The seeds, each a whole number >= 0, at least one, none twice."""
    if isinstance(seeds, (str, bytes, dict)) or not hasattr(seeds, "__iter__"):
        raise ParameterError(f"seeds must be a list of whole numbers >= 0 (e.g. [0, 1, 2]), got {seeds!r}")
    out = [int(check_number("seed", s, lo=0, integer=True)) for s in seeds]
    if not out:
        raise ParameterError("seeds is empty: give at least one seed")
    twice = sorted({s for s in out if out.count(s) > 1})
    if twice:
        raise ParameterError(f"seeds lists {', '.join(map(str, twice))} more than once")
    return out


def _check_objective(objective) -> None:
    missing = missing_members(objective)
    if missing:
        raise ParameterError(f"objective must follow the Objective contract (arraysel.objective.contract; "
                             f"it lacks {', '.join(missing)}), got {type(objective).__name__}")
