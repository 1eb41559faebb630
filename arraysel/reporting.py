"""Tables and figures written by ``arraysel compare`` (every file written atomically).

Files (see ``docs/selectors.md``):

* ``runs.csv`` — one row per (config, seed) run plus ``full``; columns
  :data:`arraysel.runner.ROW_COLUMNS`.
* ``table1.csv`` — one row per config: ``config,L_PSF,L_contrast,L_SLR_q,
  L_SLR_i,Mean,seconds,evaluations,elements`` (means over seeds), then
  ``<col>_std`` columns when several seeds ran, then ``L_SLR, gradient_steps,
  overhead_seconds, seeds, best_seed, error``. ``elements`` is the selection
  of the best seed.
* ``trace.csv`` — ``config,seed,seconds,evaluations,gradient_steps,best_Mean``,
  one row per improvement of the best evaluated selection.
* ``trace_nevergrad.csv`` — the same trace in nevergrad's benchmark columns
  ``optimizer_name,budget,loss,elapsed_time,elapsed_budget,seed`` (loadable by
  IOHanalyzer): ``budget`` is the evaluation budget (or the evaluations used
  when unlimited), ``elapsed_budget`` the evaluations used at that point.
* figures: ``masks.png``, ``psfs.png`` (|PSF| in dB, 40 dB range),
  ``profiles.png`` (lateral/axial profiles vs the full array),
  ``trace.png`` (best Mean vs time).
"""
from __future__ import annotations

import contextvars
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_write_text", "write_json", "write_csv", "write_runs", "table1", "make_figures",
           "TABLE1_COLUMNS"]

TABLE1_COLUMNS = ("config", "L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i", "Mean", "seconds",
                  "evaluations", "elements")
_STD_OF = ("L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i", "Mean", "seconds", "evaluations")
#: where :func:`collect_figures` keeps the figures :func:`make_figures` saves (None: not kept)
_FIGURES: "contextvars.ContextVar[dict | None]" = contextvars.ContextVar("arraysel_figures", default=None)
_EXTRA = ("L_SLR", "gradient_steps", "overhead_seconds", "seeds", "best_seed", "error")


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to a temporary file next to ``path`` and ``os.replace`` it."""
    from .atomic import atomic_write_text as _write

    _write(path, text)


def write_json(path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, default=str) + "\n")


def write_csv(path, df) -> None:
    atomic_write_text(path, df.to_csv(index=False))


def _nevergrad(trace, budget) -> "Any":
    import pandas as pd

    rows = []
    for r in trace:
        limit = budget.evaluations if budget.evaluations is not None else r["evaluations"]
        rows.append({"optimizer_name": r["config"], "budget": limit, "loss": r["best_Mean"],
                     "elapsed_time": r["seconds"], "elapsed_budget": r["evaluations"], "seed": r["seed"]})
    from .runner import NEVERGRAD_COLUMNS
    return pd.DataFrame(rows, columns=list(NEVERGRAD_COLUMNS))


def write_runs(out: Path, rows: list[dict], trace: list[dict], budget) -> None:
    """Write ``runs.csv``, ``table1.csv``, ``trace.csv`` and ``trace_nevergrad.csv``."""
    import pandas as pd

    from .runner import ROW_COLUMNS, TRACE_COLUMNS
    # a several-point scene's per-point columns ("L_PSF@p0", ..., "Mean@worst") follow ROW_COLUMNS
    extra = list(dict.fromkeys(k for r in rows for k in r if k not in ROW_COLUMNS))
    runs = pd.DataFrame(rows, columns=list(ROW_COLUMNS) + extra)
    write_csv(out / "runs.csv", runs)
    write_csv(out / "table1.csv", table1(runs))
    write_csv(out / "trace.csv", pd.DataFrame(trace, columns=list(TRACE_COLUMNS)))
    write_csv(out / "trace_nevergrad.csv", _nevergrad(trace, budget))


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
        out.append(rec)
    cols = list(TABLE1_COLUMNS)
    if several:
        cols += [f"{c}_std" for c in _STD_OF]
    cols += list(_EXTRA)
    return pd.DataFrame(out, columns=cols)


# ---------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------

def _save(fig, path: Path) -> None:
    import io

    from .atomic import atomic_write_bytes

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
                ax.step(np.maximum(g["seconds"].to_numpy(float), 1e-4), g["best_Mean"].to_numpy(float),
                        where="post", label=f"{config} (seed {seed})")
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
    return problems
