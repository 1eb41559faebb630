"""A sector scene's comparison, scored the way a designer reads it: ``beams.csv``, ``pareto.csv`` and
``pareto.png`` next to ``table1.csv`` (``docs/sector.md``; the tables' columns in
:mod:`arraysel.report.beams`).

The selections the runs made (every run's, each distinct one scored once) and ``sector.fresh_random``
fresh random selections are scored on the points' exact PSFs
(:meth:`~arraysel.objective.sector_objective.SectorObjective.beam_metrics`), after the runs, never
charged to them. An objective without ``beam_metrics`` gets none of these files.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math

import numpy as np

from arraysel.objective.contract import objective_info
from arraysel.report import beams as B
from arraysel.report import tables as reporting

__all__ = ["sector_tables", "effective_options", "beam_pattern_view", "beam_source", "BeamPolish", "beam_polish_plan",
           "prepare_beam_polish"]

_log = logging.getLogger(__name__)


def effective_options(row: dict) -> str:
    """A run's options with its selector's defaults filled in (``taper=none; rotation_deg=0.0``),
    so that the output states them; the row's own text when the selector is unknown."""
    given = row.get("options") or ""
    try:
        from arraysel.selectors.registry import get_registry

        opts = {k: o.default for k, o in get_registry()[str(row.get("selector") or row["config"])].options.items()}
        opts.update(json.loads(given) if given else {})
    except Exception:  # a config that is not a registered selector (full) or a plugin gone
        return str(given)
    return "; ".join(f"{k}={v}" for k, v in opts.items())


def beam_source(objective):
    """What scores a comparison's selections per beam: a sector scene's objective, a 1-D scene's
    :class:`~arraysel.objective.beams1d.PSFBeams` when its ``metrics.per_beam`` is true; else None."""
    from arraysel.objective.psf_objective import Objective

    inner = objective_info(objective).scene_objective  # separate or full-tx apertures: the scene's objective
    if not isinstance(inner, Objective):
        return None
    scene = inner.scene
    if scene.is_sector:
        return objective  # (with apertures, its beam_metrics images both)
    if scene.is_volume or not scene.value("metrics", "per_beam") or inner is not objective:
        return None
    from arraysel.objective.beams1d import PSFBeams

    return PSFBeams(objective, int(scene.value("metrics", "fresh_random")))


def point_info(objective) -> list[tuple]:
    """``(label, angle in x (deg), angle in y (deg), range (m))`` of each of the scene's points."""
    from arraysel.objective.beams1d import PSFBeams
    from arraysel.objective.sector_objective import point_label

    if isinstance(objective, PSFBeams):
        return objective.point_info()

    out = []
    for i in range(objective.n_points):
        u, v = objective.setup.direction_of(i)
        out.append((point_label(objective, i), math.degrees(math.asin(u)), math.degrees(math.asin(v)),
                    objective.setup.range_of(i)))
    return out


def sector_tables(objective, rows: list[dict]):
    """Score the selections of ``rows`` (the ``full`` row and every run's row) on the points of
    ``objective`` (a :func:`beam_source`): ``(beams, pareto)`` DataFrames (``beams.csv``,
    ``pareto.csv``; the store writes them)."""
    import pandas as pd

    n = int(objective.n_elements)
    keyed: dict[tuple, int] = {}
    masks = []
    for r in rows:
        sel = r.get("elements")
        if sel is not None and len(sel) and tuple(sel) not in keyed:
            keyed[tuple(sel)] = len(masks)
            masks.append(np.isin(np.arange(n), list(sel)))
    fresh = objective.fresh_random_masks()
    _log.info("scoring %d selections and %d fresh random ones on %d points", len(masks), len(fresh),
              objective.n_points)
    allm = np.array(masks + list(fresh), dtype=bool).reshape(-1, n)
    if not len(allm):
        return pd.DataFrame(columns=list(B.BEAMS_COLUMNS)), pd.DataFrame(columns=list(B.PARETO_COLUMNS))
    met = objective.beam_metrics(allm)
    pts = point_info(objective)
    beams, pareto = [], []
    for config, r in reporting.best_rows(rows).items():
        sel = r.get("elements")
        if sel is None or not len(sel):
            continue
        beams += B.beam_rows(config, r.get("seed"), effective_options(r), pts, met, keyed[tuple(sel)])
    for r in rows:
        sel = r.get("elements")
        if sel is None or not len(sel):
            continue
        pareto.append({"config": r["config"], "seed": r.get("seed"), "k": len(sel),
                       **B.summary(met, keyed[tuple(sel)]), "Mean": r.get("Mean")})
    if len(fresh):
        idx = np.arange(len(masks), len(allm))
        med = {k: np.median(v[idx], axis=0)[None] for k, v in met.items()}
        beams += B.beam_rows(B.FRESH_RANDOM, "", f"n={len(fresh)}; seed=0", pts, med, 0)
        sums = [B.summary(met, i) for i in idx]
        pareto.append({"config": B.FRESH_RANDOM, "seed": "", "k": int(objective.k), "Mean": math.nan,
                       **{k: float(np.median([s[k] for s in sums])) for k in sums[0]}})
    beams = pd.DataFrame(beams, columns=list(B.BEAMS_COLUMNS))
    return beams, pd.DataFrame(B.pareto_rows(pareto, int(objective.k)), columns=list(B.PARETO_COLUMNS))


def beam_pattern_view(objective, labels: list[str], masks: np.ndarray):
    """The figure of ``beampattern.png`` (:func:`arraysel.report.uv_plots.beam_pattern_figure`): each selection's
    two-way pattern over the visible region of the sector's beams (``region="visible"``), with the
    probe lattice's grating lobes at the centre frequency and the selection's own."""
    import torch

    from arraysel.physics.beampattern import BeamPattern
    from arraysel.report import uv_plots

    probe = objective.setup.probe
    acq = objective.scene.acquisition()
    sines = objective.pattern.sines
    sector = tuple(math.degrees(math.asin(s)) for s in sines)
    view = BeamPattern.from_probe(probe, acq, sector_deg=sector, region="visible", oversample=2.0,
                                  n_freq=objective.pattern.frequencies.numel(), dtype=torch.float32)
    w = torch.as_tensor(np.asarray(masks, dtype=np.float32))
    with torch.no_grad():
        pat = view.pattern(w).cpu().numpy()
        segs = [s.numpy() for s in view.grating_directions(w)]
    lobes = uv_plots.lattice_grating_lobes(acq.c / probe.fc, probe.pitch_x, probe.pitch_y, view.extent)
    return uv_plots.beam_pattern_figure(labels, pat, view.du.numpy(), view.dv.numpy(), sines, lobes, segs)


#: the polish's search settings on a sector scene (``docs/sector.md``): 32 swaps a round, screened on
#: the points within 1 dB of the worst (every point once the side lobes are that close: then no
#: screening), the best 8 scored on every point, on the smooth maximum of the points' side lobes at 0.3 dB;
#: 3/4 of each round's swaps proposed by the gradient of the screened points' side lobes (``guide``)
BEAM_POLISH_SETTINGS = {"batch": 32, "keep": 8, "screen_db": 1.0, "soft_db": 0.3, "patience": 60,
                        "width_weight": 300.0, "guide": 0.75}


@dataclasses.dataclass
class BeamPolish:
    """The polish of a run on a sector scene: the selector searches on the beam pattern for ``1 -
    share`` of its budget, then :func:`~arraysel.objective.sector_polish.polish_on_beams` spends the
    rest on the per-beam loss (width cap ``width_ratio`` x the fresh random median's mean -6 dB
    width), its per-beam scores charged to the budget (each selection scored on one point counts as
    one evaluation)."""

    share: float
    width_ratio: float
    cap: float | None = None

    def prepare(self, objective) -> None:
        """Before the budget starts: the points' fast models (from the cache, else built) and the cap."""
        for i in range(objective.n_points):
            objective.fast_point(i)
        fresh = objective.fresh_random_masks()
        if not len(fresh):
            fresh = objective.fresh_random_masks(16)
        bm = objective.beam_metrics(fresh)
        width = (bm["width_x_6dB"].mean(1) + bm["width_y_6dB"].mean(1)) / 2
        self.cap = self.width_ratio * float(np.median(width))

    def run(self, objective, budget, seed: int, start: list[int]) -> list[int]:
        """Polish ``start`` with what is left of the started ``budget``; the polished selection."""
        from arraysel.objective.sector_polish import polish_on_beams

        mask = np.zeros(int(objective.n_elements), dtype=bool)
        mask[list(start)] = True
        left = budget.remaining_evaluations()
        res = polish_on_beams(objective, mask, width_cap=self.cap, seconds=budget.remaining_seconds(), seed=seed,
                              evaluations=None if math.isinf(left) else max(1, int(left)), **BEAM_POLISH_SETTINGS)
        objective.evaluations += int(res["scored"])
        _log.info("polish on the per-beam loss: %.2f -> %.2f dB (worst side lobe %.2f dB, mean width %.3f mm; "
                  "%d rounds, %d moves taken, %d selection-points scored, %.0f s)", res["start_loss"], res["loss"],
                  res["worst_PSL_dB"], res["mean_width_m"] * 1e3, res["rounds"], res["accepted"], res["scored"],
                  res["seconds"])
        return [int(i) for i in np.flatnonzero(res["mask"])]


def beam_polish_plan(objective, selector_cls, options: dict) -> BeamPolish | None:
    """The :class:`BeamPolish` of a run of ``selector_cls`` with ``options`` (as given) on
    ``objective``, or None: only a sector scene's objective without constraints is polished on its
    points; the share is the run's ``polish`` option when given, else the scene's ``sector.polish``
    for a selector that searches (not a ``baseline``, spending evaluations)."""
    info = objective_info(objective)
    if info.kind != "beams" or info.aperture_mode is not None or objective.constraints is not None:
        return None
    scene = objective.scene
    if "polish" in options:
        share = float(options["polish"] or 0.0)
    elif selector_cls.baseline or not selector_cls.needs_evaluations:
        share = 0.0
    else:
        share = float(scene.value("sector", "polish"))
    if share <= 0:
        return None
    return BeamPolish(share, float(scene.value("sector", "polish_width_ratio")))


def prepare_beam_polish(objective, todo) -> float:
    """Before any run's clock (in the process that starts the runs): the points' fast models of a
    sector scene whose runs ``todo`` (``RunSpec``s) polish on the points, built and cached when they
    are not, so that each run's process (:meth:`BeamPolish.prepare`) only reads them; the seconds
    it took (0.0 when no run polishes)."""
    import time

    if not any(beam_polish_plan(objective, spec.selector, spec.options) is not None for spec in todo):
        return 0.0
    t0 = time.perf_counter()
    for i in range(objective.n_points):
        objective.fast_point(i)
    return time.perf_counter() - t0
