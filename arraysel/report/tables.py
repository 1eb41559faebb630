"""Tables written by ``arraysel compare`` (every file written atomically through :mod:`arraysel.io.atomic`).

Files (see ``docs/selectors.md``):

* ``runs.csv`` — one row per (config, seed) run plus ``full``; columns
  :data:`arraysel.report.columns.ROW_COLUMNS`.
* ``table1.csv`` — one row per config: ``config,L_PSF,L_contrast,L_SLR_q,
  L_SLR_i,Mean,seconds,evaluations,elements`` (means over seeds), then
  ``<col>_std`` columns when several seeds ran, then ``L_SLR, gradient_steps,
  overhead_seconds, seeds, best_seed, error``. ``elements`` is the selection
  of the best seed.
  Then the statistics over seeds: ``Mean_median, Mean_q25, Mean_q75,
  Mean_iqr, Mean_best, evaluations_median``.
* ``trace.csv`` — ``config,seed,seconds,evaluations,gradient_steps,best_Mean,event``,
  one ``improvement`` row per new best evaluated selection, then one ``end``
  row at the run's last evaluation and time (the trace reaches the end of the
  budget).
* ``ioh/<config>/IOHprofiler_f1_<scene>.json`` + ``data_f1_<scene>/IOHprofiler_f1_DIM<Ne>.dat``
  — the same traces in the IOHprofiler format (:func:`write_ioh`), for
  IOHanalyzer and ``iohinspector``.
* figures: drawn by :mod:`arraysel.report.plots`, saved by :func:`arraysel.run.compare.compare`.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from arraysel.io.atomic import atomic_write_text  # noqa: F401  (one writer; re-exported for old callers)
from arraysel.report.columns import ROW_COLUMNS, TABLE1_METRICS, TRACE_COLUMNS
from arraysel.selection import parse_element_text

__all__ = ["atomic_write_text", "write_json", "write_csv", "write_runs", "write_ioh", "table1", "TABLE1_COLUMNS"]

TABLE1_COLUMNS = ("config", *TABLE1_METRICS, "seconds", "evaluations", "elements")
_STD_OF = (*TABLE1_METRICS, "seconds", "evaluations")
_EXTRA = ("L_SLR", "gradient_steps", "overhead_seconds", "seeds", "best_seed", "error")
#: statistics over seeds (always written): median, quartiles, IQR and best of Mean, median evaluations
_SEED_STATS = ("Mean_median", "Mean_q25", "Mean_q75", "Mean_iqr", "Mean_best", "evaluations_median")


def write_json(path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, default=str) + "\n")


def write_csv(path, df) -> None:
    atomic_write_text(path, df.to_csv(index=False))


def write_runs(out: Path, rows: list[dict], trace: list[dict], budget, problem: str | None = None) -> None:
    """Write ``runs.csv``, ``table1.csv``, ``trace.csv`` and the IOHprofiler files (``ioh/``)."""
    import pandas as pd

    # a several-point scene's per-point columns ("L_PSF@p0", ..., "Mean@worst") follow ROW_COLUMNS
    extra = list(dict.fromkeys(k for r in rows for k in r if k not in ROW_COLUMNS))
    runs = pd.DataFrame(rows, columns=list(ROW_COLUMNS) + extra)
    # traces first: a run named in runs.csv always has its trace on disk (a kill between two of
    # these writes leaves a run traced but not listed, which --resume runs again)
    write_csv(out / "trace.csv", pd.DataFrame(trace, columns=list(TRACE_COLUMNS)))
    write_ioh(out / "ioh", rows, trace, problem or "arraysel")
    write_csv(out / "runs.csv", runs)
    write_csv(out / "table1.csv", table1(runs))


# ---------------------------------------------------------------------------
# IOHprofiler format
# ---------------------------------------------------------------------------

def _safe_name(text: str) -> str:
    import re
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", str(text)).strip("_") or "x"


def write_ioh(folder: Path, rows: list[dict], trace: list[dict], problem: str,
              function_id: int = 1) -> list[Path]:
    """Write the runs in the IOHprofiler format (as ``ioh.logger.Analyzer`` writes it).

    One algorithm per config: ``folder/<config>/IOHprofiler_f<id>_<problem>.json``
    lists one run per seed (``instance`` 1, ``evals`` = the run's evaluations
    in ``runs.csv``; ``best.y`` and ``best.evals`` = the best row of its ``.dat`` lines, so the two
    agree by construction; ``best.x`` = its 0/1 mask when its ``Mean`` is that best),
    and ``data_f<id>_<problem>/IOHprofiler_f<id>_DIM<Ne>.dat`` holds, per run,
    a header line ``evaluations raw_y seconds`` and one row per improvement of
    the trace, then the trace's ``end`` row. IOHprofiler readers split runs at
    ``evaluations == 1``, so a run whose first scored ``k``-selection came later
    (after gradient steps, or greedy's larger masks) starts with a row
    ``1 inf 0``. Runs without a finite Mean are left out. Minimisation.
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
            rows_t = sorted(by_run[(config, str(r["seed"]))],
                            key=lambda t: (int(t["evaluations"]), str(t.get("event")) == "end"))
            lines.append("evaluations raw_y seconds")
            if int(rows_t[0]["evaluations"]) > 1:
                lines.append("1 inf 0")
            best_evals = None
            best_y = math.inf
            for t in rows_t:
                ev = max(1, int(t["evaluations"]))
                y = repr(float(t["best_Mean"]))  # the shortest text that reads back as the same float
                lines.append(f"{ev} {y} {float(t['seconds']):.6f}")
                if float(y) < best_y:  # the value as the .dat holds it
                    best_y, best_evals = float(y), ev
            # the json's best is the .dat's best (the same trace rows); its x is the run's selection
            # when that selection scored this best, else left out
            best = {"evals": int(best_evals or r["evaluations"]), "y": best_y}
            mean = pd_float(r["Mean"])
            if abs(mean - best_y) <= 1e-6 * abs(best_y):
                x = [0] * dim
                for i in parse_element_text(str(r.get("elements") or "")):
                    x[i] = 1
                best["x"] = x
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


def pd_float(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _nanmean(x) -> float:
    v = np.asarray(x, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else math.nan


def _nanstd(x) -> float:
    v = np.asarray(x, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.std(ddof=1)) if v.size > 1 else math.nan


def table1(runs) -> "Any":
    """Aggregate run rows (a DataFrame with ``ROW_COLUMNS``) to the Table-1 layout."""
    import pandas as pd

    several = runs[runs["config"] != "full"].groupby("config", sort=False).size().max()
    several = bool(several and several > 1)
    out = []
    for config, g in runs.groupby("config", sort=False):
        rec: dict[str, Any] = {"config": config}
        for col in (*_STD_OF, "L_SLR", "gradient_steps", "overhead_seconds"):
            rec[col] = _nanmean(g[col])
        means = pd.to_numeric(g["Mean"], errors="coerce").to_numpy(dtype=np.float64)
        finite = np.where(np.isfinite(means), means, np.inf)
        best = int(np.argmin(finite)) if len(finite) else 0
        rec["elements"] = g["elements"].iloc[best] if len(g) else ""
        rec["best_seed"] = g["seed"].iloc[best] if len(g) else ""
        rec["seeds"] = len(g)
        errs = [f"seed {s}: {e}" if str(s) != "" else str(e)
                for s, e in zip(g["seed"], g["error"]) if isinstance(e, str) and e]
        rec["error"] = "; ".join(errs)
        if several:
            for col in _STD_OF:
                rec[f"{col}_std"] = _nanstd(g[col])
        fin = means[np.isfinite(means)]
        q25, med, q75 = (np.percentile(fin, [25, 50, 75]) if fin.size else (math.nan,) * 3)
        rec.update({"Mean_median": float(med), "Mean_q25": float(q25), "Mean_q75": float(q75),
                    "Mean_iqr": float(q75 - q25), "Mean_best": float(fin.min()) if fin.size else math.nan})
        ev = pd.to_numeric(g["evaluations"], errors="coerce").to_numpy(dtype=np.float64)
        ev = ev[np.isfinite(ev)]
        rec["evaluations_median"] = float(np.median(ev)) if ev.size else math.nan
        out.append(rec)
    cols = list(TABLE1_COLUMNS)
    if several:
        cols += [f"{c}_std" for c in _STD_OF]
    cols += list(_EXTRA) + list(_SEED_STATS)
    return pd.DataFrame(out, columns=cols)
