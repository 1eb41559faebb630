"""Tables and figures written by ``arraysel compare`` (every file written atomically).

Files (see ``docs/selectors.md``):

* ``runs.csv`` — one row per (config, seed) run plus ``full``; columns
  :data:`arraysel.run.experiment.ROW_COLUMNS`.
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
* figures: ``masks.png``, ``psfs.png`` (|PSF| in dB, 40 dB range),
  ``profiles.png`` (lateral/axial profiles vs the full array),
  ``trace.png`` (best Mean vs time, every run), ``anytime.png``
  (:func:`plot_anytime`: median and IQR over seeds vs time and vs
  evaluations, ECDF of (run, target) pairs over time).
"""
from __future__ import annotations

import contextvars
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_write_text", "write_json", "write_csv", "write_runs", "write_ioh", "table1",
           "make_figures", "plot_anytime", "TABLE1_COLUMNS"]

TABLE1_COLUMNS = ("config", "L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i", "Mean", "seconds",
                  "evaluations", "elements")
_STD_OF = ("L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i", "Mean", "seconds", "evaluations")
#: where :func:`collect_figures` keeps the figures :func:`make_figures` saves (None: not kept)
_FIGURES: "contextvars.ContextVar[dict | None]" = contextvars.ContextVar("arraysel_figures", default=None)
_EXTRA = ("L_SLR", "gradient_steps", "overhead_seconds", "seeds", "best_seed", "error")
#: statistics over seeds (always written): median, quartiles, IQR and best of Mean, median evaluations
_SEED_STATS = ("Mean_median", "Mean_q25", "Mean_q75", "Mean_iqr", "Mean_best", "evaluations_median")


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to a temporary file next to ``path`` and ``os.replace`` it."""
    from arraysel.io.atomic import atomic_write_text as _write

    _write(path, text)


def write_json(path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, default=str) + "\n")


def write_csv(path, df) -> None:
    atomic_write_text(path, df.to_csv(index=False))


def write_runs(out: Path, rows: list[dict], trace: list[dict], budget, problem: str | None = None) -> None:
    """Write ``runs.csv``, ``table1.csv``, ``trace.csv`` and the IOHprofiler files (``ioh/``)."""
    import pandas as pd

    from arraysel.run.experiment import ROW_COLUMNS, TRACE_COLUMNS
    # a several-point scene's per-point columns ("L_PSF@p0", ..., "Mean@worst") follow ROW_COLUMNS
    extra = list(dict.fromkeys(k for r in rows for k in r if k not in ROW_COLUMNS))
    runs = pd.DataFrame(rows, columns=list(ROW_COLUMNS) + extra)
    write_csv(out / "runs.csv", runs)
    write_csv(out / "table1.csv", table1(runs))
    write_csv(out / "trace.csv", pd.DataFrame(trace, columns=list(TRACE_COLUMNS)))
    write_ioh(out / "ioh", rows, trace, problem or "arraysel")


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
    in ``runs.csv``, ``best.y`` = its ``Mean``, ``best.x`` = its 0/1 mask),
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
                lines.append(f"{ev} {float(t['best_Mean']):.10e} {float(t['seconds']):.6f}")
                if float(t["best_Mean"]) < best_y:
                    best_y, best_evals = float(t["best_Mean"]), ev
            x = [0] * dim
            for i in str(r.get("elements") or "").split():
                x[int(i)] = 1
            jruns.append({"instance": 1, "evals": int(r["evaluations"]),
                          "best": {"evals": int(best_evals or r["evaluations"]), "y": pd_float(r["Mean"]),
                                   "x": x},
                          "seed": int(r["seed"])})
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
        for col in ("L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i", "Mean", "seconds", "evaluations",
                    "L_SLR", "gradient_steps", "overhead_seconds"):
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


# ---------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------

def _save(fig, path: Path) -> None:
    import io

    from arraysel.io.atomic import atomic_write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())
    sink = _FIGURES.get()
    if sink is not None:
        sink[Path(path).stem] = fig


def collect_figures():
    """Context manager: the figures saved inside it are also kept, ``{file stem: Figure}``
    (the Python API returns them to notebooks)."""
    import contextlib

    @contextlib.contextmanager
    def _cm():
        sink: dict = {}
        token = _FIGURES.set(sink)
        try:
            yield sink
        finally:
            _FIGURES.reset(token)
    return _cm()


def _masks(table, n: int) -> tuple[list[str], np.ndarray]:
    labels, masks = [], []
    for config, elements in zip(table["config"], table["elements"]):
        if not isinstance(elements, str) or not elements.strip():
            continue
        m = np.zeros(n, dtype=bool)
        m[[int(i) for i in elements.split()]] = True
        labels.append(str(config))
        masks.append(m)
    return labels, np.array(masks).reshape(len(masks), n)


def _db(k: np.ndarray, ref_peak: float) -> np.ndarray:
    mag = np.abs(k) / max(ref_peak, np.finfo(float).tiny)
    return 20 * np.log10(np.maximum(mag, 1e-12))


def make_figures(objective, table, trace, out: Path) -> list[str]:
    """Write the PNG figures; return a list of problems (empty when all went well).

    Uses matplotlib's object API with the Agg canvas (no display, no pyplot state).
    """
    from matplotlib.figure import Figure

    problems: list[str] = []
    n = int(objective.n_elements)
    labels, masks = _masks(table, n)

    try:
        fig = Figure(figsize=(8, 0.4 * max(len(labels), 1) + 1.2))
        ax = fig.subplots()
        if len(labels):
            ax.imshow(masks.astype(float), aspect="auto", cmap="Greys", vmin=0, vmax=1,
                      interpolation="nearest")
        ax.set_yticks(range(len(labels)), labels)
        ax.set_xlabel("element index")
        ax.set_title("active elements")
        _save(fig, out / "masks.png")
    except Exception as exc:  # a figure must never lose the tables
        problems.append(f"masks.png: {type(exc).__name__}: {exc}")

    keep = [i for i, lab in enumerate(labels) if lab != "full"]
    labels, masks = [labels[i] for i in keep], masks[keep]
    if len(labels):
        try:
            import torch
            with torch.no_grad():
                kern = objective.kernels(masks).detach().cpu().numpy()
                ref = objective.reference_kernel().detach().cpu().numpy()
            peak = float(np.abs(ref).max())
            cols = min(4, len(labels) + 1)
            rows_ = math.ceil((len(labels) + 1) / cols)
            fig = Figure(figsize=(3 * cols, 3 * rows_))
            axes = np.atleast_1d(fig.subplots(rows_, cols)).ravel()
            for ax, (lab, kk) in zip(axes, [("full (reference)", ref)] + list(zip(labels, kern))):
                im = ax.imshow(_db(kk, peak), vmin=-40, vmax=0, cmap="gray")
                ax.set_title(lab, fontsize=8)
                ax.set_xticks([])
                ax.set_yticks([])
            for ax in axes[len(labels) + 1:]:
                ax.axis("off")
            fig.colorbar(im, ax=list(axes), label="dB", shrink=0.8)
            _save(fig, out / "psfs.png")

            fig = Figure(figsize=(10, 4))
            ax_l, ax_a = fig.subplots(1, 2)
            for lab, kk in [("full", ref)] + list(zip(labels, kern)):
                r, c = np.unravel_index(int(np.argmax(np.abs(kk))), kk.shape)
                style = dict(color="k", lw=2) if lab == "full" else dict(lw=1)
                ax_l.plot(_db(kk[r, :], peak), label=lab, **style)
                ax_a.plot(_db(kk[:, c], peak), label=lab, **style)
            for ax, what in ((ax_l, "lateral"), (ax_a, "axial")):
                ax.set_ylim(-60, 3)
                ax.set_xlabel(f"{what} pixel")
                ax.set_ylabel("dB")
                ax.set_title(f"{what} profile through the peak")
            ax_a.legend(fontsize=7)
            _save(fig, out / "profiles.png")
        except Exception as exc:
            problems.append(f"psfs/profiles: {type(exc).__name__}: {exc}")

    try:
        fig = Figure(figsize=(7, 4.5))
        ax = fig.subplots()
        if trace is not None and len(trace):
            for (config, seed), g in trace.groupby(["config", "seed"], sort=False):
                g = g.sort_values("seconds")
                x = np.maximum(g["seconds"].to_numpy(float), 1e-4)
                y = g["best_Mean"].to_numpy(float)
                line, = ax.step(x, y, where="post", label=f"{config} (seed {seed})")
                ax.plot(x[-1:], y[-1:], marker="o", ms=4, color=line.get_color())  # single-point runs too
            ax.set_xscale("log")
            ax.legend(fontsize=7)
        full = table[table["config"] == "full"]
        if len(full) and np.isfinite(full["Mean"].iloc[0]):
            ax.axhline(float(full["Mean"].iloc[0]), color="k", ls="--", lw=1, label="full")
        ax.set_xlabel("seconds")
        ax.set_ylabel("best Mean")
        ax.set_title("best Mean vs time")
        _save(fig, out / "trace.png")
    except Exception as exc:
        problems.append(f"trace.png: {type(exc).__name__}: {exc}")
    try:
        full = table[table["config"] == "full"]
        ref = float(full["Mean"].iloc[0]) if len(full) else None
        _save(plot_anytime(trace, full_mean=ref), out / "anytime.png")
    except Exception as exc:
        problems.append(f"anytime.png: {type(exc).__name__}: {exc}")
    return problems


# ---------------------------------------------------------------------------
# anytime statistics over seeds
# ---------------------------------------------------------------------------

def _best_at(g, x: np.ndarray, column: str) -> np.ndarray:
    """Best-so-far Mean of one run at the points ``x`` of ``column`` (+inf before its first row;
    after its last row the run's final best holds)."""
    g = g.sort_values([column, "best_Mean"], ascending=[True, False])
    xs = g[column].to_numpy(float)
    ys = np.minimum.accumulate(g["best_Mean"].to_numpy(float))
    idx = np.searchsorted(xs, x, side="right") - 1
    return np.where(idx >= 0, ys[np.clip(idx, 0, None)], np.inf)


def _grid(values: np.ndarray, points: int = 200) -> np.ndarray:
    v = values[np.isfinite(values) & (values > 0)]
    if not v.size:
        return np.array([1.0])
    lo, hi = float(v.min()), float(v.max())
    if hi <= lo:
        hi = lo * 1.01
    return np.unique(np.concatenate([np.geomspace(lo, hi, points), v]))


def ecdf_targets(trace, count: int = 51) -> np.ndarray:
    """Targets of the ECDF: ``count`` values spaced evenly in log(Mean) between the best
    Mean any run reached and the largest first value of a run."""
    firsts = trace.sort_values("evaluations").groupby(["config", "seed"], sort=False)["best_Mean"].first()
    lo = float(trace["best_Mean"].min())
    hi = float(firsts.max())
    if not (np.isfinite(lo) and np.isfinite(hi)) or lo <= 0 or hi <= lo:
        return np.array([lo])
    return np.geomspace(hi, lo, count)


def plot_anytime(trace, full_mean: float | None = None, targets: np.ndarray | None = None):
    """Anytime comparison over seeds; returns a matplotlib ``Figure`` (the caller saves it).

    Panels: per config, the median over its runs of the best-so-far Mean with
    the interquartile band, (a) against wall seconds and (b) against
    evaluations (log x), and (c) the ECDF of (run, target) pairs reached
    against seconds, COCO / IOHanalyzer style: for each run and each target of
    :func:`ecdf_targets`, the time the run's best first reached the target;
    the curve is the fraction of all (run, target) pairs of the config reached
    by then. Every config appears, runs of one evaluation included (their curve
    starts at that point, marked, and holds to the end of the x range).
    ``full_mean`` draws the full array's Mean as a dashed line.
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=(15, 4.6))
    ax_t, ax_e, ax_c = fig.subplots(1, 3)
    if trace is None or not len(trace):
        for ax in (ax_t, ax_e, ax_c):
            ax.text(0.5, 0.5, "no trace", ha="center", va="center", transform=ax.transAxes)
        return fig
    trace = trace[np.isfinite(trace["best_Mean"].astype(float))].copy()
    trace["seconds"] = np.maximum(trace["seconds"].astype(float), 1e-4)
    trace["evaluations"] = np.maximum(trace["evaluations"].astype(float), 1.0)
    targets = ecdf_targets(trace) if targets is None else np.asarray(targets, dtype=float)
    colours = {}
    for config, gc in trace.groupby("config", sort=False):
        runs = [g for _, g in gc.groupby("seed", sort=False)]
        colour = None
        for ax, column, label in ((ax_t, "seconds", "seconds"), (ax_e, "evaluations", "evaluations")):
            x = _grid(trace[column].to_numpy(float))
            y = np.array([_best_at(g, x, column) for g in runs])
            with np.errstate(invalid="ignore"):
                q25, med, q75 = np.percentile(y, [25, 50, 75], axis=0)
            ok = np.isfinite(med)
            line, = ax.step(x[ok], med[ok], where="post", color=colour, lw=1.5,
                            label=f"{config} ({len(runs)} run{'s' if len(runs) != 1 else ''})")
            colour = line.get_color()
            band = ok & np.isfinite(q25) & np.isfinite(q75)
            ax.fill_between(x[band], q25[band], q75[band], step="post", color=colour, alpha=0.2, lw=0)
            if ok.any():
                first = int(np.flatnonzero(ok)[0])
                ax.plot([x[first]], [med[first]], marker="o", ms=4, color=colour)
            ax.set_xscale("log")
            ax.set_xlabel(label)
        colours[config] = colour
        # ECDF of (run, target) pairs over time
        hits = []
        for g in runs:
            g = g.sort_values("seconds")
            best = np.minimum.accumulate(g["best_Mean"].to_numpy(float))
            secs = g["seconds"].to_numpy(float)
            for tgt in targets:
                reached = np.flatnonzero(best <= tgt)
                hits.append(secs[reached[0]] if reached.size else np.inf)
        hits = np.sort(np.asarray(hits, dtype=float))
        x = _grid(trace["seconds"].to_numpy(float))
        frac = np.searchsorted(hits, x, side="right") / max(len(hits), 1)
        ax_c.step(x, frac, where="post", color=colour, label=config)
        ax_c.plot([x[-1]], [frac[-1]], marker="o", ms=4, color=colour)
    for ax, what in ((ax_t, "time"), (ax_e, "evaluations")):
        if full_mean is not None and np.isfinite(full_mean):
            ax.axhline(full_mean, color="k", ls="--", lw=1, label="full array")
        ax.set_yscale("log")
        ax.set_ylabel("best Mean so far (median, IQR band)")
        ax.set_title(f"best Mean vs {what}")
    ax_t.legend(fontsize=7)
    ax_c.set_xscale("log")
    ax_c.set_ylim(-0.02, 1.02)
    ax_c.set_xlabel("seconds")
    ax_c.set_ylabel("fraction of (run, target) pairs reached")
    ax_c.set_title(f"ECDF, {len(targets)} targets in [{targets.min():.3g}, {targets.max():.3g}]")
    fig.tight_layout()
    return fig
