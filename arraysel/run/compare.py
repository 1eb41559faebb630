"""``compare``: run every selector for every seed on one objective and write the report.

It adds the ``full`` reference row and writes, atomically and after each finished run, the
files described in ``docs/selectors.md`` (``runs.csv``, ``table1.csv``, ``stats.csv``, ``trace.csv``, the
IOHprofiler files under ``ioh/``, ``run.json``, then the figures). The runs go one after
another in this process, each in a fresh child process (:mod:`arraysel.run.isolation`), or
on an executor, each again in a fresh child process (:mod:`arraysel.run.executors`,
:mod:`arraysel.run.compare_task`), so a plugin cannot change another run's numbers. The folder
is locked for the whole run (:func:`arraysel.run.outdir.lock_out_dir`); each save writes the
traces before the rows that name them, so a run killed at any point and resumed lists every run
in ``runs.csv`` with its trace.
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import math
import os
import platform
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from arraysel.errors import ArrayselError, ParameterError, check_number, error_text as _error_text
from arraysel.report import plots
from arraysel.report import tables as reporting
from arraysel.report.columns import ROW_COLUMNS
from arraysel.run.compare_task import _Raise, compare_item, compare_task
from arraysel.run.experiment import (Experiment, _failed_row, _final_metrics, _lost_row, budget_flag, config_label,
                                     full_row)
from arraysel.run.isolation import DEFAULT_GRACE_S, IsolatedWorker
from arraysel.run.outdir import check_out_dir, check_resume, lock_out_dir, remove_results
from arraysel.run.workers import TaskFailed, objective_factory_for
from arraysel.selection import Selection, indices_to_mask, parse_element_text
from arraysel.selectors.contract import Budget, BudgetExceededError

__all__ = ["DEFAULT_SEEDS", "compare", "write_figures"]


def _make_isolator(objective, objective_factory, todo, classes, threads=None):
    """An :class:`~arraysel.run.isolation.IsolatedWorker` for the local runs, and the configs whose
    selector class cannot be sent to it (they run in this process)."""
    factory = objective_factory if objective_factory is not None else objective_factory_for(objective)
    in_process = set()
    # the children load the cache entries this process has just loaded and checked: sizes suffice
    verify = "size" if objective_factory is None else None
    for lab, name, opts, _seed in todo:
        try:
            compare_item(lab, classes[name], opts, Budget(evaluations=1), 0)
        except ParameterError as exc:
            print(f"arraysel compare: {lab} runs in this process, not isolated: {exc}", file=sys.stderr)
            in_process.add(lab)
    return IsolatedWorker(factory, threads=threads, verify=verify), in_process


def _timeout(budget: Budget, grace: float) -> float | None:
    """Seconds a run's process may take: its time budget plus the grace period."""
    return None if budget.seconds is None else budget.seconds + grace


def _task_failed_row(objective, lab, cls, opts, seed, res: TaskFailed, budget, grace, lost: bool) -> dict:
    """The error row of a run whose process was stopped at its deadline (``run failed:
    BudgetExceededError: ...``), died or failed (``run failed:``, or ``run lost:`` on an executor)."""
    msg = res.message
    if res.kind == "timeout":
        return _failed_row(objective, lab, cls.name, opts, seed,
                           f"run failed: BudgetExceededError: {msg}; the budget was {budget.seconds:g} s and "
                           f"the grace period {grace:g} s")
    if lost:
        return _lost_row(objective, lab, cls.name, opts, seed, msg)
    return _failed_row(objective, lab, cls.name, opts, seed, f"run failed: {msg}")


def _checked(objective, row: dict, trace: list) -> tuple[dict, list]:
    """A row made in another process, checked here: its selection is scored again on this
    process's objective, which no plugin has touched. A Mean that differs (a selector that
    patched ``evaluate`` in its own process, say) is replaced by the true one, the row gets an
    error naming both, and its trace, recorded in that process, is left out."""
    selection = parse_element_text(str(row.get("elements") or ""))
    if not selection or str(row.get("error") or "").strip():
        return row, trace
    try:
        true = _final_metrics(objective, selection)
    except Exception as exc:  # its selection cannot be scored here: the row cannot be trusted
        return {**row, "error": f"its selection could not be scored again: {_error_text(exc)}"}, []
    got, want = float(row.get("Mean", math.nan)), float(true.get("Mean", math.nan))
    if got == want or abs(got - want) <= 1e-5 * abs(want):
        return row, trace
    return {**row, **true, "error": f"the run reported Mean {got:.6g} for its selection, which scores {want:.6g}: "
                                    f"the selector changed the objective in its own process (its trace is "
                                    f"left out)"}, []


def _run_isolated(isolator, objective, lab, cls, opts, budget, seed, grace) -> tuple[dict, list]:
    item = compare_item(lab, cls, opts, budget, seed)
    res = isolator.run(compare_task, item, _timeout(budget, grace))
    if isinstance(res, _Raise):
        if isinstance(res.exception, BudgetExceededError):
            return _failed_row(objective, lab, cls.name, opts, seed, _error_text(res.exception)), []
        raise res.exception
    if isinstance(res, TaskFailed):
        return _task_failed_row(objective, lab, cls, opts, seed, res, budget, grace, lost=False), []
    return _checked(objective, res["row"], res["trace"])


def _warm_here(objective) -> dict:
    """Warm the objective of this process before a run made here starts its clock (so that its
    one-off work is not charged to the first run); the warm-up's figures for ``run.json``."""
    from arraysel.run.template import warm_objective

    return warm_objective(objective)


def _record_warm_ups(meta: dict, executor, isolator) -> None:
    """``run.json``'s ``worker_warm_ups``: each worker's one-off work (objective build, basis
    check, compiled code, plans), timed once per worker, never charged to a run."""
    found = []
    if executor is not None and hasattr(executor, "worker_warm_ups"):
        found = executor.worker_warm_ups()
    elif isolator is not None:
        found = isolator.warm_ups
    if found:
        meta["worker_warm_ups"] = [{k: (round(v, 4) if isinstance(v, float) else v) for k, v in w.items()}
                                   for w in found]


#: the objective's counters (they change with every call)
_COUNTERS = ("evaluations", "gradient_steps", "seconds")


class _Fingerprint:
    """What a run in this process must leave as it found it: the objective's attributes and the
    methods of its class and of :class:`~arraysel.selectors.contract.BudgetedObjective` (by
    identity: a replaced or wrapped ``evaluate`` shows), and the full array's Mean (an attribute
    edited in place, such as ``metric_kw["r_main"]``, shows there)."""

    def __init__(self, objective, full: dict):
        self.objective = objective
        self.full_mean = float(full.get("Mean", math.nan))
        self.ids = self._ids()

    def _ids(self) -> dict:
        from arraysel.selectors.contract import BudgetedObjective

        out = {}
        for where, mapping in (("objective", getattr(self.objective, "__dict__", {})),
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
            isolate: bool = False, grace_s: float | None = None, threads: int | None = None):
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
        worker (default: :func:`arraysel.run.workers.objective_factory_for`)
    force : replace the results already in ``out_dir`` (without it, a folder that holds
        results of a compare run is refused unless ``resume``)
    isolate : run each ``(selector, seed)`` in a child process (built from ``objective_factory``)
        that is stopped ``grace_s`` seconds after its time budget: a selector that hangs, exits
        the process (``sys.exit``) or crashes it gets an error row and the other runs go on.
        A selector class that cannot be sent to a child process runs in this process.
    grace_s : seconds past the time budget before an isolated run is stopped (default
        :data:`arraysel.run.isolation.DEFAULT_GRACE_S`)
    threads : threads of each isolated local run (default: this process's torch threads); an
        executor sets its own (``threads=`` of :func:`arraysel.run.executors.make_executor`)

    Returns
    -------
    pandas.DataFrame : the ``table1.csv`` table (each configuration's best run; the statistics
    over seeds are in ``stats.csv``, :func:`arraysel.report.stats.stats_table`)

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

    from arraysel.selectors.registry import get_registry

    registry = get_registry() if registry is None else registry
    budget = Budget(seconds=120.0) if budget is None else budget
    sels = _normalise_selectors(selectors)
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
    grace = DEFAULT_GRACE_S if grace_s is None else float(check_number("grace_s", grace_s, lo=0, hi=1e6))

    out = Path(out_dir)
    if resume and force:
        check_out_dir(out, resume=resume, force=force)  # refused before a folder is made
    with lock_out_dir(out):  # one compare at a time in a folder, for the whole run
        return _compare_locked(objective, out, registry, budget, sels, seeds, classes, labels, grace,
                               resume=resume, force=force, progress=progress, figures=figures,
                               command_line=command_line, info=info, executor=executor,
                               objective_factory=objective_factory, isolate=isolate, threads=threads)


def _compare_locked(objective, out: Path, registry, budget, sels, seeds, classes, labels, grace, *, resume,
                    force, progress, figures, command_line, info, executor, objective_factory, isolate, threads):
    """The body of :func:`compare`, once ``out`` is locked."""
    import pandas as pd
    from tqdm.auto import tqdm

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
        return seeds[:1] if classes[name].deterministic else seeds

    todo = [(lab, name, opts, seed) for lab, (name, opts) in zip(labels, sels) for seed in seeds_of(name)
            if (lab, seed) not in done]
    remote = executor is not None and not getattr(executor, "in_process", False)
    if remote:
        factory = objective_factory if objective_factory is not None else objective_factory_for(objective)
        items = [compare_item(lab, classes[name], opts, budget, seed) for lab, name, opts, seed in todo]
    isolator, in_process = None, set()
    if isolate and not remote and todo:
        isolator, in_process = _make_isolator(objective, objective_factory, todo, classes, threads)
    if not remote and todo and (isolator is None or in_process):  # runs in this process: warm it first
        meta["warm_up"] = _warm_here(objective)
    fingerprint = _Fingerprint(objective, full)  # checked after each run made in this process (warmed)
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
                    changed = fingerprint.changed()
                    if changed:  # its numbers, and those of every later run here, cannot be trusted
                        why = (f"the selector changed the objective it was given ({changed}); run it "
                               f"isolated (without --in-process)")
                        row = {**row, "error": "; ".join(e for e in (str(row.get("error") or ""), why) if e)}
                        rows.append(row)
                        traces.extend({"config": lab, "seed": seed, **t} for t in trace)
                        save()
                        raise ArrayselError(f"{lab} seed {seed}: {why}")
                row = {**row, "budget_flag": budget_flag(row, budget, grace)}
                rows.append(row)
                traces.extend({"config": lab, "seed": seed, **t} for t in trace)
                save()
                finished += 1
                bar.update(1)
        else:
            # results arrive in any order; rows and traces are kept in the order of `todo`
            kept_rows, kept_traces = list(rows), list(traces)
            results: dict[int, tuple[dict, list]] = {}
            verify = "size" if objective_factory is None else None  # as in _make_isolator
            tasks = executor.run_tasks(factory, compare_task, items, fresh=True, timeout=_timeout(budget, grace),
                                       verify=verify)  # each run in a fresh process, killed at its deadline
            with contextlib.closing(tasks):
                for i, res in tasks:  # closing the generator cancels the rest on an exception
                    lab, name, opts, seed = todo[i]
                    if isinstance(res, _Raise) and isinstance(res.exception, BudgetExceededError):
                        res = TaskFailed(_error_text(res.exception))
                    if isinstance(res, _Raise):
                        raise res.exception
                    if isinstance(res, TaskFailed):
                        row = _task_failed_row(objective, lab, classes[name], opts, seed, res, budget, grace,
                                               lost=True)
                        trace = []
                    else:
                        row, trace = _checked(objective, res["row"], res["trace"])
                    row = {**row, "budget_flag": budget_flag(row, budget, grace)}
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
        _record_warm_ups(meta, executor if remote else None, isolator)
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
    _record_warm_ups(meta, executor if remote else None, isolator)

    table = reporting.table1(pd.DataFrame([full] + rows, columns=list(ROW_COLUMNS)))
    if figures:
        # each config's selection, from the run the table keeps (a row's ``elements`` is the text
        # a run sends back and a resumed folder holds: read once here, not back from the table)
        n = int(objective.n_elements)
        selections = {config: Selection.from_text(str(row.get("elements") or ""), n)
                      for config, row in reporting.best_rows([full] + rows).items()}
        meta["figure_errors"] = write_figures(objective, selections, table, pd.DataFrame(traces), out)
    failed = [f"{r['config']} seed {r['seed']}" for r in [full] + rows if str(r.get("error") or "").strip()]
    meta["error_rows"] = len(failed)
    meta["failed_runs"] = failed
    meta["status"] = "finished"
    meta["finished"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    reporting.write_json(out / "run.json", meta)
    return table


# ---------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------

def write_figures(objective, selections: dict[str, Selection], table, trace, out: Path) -> list[str]:
    """Draw the figures of a comparison (:mod:`arraysel.report.plots`) from each config's
    :class:`~arraysel.selection.Selection` (``table``: its ``full`` row's Mean) and save them in
    ``out``: ``masks.png``, ``psfs.png`` (a 3-D scene: ``planes.png``), ``profiles.png``, ``trace.png``,
    ``anytime.png``. Returns a
    list of problems (empty when all went well): a figure never loses the tables."""
    problems: list[str] = []
    pitch = getattr(getattr(objective, "setup", None), "pitch", None)
    grid = getattr(objective, "element_grid", None)
    try:
        if grid is not None:  # a matrix probe: each selection as its ny x nx image
            kept = [config for config, sel in selections.items() if len(sel)]
            plots.save_figure(plots.matrix_masks_figure(kept, np.array([selections[c].mask for c in kept]), grid),
                              out / "masks.png")
        else:
            plots.save_figure(plots.selections_figure(selections), out / "masks.png")
    except Exception as exc:  # a figure must never lose the tables
        problems.append(f"masks.png: {type(exc).__name__}: {exc}")
    labels = [config for config, sel in selections.items() if len(sel) and config != "full"]
    masks = np.array([selections[config].mask for config in labels], dtype=bool)
    if len(labels) and hasattr(objective, "reference_planes"):
        try:  # a 3-D scene: its planes and the C-plane's lateral profiles
            import torch
            with torch.no_grad():
                planes = {k: v.cpu().numpy() for k, v in objective.planes(masks.astype(np.float32)).items()}
                ref = {k: v.cpu().numpy() for k, v in objective.reference_planes().items()}
            plots.save_figure(plots.planes_figure(labels, planes, objective.coords, ref), out / "planes.png")
            if "xy" in planes:
                plots.save_figure(plots.lateral_profiles_figure(labels, planes["xy"], objective.coords["xy"],
                                                                ref["xy"]), out / "profiles.png")
        except Exception as exc:
            problems.append(f"planes/profiles: {type(exc).__name__}: {exc}")
    elif len(labels):
        try:
            import torch
            with torch.no_grad():
                kern = objective.kernels(masks).detach().cpu().numpy()
                ref = objective.reference_kernel().detach().cpu().numpy()
            plots.save_figure(plots.psfs_figure(labels, kern, ref, pitch), out / "psfs.png")
            plots.save_figure(plots.profiles_figure(labels, kern, ref, pitch), out / "profiles.png")
        except Exception as exc:
            problems.append(f"psfs/profiles: {type(exc).__name__}: {exc}")
    full = table[table["config"] == "full"]
    full_mean = float(full["Mean"].iloc[0]) if len(full) and np.isfinite(full["Mean"].iloc[0]) else None
    try:
        plots.save_figure(plots.trace_figure(trace, full_mean), out / "trace.png")
    except Exception as exc:
        problems.append(f"trace.png: {type(exc).__name__}: {exc}")
    try:
        ref_mean = float(full["Mean"].iloc[0]) if len(full) else None
        plots.save_figure(plots.plot_anytime(trace, full_mean=ref_mean), out / "anytime.png")
    except Exception as exc:
        problems.append(f"anytime.png: {type(exc).__name__}: {exc}")
    return problems
