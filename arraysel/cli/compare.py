"""``arraysel compare``: run selectors on a scene and write Table 1, traces and figures."""
from __future__ import annotations

import contextlib
import logging
import math
import signal
import sys
import threading

from arraysel.errors import ParameterError, check_number
from arraysel.objective.build import TOY_SCENE
from arraysel.objective.build import objective_for as build_objective  # the CLI's name for it (loads no torch)

#: the default time budget: the runs of one comparison share DEFAULT_TOTAL_S seconds, each getting
#: at least DEFAULT_MIN_S and at most DEFAULT_BUDGET_S (so that the main job, 5 seeds of two
#: stochastic selectors, and a comparison on a 128-element scene, basis build included, finish in
#: about 10 minutes on two cores)
DEFAULT_TOTAL_S = 420.0
DEFAULT_BUDGET_S = 120.0
DEFAULT_MIN_S = 10.0

_log = logging.getLogger(__name__)


def default_budget_s(runs: int) -> float:
    """Seconds per run of the default time budget for ``runs`` (selector, seed) runs: an equal
    share of :data:`DEFAULT_TOTAL_S`, between :data:`DEFAULT_MIN_S` and :data:`DEFAULT_BUDGET_S`,
    rounded down to a whole second."""
    share = DEFAULT_TOTAL_S / max(1, runs)
    return float(max(DEFAULT_MIN_S, min(DEFAULT_BUDGET_S, math.floor(share))))


def scene_defaults(scene: str) -> tuple[float | None, list[int] | None]:
    """The scene's own defaults of a comparison, ``(compare.budget_s, compare.seeds)`` (None where
    it sets none; the ``toy`` objective has none)."""
    if scene == TOY_SCENE:
        return None, None
    from arraysel.scenes.schema import load_scene

    sc = load_scene(scene)
    seeds = sc.value("compare", "seeds")
    if seeds is not None and (not seeds or len(set(seeds)) != len(seeds)):
        raise ParameterError(f"compare.seeds must list distinct integers >= 0, got {seeds!r}")
    budget = sc.value("compare", "budget_s")
    return (None if budget is None else float(budget)), (None if seeds is None else [int(s) for s in seeds])


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "compare", help="compare selectors on a scene (Table 1, traces, figures)",
        description="Run each selector once per seed on the scene's objective, add the full-array "
                    "reference row and write table1.csv (the metrics of each selector's best run), stats.csv "
                    "(statistics over seeds), runs.csv, trace.csv, IOHprofiler files (ioh/), "
                    "run.json and figures to --out. Rows are saved as each run finishes; after an "
                    "interruption, rerun the same command with --resume.")
    p.add_argument("--selectors", required=True, metavar="A,B,...",
                   help="comma-separated selector names (see `arraysel list`)")
    p.add_argument("--scene", default="paper",
                   help="scene name or file (default: paper); 'toy' is the cheap synthetic objective "
                        "arraysel.objective.toy (Ne=64, k=32), for trying selectors out")
    p.add_argument("--budget-s", type=float, default=None, metavar="S",
                   help=f"wall-clock seconds per selector run (0: no limit; default: the scene's "
                        f"compare.budget_s, else the runs share {DEFAULT_TOTAL_S / 60:g} minutes, "
                        f"{DEFAULT_MIN_S:g} to {DEFAULT_BUDGET_S:g} s each, "
                        f"e.g. 38 s for 'ste,random,uniform' with 5 seeds; with --resume the budget of "
                        f"the runs being resumed)")
    p.add_argument("--budget-evals", type=int, default=None, metavar="N",
                   help="objective evaluations per selector run (default: no limit)")
    p.add_argument("--seeds", default=None, metavar="0,1,2",
                   help="comma-separated seeds, each stochastic selector runs once per seed (default: the "
                        "scene's compare.seeds, else 0,1,2,3,4); a deterministic one (uniform, greedy) runs "
                        "once, with the first")
    p.add_argument("--out", default="results/compare", metavar="DIR",
                   help="output folder (default results/compare)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="torch device (default cpu)")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32",
                   help="real dtype of the objective (default float32)")
    p.add_argument("--plugin", action="append", default=[], metavar="MODULE_OR_PATH",
                   help="load a selector plugin (module name or .py file) without installing it; repeatable")
    p.add_argument("-o", "--option", action="append", default=[], metavar="SELECTOR.KEY=VALUE",
                   help="selector option, e.g. -o ste.lr=1e-3 (repeatable; see `arraysel list -v`)")
    p.add_argument("--resume", action="store_true",
                   help="keep the finished runs in --out/runs.csv and run only the missing ones (refused "
                        "when the scene, k, dtype or budget differ from --out/run.json; seeds and "
                        "selectors may be added)")
    p.add_argument("--force", action="store_true",
                   help="replace the results already in --out (without it, a folder holding the results "
                        "of a compare run is refused)")
    p.add_argument("--grace-s", type=float, default=None, metavar="S",
                   help="seconds a run may go past --budget-s before its process is stopped and it gets "
                        "an error row (default 30); with --budget-s 0, the seconds a run may take (default 3600)")
    p.add_argument("--in-process", action="store_true",
                   help="run the selectors in this process instead of a fresh child process per run "
                        "(faster start, not isolated: a run is still stopped at its deadline, but one that "
                        "exits the process stops the whole compare, and one that changes the objective or "
                        "the functions the tables use stops it with an error)")
    g = p.add_argument_group("parallel runs (see docs/distributed.md)")
    g.add_argument("--executor", choices=("local", "process", "dask"), default="local",
                   help="where the (selector, seed) runs are computed: local (default: this process, "
                        "one after another), process (a local process pool of --workers processes) or "
                        "dask (a Dask cluster at --scheduler, or a local one with --workers processes; "
                        "needs pip install arraysel[dask]). Results are the same as a local run")
    g.add_argument("--workers", type=int, default=None, metavar="N",
                   help="worker processes for --executor process / dask without --scheduler "
                        "(default: the number of CPU cores)")
    g.add_argument("--scheduler", default=None, metavar="tcp://HOST:8786",
                   help="address of a running Dask scheduler (--executor dask)")
    g.add_argument("--threads", type=int, default=None, metavar="T",
                   help="threads of each run (torch, numba, BLAS); default: the cores shared out over the "
                        "runs that go at a time (cores / --workers; on a Dask cluster, each host's cores / "
                        "the tasks its workers run at a time; locally, all cores)")
    g.add_argument("--retries", type=int, default=2, metavar="N",
                   help="times a run is started again after its worker died or it failed (default 2)")
    p.add_argument("--aggregate", choices=("mean", "worst"), default=None,
                   help="headline metrics of a scene with several field points: the mean over the points or "
                        "the worst point (default: the scene's metrics.aggregate, 'mean')")
    p.add_argument("--no-figures", action="store_true", help="write tables only")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress bar (without it: bars when stderr is a terminal, none in a redirected log)")
    p.set_defaults(func=run)


def parse_seeds(text: str) -> list[int]:
    try:
        seeds = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise ParameterError(f"--seeds must be comma-separated integers, got {text!r}") from None
    if not seeds or any(s < 0 for s in seeds) or len(set(seeds)) != len(seeds):
        raise ParameterError(f"--seeds must list distinct integers >= 0, got {text!r}")
    return seeds


def parse_selectors(text: str, registry) -> list[str]:
    names = [s.strip() for s in text.split(",") if s.strip()]
    if not names:
        raise ParameterError("--selectors is empty; known selectors: " + ", ".join(registry.names()))
    unknown = [n for n in names if n not in registry]
    if unknown:
        raise ParameterError(f"unknown selector(s) {', '.join(unknown)}; known selectors: "
                             f"{', '.join(registry.names())} (load others with --plugin)")
    if len(set(names)) != len(names):
        raise ParameterError(f"--selectors lists a selector twice: {text!r}")
    for n in names:  # before anything is built: a missing extra is one line with its pip command
        registry[n].check_available()
    return names


def parse_options(items: list[str], names: list[str], registry) -> dict[str, dict]:
    """``["ste.lr=1e-3", ...]`` -> ``{"ste": {"lr": 0.001}}`` validated against declared options."""
    raw: dict[str, dict[str, str]] = {n: {} for n in names}
    for item in items:
        key, sep, value = item.partition("=")
        sel, dot, opt = key.strip().partition(".")
        if not sep or not dot or not sel or not opt:
            raise ParameterError(f"-o {item!r}: expected SELECTOR.KEY=VALUE, e.g. -o ste.lr=1e-3")
        if sel not in raw:
            raise ParameterError(f"-o {item!r}: selector {sel!r} is not in --selectors ({', '.join(names)})")
        raw[sel][opt] = value
    return {n: registry[n].parse_options(raw[n]) for n in names}


def _exact_run_notice(objective, budget, runs: int) -> str | None:
    """The whole comparison's estimated time when the scene runs on the exact PSF path."""
    if not any(p.basis is None for p in getattr(objective, "psfs", ())):
        return None
    if budget.evaluations is not None:
        return f"{objective.exact_notice(budget.evaluations * runs)} ({runs} run(s) of {budget.evaluations})"
    per = objective.estimate_seconds(1)
    return (f"the exact PSF path takes about {per:.2g} s a mask: each of the {runs} run(s) stops at its "
            f"{budget.seconds:g} s budget after about {int(budget.seconds / per)} evaluation(s)")


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread: ``compare`` handles it as Ctrl-C (its children and
    pool workers are stopped, run.json says ``interrupted``, temporary files are removed)."""


def _raise_terminated(signum, frame):
    raise Terminated(f"signal {signum}")


@contextlib.contextmanager
def _sigterm_as_interrupt():
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def run(args) -> int:
    try:
        with _sigterm_as_interrupt():
            return _run(args)
    except Terminated:
        print("arraysel compare: terminated (SIGTERM)", file=sys.stderr)
        return 128 + signal.SIGTERM


def _run(args) -> int:
    # imported here, not at the top: building the parser (``arraysel --help``) loads no torch
    from arraysel.selectors.registry import get_registry, load_plugin
    from arraysel.io.outputs import check_outputs, folder_files, scene_input
    from arraysel.run.outdir import RESULT_FILES

    check_outputs(folder_files("--out", args.out, [n for n in RESULT_FILES if n != "ioh"]),
                  folders=[("--out", args.out), ("--out (ioh)", f"{args.out}/ioh")],
                  inputs=[("--scene", scene_input(args.scene)), *(("--plugin", p) for p in args.plugin)])
    from arraysel.run.guard import describe, watched_reductions

    reductions = watched_reductions()  # what a plugin must not replace while it loads
    for spec in args.plugin:
        load_plugin(spec)
        _untouched(reductions, f"--plugin {spec}", describe)
    registry = get_registry()
    _untouched(reductions, "an installed plugin", describe)
    names = parse_selectors(args.selectors, registry)
    options = parse_options(args.option, names, registry)
    seeds = None if args.seeds is None else parse_seeds(args.seeds)
    if args.budget_s is not None and not math.isfinite(args.budget_s):
        raise ParameterError(f"--budget-s must be a finite number of seconds >= 0 (0: no time limit), "
                             f"got {args.budget_s}")
    budget_s = None if args.budget_s is None else check_number("--budget-s", args.budget_s, lo=0)
    grace_s = None if args.grace_s is None else check_number("--grace-s", args.grace_s, lo=0, hi=86400)
    from arraysel.run.outdir import check_out_dir, lock_out_dir
    if args.resume and args.force:
        check_out_dir(args.out, resume=True, force=True)  # refused before a folder is made
    with lock_out_dir(args.out):  # held until the end; compare() takes it again (re-entrant)
        return _run_locked(args, registry, names, options, seeds, budget_s, grace_s,
                           check_out_dir(args.out, resume=args.resume, force=args.force))


def _untouched(reductions, what: str, describe) -> None:
    """Refuse a plugin that replaced, while it loaded, a function the tables are computed with."""
    changed = reductions.restore()
    if changed:
        raise ParameterError(f"{what} replaced {describe(changed)} while it was loaded; the tables of a "
                             f"comparison are computed with these, so it is refused")


def _run_locked(args, registry, names, options, seeds, budget_s, grace_s, previous) -> int:
    from arraysel.run.compare import DEFAULT_SEEDS, compare
    from arraysel.selectors.contract import Budget

    scene_s, scene_seeds = scene_defaults(args.scene)
    seeds = scene_seeds if seeds is None else seeds
    n_runs = sum(1 if registry[n].deterministic else len(seeds or DEFAULT_SEEDS) for n in names)
    if budget_s is None and args.resume and isinstance((previous or {}).get("budget"), dict):
        budget_s = float(previous["budget"].get("seconds") or 0)     # the runs being resumed
    elif budget_s is None and scene_s is not None:
        budget_s = scene_s
        _log.warning("arraysel compare: %d run(s) of %g s each (the scene's compare.budget_s; --budget-s sets it)",
                     n_runs, budget_s)
    elif budget_s is None:
        budget_s = default_budget_s(n_runs)
        _log.warning("arraysel compare: %d run(s) of %g s each (the default time budget shares %g minutes; "
                     "--budget-s sets it)", n_runs, budget_s, DEFAULT_TOTAL_S / 60)
    evals = None if args.budget_evals is None else check_number("--budget-evals", args.budget_evals,
                                                                lo=1, integer=True)
    budget = Budget(seconds=budget_s or None, evaluations=evals)
    if budget.unlimited:
        raise ParameterError("--budget-s 0 needs --budget-evals: a run must have some budget")
    retries = check_number("--retries", args.retries, lo=0, hi=100, integer=True)
    threads = None if args.threads is None else check_number("--threads", args.threads, lo=1, hi=1024, integer=True)
    executor = None
    if args.executor != "local" or args.workers is not None or args.scheduler:
        from arraysel.run.executors import make_executor
        executor = make_executor(args.executor, workers=args.workers, scheduler=args.scheduler,
                                 retries=retries, threads=threads)
    try:
        objective = build_objective(args.scene, args.device, args.dtype, args.aggregate)
        notice = _exact_run_notice(objective, budget, n_runs)
        if notice:
            _log.warning("arraysel compare: %s", notice)
        result = compare(objective, [(n, options[n]) for n in names], out_dir=args.out, seeds=seeds,
                         budget=budget, registry=registry, resume=args.resume,
                         progress=False if args.no_progress else None, figures=not args.no_figures,
                         command_line=["arraysel", *sys.argv[1:]], executor=executor, force=args.force,
                         isolate=not args.in_process, grace_s=grace_s, threads=threads)
    finally:
        if executor is not None:
            executor.close()
    from arraysel.report.summary import to_text

    print(to_text(result.table, result.stats))  # the tables as written (AOCC, gaps)
    print(f"wrote {args.out}/table1.csv (each selector's best run), stats.csv (statistics over seeds), "
          f"runs.csv, trace.csv, ioh/, run.json" + ("" if args.no_figures else " and figures"))
    return _report_failures(result.failures)


def _report_failures(failed) -> int:
    """Say which runs have an error row; exit code 1 when any, else 0."""
    if failed:
        print(f"arraysel compare: {len(failed)} run(s) failed (see the error column of runs.csv): "
              + ", ".join(failed), file=sys.stderr)
        return 1
    return 0
