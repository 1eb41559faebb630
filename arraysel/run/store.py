"""The files of a comparison: :class:`CompareStore` writes them, each atomically
(:mod:`arraysel.io.atomic`, through :mod:`arraysel.report.tables` and
:func:`arraysel.report.plots.save_figure`), and reads back what a resumed folder holds.

The files are those of ``docs/selectors.md``: ``runs.csv``, ``table1.csv``, ``stats.csv``,
``trace.csv``, the IOHprofiler files under ``ioh/``, ``run.json`` and the figures. In memory a
row's ``elements`` is a :class:`~arraysel.selection.Selection` (``None`` for a run without one);
:func:`file_row` forms its text (``"0 2 4"``) where the row is written, and :meth:`CompareStore.previous`
reads it back into a ``Selection`` for a resumed folder: the one edge between the two forms.
"""
from __future__ import annotations

import contextlib
import logging
from pathlib import Path

import numpy as np

from arraysel.errors import ArrayselError, ParameterError, SelectionError, error_text as _error_text
from arraysel.objective.contract import element_layout, objective_info
from arraysel.report import plots
from arraysel.report import tables as reporting
from arraysel.report.columns import ROW_COLUMNS
from arraysel.run.outdir import remove_results
from arraysel.selection import Selection

__all__ = ["CompareStore", "file_row", "write_figures"]


def file_row(row: dict) -> dict:
    """``row`` as a file holds it: its ``elements`` (a :class:`Selection`, or ``None``) as text."""
    sel = row.get("elements")
    return {**row, "elements": sel.text if isinstance(sel, Selection) else ("" if sel is None else str(sel))}


class CompareStore:
    """The output folder ``out`` of one comparison (``problem``: the scene's name, for the
    IOHprofiler files). After each :meth:`save`, ``tables`` holds the tables written
    (:class:`arraysel.report.tables.WrittenTables`)."""

    def __init__(self, out: Path, budget, problem: str | None):
        self.out = Path(out)
        self.budget = budget
        self.problem = problem or "arraysel"
        self.tables: reporting.WrittenTables | None = None

    def start(self, force: bool) -> None:
        """Make the folder (``force``: remove the results it holds first)."""
        if force:
            remove_results(self.out)
        self.out.mkdir(parents=True, exist_ok=True)

    def previous(self, n_elements: int) -> tuple[list[dict], list[dict]]:
        """The finished, error-free runs of ``runs.csv`` (their ``elements`` as a :class:`Selection`)
        and their trace rows, for ``--resume``; ``([], [])`` without ``runs.csv``. A run whose
        ``trace.csv`` rows lack their ``end`` row, or hold more than one (the file was deleted,
        cut short or edited), is left out, so that it is run again: a line on stderr names those."""
        rows = self._previous_rows(n_elements)
        traces = self._previous_traces(n_elements)
        ends: dict[tuple, int] = {}
        for t in traces:
            if t.get("event") == "end":
                ends[(t["config"], t["seed"])] = ends.get((t["config"], t["seed"]), 0) + 1
        lost = [r for r in rows if ends.get((r["config"], r["seed"]), 0) != 1]
        if lost:
            names = ", ".join(f"{r['config']} seed {r['seed']}" for r in lost)
            logging.getLogger(__name__).warning(
                "arraysel compare: --resume: %d finished run(s) of runs.csv have no single end row in %s and are "
                "run again: %s", len(lost), self.out / "trace.csv", names)
        done = {(r["config"], r["seed"]) for r in rows if ends.get((r["config"], r["seed"]), 0) == 1}
        return [r for r in rows if (r["config"], r["seed"]) in done], \
            [t for t in traces if (t["config"], t["seed"]) in done]

    def _previous_rows(self, n_elements: int) -> list[dict]:
        """The finished, error-free rows of ``runs.csv`` (``[]`` without it)."""
        import pandas as pd

        runs_path = self.out / "runs.csv"
        if not runs_path.exists():
            return []
        try:
            reporting.check_table(runs_path, "runs")  # cut short or edited: damaged
            old = pd.read_csv(runs_path, dtype={"elements": str})  # "5" stays text
            missing = [c for c in ("config", "seed", "error", "options") if c not in old.columns]
            if missing:
                raise ValueError(f"no column(s) {missing}")
        except (ValueError, UnicodeDecodeError, pd.errors.ParserError) as exc:
            raise self._damaged(runs_path, exc) from None
        rows = []
        for rec in old.to_dict("records"):
            err = rec.get("error")
            if rec["config"] == "full" or (isinstance(err, str) and err.strip()):
                continue
            rec["seed"] = int(rec["seed"])
            rec["error"] = ""
            rec["options"] = rec["options"] if isinstance(rec.get("options"), str) else ""
            text = rec.get("elements")
            rec["elements"] = Selection.from_text(text, n_elements) if isinstance(text, str) and text.strip() else None
            rows.append({**{c: rec.get(c, "") for c in ROW_COLUMNS},  # and a scene's per-point columns
                         **{c: v for c, v in rec.items() if c not in ROW_COLUMNS}})
        return rows

    def _previous_traces(self, n_elements: int) -> list[dict]:
        """The rows of ``trace.csv`` (``[]`` without it), ``seed`` a whole number and an ``end``
        row's ``elements`` a :class:`Selection`."""
        import pandas as pd

        tpath = self.out / "trace.csv"
        if not tpath.exists():
            return []
        try:
            t = reporting.read_trace(tpath)
            traces = t.to_dict("records")
            for r in traces:
                r["seed"] = int(r["seed"])
                text = r.get("elements")
                r["elements"] = Selection.from_text(text, n_elements) if isinstance(text, str) and text.strip() \
                    else None
        except (ValueError, KeyError, UnicodeDecodeError, SelectionError, pd.errors.ParserError) as exc:
            raise self._damaged(tpath, exc) from None
        return traces

    @staticmethod
    def _damaged(path: Path, exc: BaseException) -> ParameterError:
        return ParameterError(f"--resume: {path} is damaged ({_error_text(exc)}); rerun with --force "
                              f"to start over, or choose another --out")

    def write_meta(self, meta: dict) -> None:
        """``run.json``."""
        with self._writing():
            reporting.write_json(self.out / "run.json", meta)

    def save(self, rows: list[dict], traces: list[dict]) -> reporting.WrittenTables:
        """Write the rows (the ``full`` row first) and their traces: ``trace.csv`` and ``ioh/``
        before ``runs.csv``, then ``table1.csv`` and ``stats.csv``."""
        with self._writing():
            self.tables = reporting.write_runs(self.out, [file_row(r) for r in rows],
                                               [file_row(t) for t in traces], self.budget, problem=self.problem)
        return self.tables

    @contextlib.contextmanager
    def _writing(self):
        """A file that cannot be written (a full disk, a quota) is an :class:`ArrayselError` naming
        it; every file is replaced whole or not at all, so those written before stay as they were."""
        try:
            yield
        except OSError as exc:
            where = exc.filename or self.out
            raise ArrayselError(f"cannot write {where}: {exc.strerror or _error_text(exc)}; the files written "
                                f"before it are whole: make room, then rerun the same command with --resume") \
                from exc

    def write_sector(self, objective, rows: list[dict], figures: bool = True) -> list[str]:
        """A sector scene's ``beams.csv``, ``pareto.csv`` and (``figures``) ``pareto.png``
        (:mod:`arraysel.run.sector_report`), then the files of its points
        (:mod:`arraysel.run.sector_points`); returns the problems met."""
        from arraysel.report.beams import pareto_figure
        from arraysel.report.tables import write_csv
        from arraysel.run.sector_points import point_files
        from arraysel.run.sector_report import sector_tables

        beams, pareto = sector_tables(objective, rows)
        with self._writing():
            write_csv(self.out / "beams.csv", beams)
            write_csv(self.out / "pareto.csv", pareto)
        problems = []
        if figures:
            try:
                plots.save_figure(pareto_figure(pareto), self.out / "pareto.png")
            except Exception as exc:  # a figure must never lose the tables
                problems.append(f"pareto.png: {type(exc).__name__}: {exc}")
        tables, draw = point_files(objective, rows, beams, figures)  # depths.csv/png, points-*.png, cysts.csv
        with self._writing():
            for name, table in tables.items():
                write_csv(self.out / name, table)
        for name, make in draw.items():
            try:
                plots.save_figure(make(), self.out / name)
            except Exception as exc:  # a figure must never lose the tables
                problems.append(f"{name}: {type(exc).__name__}: {exc}")
        return problems

    def write_figures(self, objective, selections: dict[str, Selection], table, trace) -> list[str]:
        """The figures (:func:`write_figures`); returns the problems met."""
        return write_figures(objective, selections, table, trace, self.out)


def write_figures(objective, selections: dict[str, Selection], table, trace, out: Path) -> list[str]:
    """Draw the figures of a comparison (:mod:`arraysel.report.plots`) from each config's
    :class:`~arraysel.selection.Selection` (``table``: its ``full`` row's Mean) and save them in
    ``out``: ``masks.png``, ``psfs.png`` (a 3-D scene: ``planes.png``), ``profiles.png``, ``trace.png``,
    ``anytime.png``. Returns a list of problems (empty when all went well): a figure never loses
    the tables."""
    out = Path(out)
    problems: list[str] = []
    try:
        _masks_figure(objective, selections, out)
    except Exception as exc:  # a figure must never lose the tables
        problems.append(f"masks.png: {type(exc).__name__}: {exc}")
    info = objective_info(objective)
    apertures = info.aperture_mode  # full-tx, separate (docs/apertures.md)
    if apertures:
        try:
            _apertures_figure(objective, selections, out)
        except Exception as exc:
            problems.append(f"apertures.png: {type(exc).__name__}: {exc}")
    labels = [config for config, sel in selections.items() if len(sel) and config != "full" and not apertures]
    masks = np.array([selections[config].mask for config in labels], dtype=bool)
    if len(labels) and info.kind == "planes":
        try:  # a 3-D scene: its planes and the C-plane's lateral profiles
            _planes_figures(objective, labels, masks, out)
        except Exception as exc:
            problems.append(f"planes/profiles: {type(exc).__name__}: {exc}")
    elif len(labels) and info.kind == "beams":  # a sector scene: pareto.png and its beam patterns
        try:
            from arraysel.run.sector_report import beam_pattern_view

            plots.save_figure(beam_pattern_view(objective, labels, masks), out / "beampattern.png")
        except Exception as exc:
            problems.append(f"beampattern.png: {type(exc).__name__}: {exc}")
    elif len(labels):
        try:
            _psf_figures(objective, labels, masks, out)
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


def _apertures_figure(objective, selections: dict[str, Selection], out: Path) -> None:
    """``apertures.png``: each selection's transmit and receive elements on the probe."""
    from arraysel.report.layout_plots import apertures_figure

    kept = [config for config, sel in selections.items() if len(sel)]
    n = objective.n_probe
    tx, rx = np.zeros((len(kept), n), dtype=bool), np.zeros((len(kept), n), dtype=bool)
    for i, c in enumerate(kept):
        t, r = objective.split(selections[c].indices)
        tx[i, t], rx[i, r] = True, True
    plots.save_figure(apertures_figure(kept, tx, rx, objective.inner.element_positions), out / "apertures.png")


def _masks_figure(objective, selections: dict[str, Selection], out: Path) -> None:
    grid, positions = element_layout(objective)
    kept = [config for config, sel in selections.items() if len(sel)]
    if grid is not None:  # a matrix probe: each selection as its ny x nx image
        plots.save_figure(plots.matrix_masks_figure(kept, np.array([selections[c].mask for c in kept]), grid),
                          out / "masks.png")
    elif positions is not None and np.ptp(np.asarray(positions)[:, 1]) > 0 and kept:
        # a 2-D array without a full grid (blank rows, an imported layout): drawn at its element positions
        from arraysel.report.layout_plots import layout_masks_figure

        plots.save_figure(layout_masks_figure(kept, np.array([selections[c].mask for c in kept]), positions),
                          out / "masks.png")
    else:
        plots.save_figure(plots.selections_figure(selections), out / "masks.png")


def _planes_figures(objective, labels: list[str], masks: np.ndarray, out: Path) -> None:
    import torch

    with torch.no_grad():
        planes = {k: v.cpu().numpy() for k, v in objective.planes(masks.astype(np.float32)).items()}
        ref = {k: v.cpu().numpy() for k, v in objective.reference_planes().items()}
    plots.save_figure(plots.planes_figure(labels, planes, objective.coords, ref), out / "planes.png")
    if "xy" in planes:
        plots.save_figure(plots.lateral_profiles_figure(labels, planes["xy"], objective.coords["xy"], ref["xy"]),
                          out / "profiles.png")


def _psf_figures(objective, labels: list[str], masks: np.ndarray, out: Path) -> None:
    import torch

    pitch = objective_info(objective).pitch
    with torch.no_grad():
        kern = objective.kernels(masks).detach().cpu().numpy()
        ref = objective.reference_kernel().detach().cpu().numpy()
    plots.save_figure(plots.psfs_figure(labels, kern, ref, pitch), out / "psfs.png")
    plots.save_figure(plots.profiles_figure(labels, kern, ref, pitch), out / "profiles.png")
