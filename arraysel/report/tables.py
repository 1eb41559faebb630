"""Tables written by ``arraysel compare`` (every file written atomically through :mod:`arraysel.io.atomic`).

Files (see ``docs/selectors.md``):

* ``runs.csv`` — one row per (config, seed) run plus ``full``; columns
  :data:`arraysel.report.columns.ROW_COLUMNS`. The other tables are built from it
  (:func:`rebuild_tables` rebuilds them from a folder's ``runs.csv``).
* ``table1.csv`` — one row per config, columns :data:`arraysel.report.columns.TABLE1_COLUMNS`:
  ``config, L_PSF, L_contrast, L_SLR_q, L_SLR_i, Mean, seconds, evaluations, elements,
  L_SLR, gradient_steps, overhead_seconds, seed, seeds, error``. Every value but ``seeds``
  (the config's runs) and ``error`` (the errors of all its runs) is that of ONE run, the
  config's listed selection: its run with the lowest finite ``Mean`` (``seed`` names it),
  so the metrics are those of ``elements``.
* ``stats.csv`` — one row per config, the statistics of its runs' Means over seeds
  (median, quartiles, IQR, mean, std, best, worst, order-statistic confidence interval of the
  median with its coverage, Mann-Whitney U test against ``random``, Holm-adjusted, and
  Vargha-Delaney A): :mod:`arraysel.report.stats`, columns
  :data:`arraysel.report.columns.STATS_COLUMNS`.
* ``trace.csv`` — ``config,seed,seconds,evaluations,gradient_steps,best_Mean,event``,
  one ``improvement`` row per new best evaluated selection, then one ``end`` row at the
  run's last evaluation and time (the trace reaches the end of the budget).
* ``ioh/<config>/IOHprofiler_f1_<scene>.json`` + ``data_f1_<scene>/IOHprofiler_f1_DIM<Ne>.dat``
  — the same traces in the IOHprofiler format (:func:`write_ioh`), for
  IOHanalyzer and ``iohinspector``.
* figures: drawn by :mod:`arraysel.report.plots`, saved by :func:`arraysel.run.compare.compare`.
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from arraysel.errors import ParameterError
from arraysel.io.atomic import atomic_write_text  # noqa: F401  (one writer; re-exported for old callers)
from arraysel.report.columns import METRICS as METRIC_NAMES, MERIT_COLUMNS, ROW_COLUMNS, TABLE1_COLUMNS, TRACE_COLUMNS
from arraysel.report.stats import deterministic_configs, stats_table
from arraysel.selection import Selection

__all__ = ["atomic_write_text", "write_json", "write_csv", "write_runs", "write_ioh", "table1", "best_rows", "stats_table",
           "read_runs", "read_trace", "check_table", "typed_runs", "rebuild_tables", "compare_folder", "TABLE1_COLUMNS",
           "WrittenTables"]

#: text columns of ``runs.csv`` (read as text, an empty cell as "")
_TEXT_COLUMNS = ("config", "selector", "elements", "options", "error", "budget_flag")


def write_json(path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, default=str) + "\n")


def write_csv(path, df) -> None:
    atomic_write_text(path, df.to_csv(index=False))


def write_tables(out: Path, runs, trace=None) -> tuple[Any, Any]:
    """Write ``table1.csv`` and ``stats.csv`` of the runs table ``runs`` to the folder ``out``; the
    AOCC from ``trace`` (default: the folder's ``trace.csv``), the gap to the best known from the
    scene and ``k`` of the folder's ``run.json``. Returns the two tables written."""
    out = Path(out)
    if trace is None and (out / "trace.csv").is_file():
        trace = read_trace(out / "trace.csv")
    selectors = _run_meta(out).get("selectors")
    stats = stats_table(runs, trace, best_known_mean(out),
                        deterministic=deterministic_configs(runs, selectors if isinstance(selectors, list) else None))
    table = aperture_columns(table1(runs, dict(zip(stats["config"], stats["AOCC"]))), _run_meta(out))
    write_csv(out / "table1.csv", table)
    write_csv(out / "stats.csv", stats)
    return table, stats


def aperture_columns(table, meta: dict):
    """``table`` with the columns ``tx_elements`` and ``rx_elements`` after ``elements`` when the
    comparison's scene (``meta``, its ``run.json``) has ``aperture.mode`` ``full-tx`` or
    ``separate`` or ``per-transmit`` (``docs/apertures.md``): each row's transmit and receive
    elements of the probe (``elements`` holds the selector's units: under ``separate`` the receive
    element ``e`` is unit ``Ne + e``; under ``per-transmit`` ``tx_elements`` lists each transmit
    event's elements, the events separated by `` | ``). A shared-aperture scene's table is returned
    as it is."""
    from arraysel.objective.aperture import split_events, split_apertures
    from arraysel.selection import Selection

    scene = meta.get("scene") if isinstance(meta.get("scene"), dict) else {}
    mode = (scene.get("aperture") or {}).get("mode", "shared")
    if mode == "shared" or "elements" not in table.columns or not meta.get("n_elements"):
        return table
    n_units = int(meta["n_elements"])
    events = int(meta.get("aperture_events", 1))
    n_probe = n_units // {"separate": 2, "per-transmit": events + 1}.get(mode, 1)
    tx, rx = [], []
    for row in table.to_dict("records"):
        text = row["elements"]
        sel = Selection.from_text(text, n_units).indices if isinstance(text, str) and text.strip() else ()
        if mode == "per-transmit":
            ev, r = split_events(sel, n_probe, events) if sel else ([], [])
            tx.append(" | ".join(Selection.of(e, n_probe).text for e in ev) if sel else "")
        else:
            t, r = split_apertures(sel, n_probe, mode) if sel else ([], [])
            tx.append(Selection.of(t, n_probe).text if t else "")
        rx.append(Selection.of(r, n_probe).text if r else "")
    table = table.copy()
    at = list(table.columns).index("elements") + 1
    table.insert(at, "tx_elements", tx)
    table.insert(at + 1, "rx_elements", rx)
    return table


def best_known_mean(folder) -> float | None:
    """The best-known Mean of the scene and ``k`` the comparison in ``folder`` ran (its ``run.json``):
    the entry's ``reference_Mean`` where it has one (a lower value reported without its mask), else
    its ``Mean``; None without run.json or a stored entry."""
    from arraysel.scenes.best_known import best_known

    meta = _run_meta(folder)
    entry = best_known(meta.get("scene_name"), meta.get("k")) if meta else None
    return float(entry.get("reference_Mean", entry["Mean"])) if entry else None


def _run_meta(folder) -> dict:
    """The folder's ``run.json`` as a dict; empty when it is missing or not a JSON object."""
    try:
        meta = json.loads((Path(folder) / "run.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return meta if isinstance(meta, dict) else {}


def compare_folder(folder, option: str) -> tuple[dict, list[dict], str]:
    """``(scene dict, table1.csv rows, table1.csv path)`` of a folder written by ``arraysel compare``,
    for a command that takes it as ``option`` (named in every error): both files must exist and
    ``run.json`` must hold the scene."""
    import csv

    run_json, table = str(Path(folder) / "run.json"), str(Path(folder) / "table1.csv")
    for path in (run_json, table):
        if not Path(path).is_file():
            raise ParameterError(f"{option}: {path!r} does not exist (a folder written by arraysel compare holds it)")
    try:
        scene = json.loads(Path(run_json).read_text(encoding="utf-8"))["scene"]
    except (ValueError, KeyError, TypeError) as exc:
        raise ParameterError(f"{option}: {run_json!r} holds no scene ({type(exc).__name__})") from None
    with open(table, encoding="utf-8", newline="") as fh:
        return scene, list(csv.DictReader(fh)), table


def read_runs(path):
    """``runs.csv`` as a DataFrame: the text columns as text (an empty cell as ``""``), the numbers
    as numbers (``nan`` as NaN). A file cut short or edited into something else is refused
    (:func:`check_table`: ``ValueError`` naming the line)."""
    import pandas as pd

    check_table(path, "runs")
    return typed_runs(pd.read_csv(path, dtype={c: str for c in _TEXT_COLUMNS}, keep_default_na=False,
                                  na_values=["", "nan", "NaN"]))


def read_trace(path):
    """``trace.csv`` as a DataFrame, checked as :func:`read_runs` checks ``runs.csv``."""
    import pandas as pd

    check_table(path, "trace")
    return pd.read_csv(path, dtype={"config": str, "event": str, "elements": str}, keep_default_na=False,
                       na_values=["", "nan", "NaN"])


#: the number columns of each table :func:`check_table` checks (``seed``: a whole number)
_NUMBERS = {"runs": (*METRIC_NAMES, "seconds", "evaluations", "gradient_steps", "objective_seconds",
                     "overhead_seconds", "k", "n_elements"),
            "trace": ("seconds", "evaluations", "gradient_steps", "best_Mean")}
_NUMBER_RE = re.compile(r"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|nan|inf|infinity)", re.IGNORECASE)


def _whole(text: str) -> bool:
    """Whether ``text`` is a whole number >= 0 (``3``, or ``3.0`` as a table edited with pandas holds it)."""
    return bool(_NUMBER_RE.fullmatch(text)) and math.isfinite(float(text)) and float(text) >= 0 and \
        float(text).is_integer()


def check_table(path, kind: str) -> None:
    """Refuse (``ValueError`` naming the line) a ``runs.csv`` or ``trace.csv`` (``kind``) that was
    cut short or edited into something its readers would take silently: a line with another
    number of fields than the header, a number column holding text, a run without a whole-number
    seed, a ``runs.csv`` run listed twice."""
    import csv

    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None:
            return  # an empty file: the reader says so
        col = {c: i for i, c in enumerate(header)}
        numbers = [c for c in _NUMBERS[kind] if c in col]
        seen: dict[tuple, int] = {}
        for row in reader:
            line = reader.line_num
            if not row:
                continue
            if len(row) != len(header):
                raise ValueError(f"line {line} has {len(row)} fields, the header {len(header)}: the file was cut "
                                 f"short or edited")
            for c in numbers:
                cell = row[col[c]].strip()
                if cell and not _NUMBER_RE.fullmatch(cell):
                    raise ValueError(f"line {line}: {c} = {cell[:30]!r} is not a number")
            config = row[col["config"]] if "config" in col else ""
            seed = row[col["seed"]].strip() if "seed" in col else ""
            if "seed" in col and not _whole(seed) and not (kind == "runs" and config == "full" and seed == ""):
                raise ValueError(f"line {line}: {config} has seed {seed!r}, not a whole number >= 0")
            seed = str(int(float(seed))) if seed else seed
            if kind == "runs":
                key = (config, seed)
                if key in seen:
                    raise ValueError(f"lines {seen[key]} and {line} both list {config} seed {seed or '(none)'}")
                seen[key] = line


def typed_runs(runs):
    """A runs table with the types :func:`read_runs` gives: the text columns as text (a missing
    cell as ``""``), ``seed`` as whole numbers with a gap (the ``full`` row has none)."""
    import pandas as pd

    runs = runs.copy()
    for c in _TEXT_COLUMNS:
        if c in runs:
            runs[c] = runs[c].fillna("").astype(str)
    if "seed" in runs:  # the full row has none: integers with a gap, not floats
        runs["seed"] = pd.to_numeric(runs["seed"], errors="coerce").astype("Int64")
    return runs


def rebuild_tables(folder) -> list[Path]:
    """Rebuild ``table1.csv`` and ``stats.csv`` of a comparison folder from its ``runs.csv``;
    returns the paths written."""
    folder = Path(folder)
    write_tables(folder, read_runs(folder / "runs.csv"))  # the trace and run.json from the folder too
    return [folder / "table1.csv", folder / "stats.csv"]


class WrittenTables(NamedTuple):
    """The tables :func:`write_runs` wrote (DataFrames): ``runs.csv``, ``trace.csv``, ``table1.csv``,
    ``stats.csv``."""

    runs: Any
    trace: Any
    table: Any
    stats: Any


def write_runs(out: Path, rows: list[dict], trace: list[dict], budget, problem: str | None = None) -> WrittenTables:
    """Write ``runs.csv``, ``table1.csv``, ``stats.csv``, ``trace.csv`` and the IOHprofiler files
    (``ioh/``) of the rows as a file holds them (``elements`` as text); returns the tables."""
    import pandas as pd

    # a several-point scene's per-point columns ("L_PSF@p0", ..., "Mean@worst") follow ROW_COLUMNS
    extra = list(dict.fromkeys(k for r in rows for k in r if k not in ROW_COLUMNS))
    runs = pd.DataFrame(rows, columns=list(ROW_COLUMNS) + extra)
    # traces first: a run named in runs.csv always has its trace on disk (a kill between two of
    # these writes leaves a run traced but not listed, which --resume runs again)
    traces = pd.DataFrame(trace, columns=list(TRACE_COLUMNS))
    write_csv(out / "trace.csv", traces)
    try:
        write_ioh(out / "ioh", rows, trace, problem or "arraysel")
        failed = None
    except OSError as exc:  # an export the file system refuses must not cost the runs
        failed = exc
    write_csv(out / "runs.csv", runs)
    table, stats = write_tables(out, runs, trace)
    if failed is not None:
        from arraysel.errors import ArrayselError

        raise ArrayselError(f"the IOHprofiler files could not be written in {out / 'ioh'} ({failed}); runs.csv, "
                            "trace.csv, table1.csv and stats.csv were written: make room, then rerun the same "
                            "command with --resume") from failed
    return WrittenTables(runs, traces, table, stats)


# ---------------------------------------------------------------------------
# IOHprofiler format
# ---------------------------------------------------------------------------

#: longest folder name of an IOHprofiler algorithm (file systems allow 255 bytes a name)
SAFE_NAME_MAX = 96


def _safe_name(text: str) -> str:
    """``text`` as a file name: runs of other characters than letters, digits and ``_.+-`` as
    ``_``; a name longer than :data:`SAFE_NAME_MAX` (a config with an ``elements`` list, say)
    is cut and ends in a hash of the whole text, so distinct configs keep distinct folders."""
    import hashlib
    import re

    name = re.sub(r"[^A-Za-z0-9_.+-]+", "_", str(text)).strip("_") or "x"
    if len(name) <= SAFE_NAME_MAX:
        return name
    digest = hashlib.sha1(str(text).encode()).hexdigest()[:12]
    return f"{name[:SAFE_NAME_MAX - 13].rstrip('_')}_{digest}"


def write_ioh(folder: Path, rows: list[dict], trace: list[dict], problem: str,
              function_id: int = 1) -> list[Path]:
    """Write the runs in the IOHprofiler format (as ``ioh.logger.Analyzer`` writes it).

    One algorithm per config: ``folder/<config>/IOHprofiler_f<id>_<problem>.json``
    lists one run per seed (``instance`` 1, ``evals`` = the run's evaluations
    in ``runs.csv``; ``best.y`` and ``best.evals`` = the best row of its ``.dat`` lines, so the two
    agree by construction; ``best.x`` = the 0/1 mask of the selection that scored it: the
    ``elements`` of the trace's ``end`` row), and
    ``data_f<id>_<problem>/IOHprofiler_f<id>_DIM<Ne>.dat`` holds, per run,
    a header line ``evaluations raw_y seconds`` and one row per improvement of
    the trace, then the trace's ``end`` row, one row per evaluation count
    (:func:`arraysel.report.stats.dat_lines`). IOHprofiler readers split runs at
    ``evaluations == 1``, so a run whose first scored ``k``-selection came later
    (after gradient steps, or greedy's larger masks) starts with a row
    ``1 inf 0``. Runs without a finite Mean or a trace are left out. Minimisation.
    Returns the JSON paths written; older files of the folder are replaced.
    """
    import shutil

    folder = Path(folder)
    by_run: dict[tuple, list[dict]] = {}
    for t in trace:
        by_run.setdefault((str(t["config"]), str(t["seed"])), []).append(t)
    configs: dict[str, list[dict]] = {}
    for r in rows:
        if r.get("config") == "full":
            continue
        mean = pd_float(r.get("Mean"))
        if not math.isfinite(mean) or not by_run.get((str(r["config"]), str(r["seed"]))):
            continue
        configs.setdefault(str(r["config"]), []).append(r)
    if folder.exists():
        shutil.rmtree(folder)
    written = []
    pname = _safe_name(problem)
    for config, runs in configs.items():
        adir = folder / _safe_name(config)
        dim = int(runs[0]["n_elements"])
        rel = f"data_f{function_id}_{pname}/IOHprofiler_f{function_id}_DIM{dim}.dat"
        (adir / rel).parent.mkdir(parents=True, exist_ok=True)
        lines, jruns = [], []
        for r in runs:
            run_trace = by_run[(config, str(r["seed"]))]
            block, best = _ioh_block(run_trace)
            best["x"] = _best_x(run_trace, r, best["y"], dim)
            best["evals"] = int(best["evals"] or r["evaluations"])
            lines += ["evaluations raw_y seconds", *block]
            jruns.append({"instance": 1, "evals": int(r["evaluations"]), "best": best, "seed": int(r["seed"])})
        atomic_write_text(adir / rel, "\n".join(lines) + "\n")
        meta = {
            "version": "0.3.22", "suite": "arraysel", "function_id": function_id, "function_name": pname,
            "maximization": False, "algorithm": {"name": config, "info": "arraysel selector"},
            "attributes": ["evaluations", "raw_y", "seconds"],
            "scenarios": [{"dimension": dim, "path": rel, "runs": jruns}],
        }
        path = adir / f"IOHprofiler_f{function_id}_{pname}.json"
        write_json(path, meta)
        written.append(path)
    return written


def _ioh_block(run_trace: list[dict]) -> tuple[list[str], dict]:
    """The ``.dat`` lines of one run and its best (``{"evals", "y"}``, as the lines hold it)."""
    from arraysel.report.stats import dat_lines

    out, best_y, best_evals = [], math.inf, None
    for ev, y, seconds in dat_lines(run_trace):
        text = repr(float(y))  # the shortest text that reads back as the same float
        out.append(f"{ev} {text} {seconds:.6f}")
        if float(text) < best_y:
            best_y, best_evals = float(text), ev
    return out, {"evals": best_evals, "y": best_y}


def _best_x(run_trace: list[dict], row: dict, best_y: float, dim: int) -> list[int]:
    """The 0/1 mask of the selection that scored ``best_y``: the ``elements`` of the run's ``end``
    row; for a trace written before it had them, the run's selection (its Mean is the best, to
    float32 rounding: the same selection scored in another batch), else the empty list."""
    end = [t for t in run_trace if str(t.get("event")) == "end"]
    text = str(end[-1].get("elements") or "").strip() if end else ""
    if text and text.lower() != "nan":
        return Selection.from_text(text, dim).mask.astype(int).tolist()
    mean = pd_float(row.get("Mean"))
    if abs(mean - best_y) <= 1e-4 * abs(best_y):
        return Selection.from_text(str(row.get("elements") or ""), dim).mask.astype(int).tolist()
    return []


def pd_float(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def table1(runs, aocc: dict | None = None) -> "Any":
    """``table1.csv`` of a runs table (a DataFrame with ``ROW_COLUMNS``): one row per config, in
    their order, each the row of the config's run with the lowest finite ``Mean`` (its first run
    when none has one), with ``seeds`` (its runs), ``error`` (the errors of all its runs) and
    ``AOCC`` (from ``aocc``, by config: :func:`arraysel.report.stats.aocc_by_config`)."""
    import pandas as pd

    out = []
    for config, g in runs.groupby("config", sort=False):
        row = g.iloc[_best(pd.to_numeric(g["Mean"], errors="coerce").to_numpy(dtype=np.float64))]
        rec: dict[str, Any] = {c: row[c] for c in TABLE1_COLUMNS if c in row.index}
        rec["config"] = config
        rec["elements"] = row["elements"] if isinstance(row["elements"], str) else ""
        rec["seeds"] = len(g)
        rec["AOCC"] = (aocc or {}).get(config, math.nan)
        errs = [f"seed {s}: {e}" if str(s) != "" else str(e)
                for s, e in zip(g["seed"], g["error"]) if isinstance(e, str) and e]
        rec["error"] = "; ".join(errs)
        rec.update({c: row[c] for c in MERIT_COLUMNS if c in row.index})
        out.append(rec)
    merit = [c for c in MERIT_COLUMNS if c in runs.columns]
    return pd.DataFrame(out, columns=list(TABLE1_COLUMNS) + merit)


def _best(means: np.ndarray) -> int:
    """Position of the run a table keeps among one config's runs: the lowest finite ``Mean``, the
    first run when none is finite."""
    return int(np.argmin(np.where(np.isfinite(means), means, np.inf)))


def best_rows(rows: list[dict]) -> dict[str, dict]:
    """Per config (in the order of ``rows``), the run :func:`table1` keeps: the row with the
    lowest finite ``Mean``, its first row when none has one."""
    groups: dict[str, list[dict]] = {}
    for row in rows:
        groups.setdefault(str(row["config"]), []).append(row)
    return {config: g[_best(np.array([pd_float(r.get("Mean")) for r in g], dtype=np.float64))]
            for config, g in groups.items()}
