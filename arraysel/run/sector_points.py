"""The points of a sector scene's comparison, drawn and checked on a handful of selections
(``docs/sector.md``): ``points-40dB.png``, ``points-60dB.png``, ``depths.csv``, ``depths.png`` and,
with a ``[cysts]`` section, ``cysts.csv`` and ``cysts.png`` (:mod:`arraysel.report.point_plots`,
:mod:`arraysel.objective.cysts`).

The selections are the table's (the full array and each configuration's listed selection, those of
``beams.csv``) and one fresh random selection (the first of ``sector.fresh_random``'s, seed 0).
Their images are the points' images the scene scores
(:meth:`~arraysel.objective.sector_objective.SectorObjective.point_images`: the fast path when a
point's model is cached, else the exact path), computed once for the figures and the cysts.
:func:`point_files` gives the tables and the figures; the store
(:meth:`~arraysel.run.store.CompareStore.write_sector`) writes them.
"""
from __future__ import annotations

import functools
import logging

import numpy as np

from arraysel.report import tables as reporting
from arraysel.run.sector_report import point_info

__all__ = ["FRESH_ONE", "point_selections", "point_files"]

_log = logging.getLogger(__name__)
#: the label of the one fresh random selection
FRESH_ONE = "random (fresh, seed 0)"
#: the dynamic ranges of the points' figures, dB
DYNAMIC_RANGES = (40.0, 60.0)


def point_selections(objective, rows: list[dict]) -> tuple[list[str], list, np.ndarray]:
    """``(labels, seeds, masks (B, Ne) bool)``: each configuration's listed selection of ``rows``
    (the ``full`` row among them) and one fresh random selection."""
    n = int(objective.n_elements)
    labels, seeds, masks = [], [], []
    for config, r in reporting.best_rows(rows).items():
        sel = r.get("elements")
        if sel is None or not len(sel):
            continue
        labels.append(config)
        seeds.append(r.get("seed"))
        masks.append(np.isin(np.arange(n), list(sel)))
    fresh = objective.fresh_random_masks(1, seed=0)
    labels.append(FRESH_ONE)
    seeds.append(0)
    masks.append(fresh[0])
    return labels, seeds, np.array(masks, dtype=bool).reshape(-1, n)


def point_files(objective, rows: list[dict], beams, figures: bool = True) -> tuple[dict, dict]:
    """The files of the module docstring for a sector scene's objective (none for another
    objective, or one seen through separate apertures); ``beams``: the ``beams.csv`` DataFrame. Returns ``({file name: DataFrame},
    {file name: a function that draws its Figure})``: the store writes them."""
    from arraysel.objective.cysts import CystSettings, score_cysts
    from arraysel.objective.contract import objective_info
    from arraysel.report import point_plots as pp

    info = objective_info(objective)
    if info.kind != "beams" or info.aperture_mode is not None:   # a sector scene's own objective only
        return {}, {}
    tables = {"depths.csv": pp.depth_table(beams)}
    cysts = CystSettings.from_scene(objective.scene)
    if not figures and cysts is None:
        return tables, {}
    labels, seeds, masks = point_selections(objective, rows)
    wanted = list(range(objective.n_points)) if figures else list(cysts.points)
    _log.info("imaging %d selections on %d points for the points' figures and cysts", len(labels), len(wanted))
    images = {i: objective.point_images(masks, i).detach().cpu().numpy() for i in wanted}
    pts = point_info(objective)
    if cysts is not None:
        import pandas as pd

        met = score_cysts(objective, masks, cysts, images=images)
        cpts = [pts[i] for i in cysts.points]
        rows_c = [row for b, (lab, seed) in enumerate(zip(labels, seeds))
                  for row in pp.cyst_rows(lab, seed, cpts, cysts.radius, met, b)]
        tables["cysts.csv"] = pd.DataFrame(rows_c, columns=list(pp.CYSTS_COLUMNS))
    if not figures:
        return tables, {}
    setup = objective.setup
    stack = np.stack([images[i] for i in range(objective.n_points)], axis=1)   # (B, P, H, W)
    extents = [tuple(float(a) * setup.range_of(i) * 1e3 for a in (setup.u[0], setup.u[-1], setup.v[0], setup.v[-1]))
               for i in range(objective.n_points)]
    names = [p[0] for p in pts]
    draw = {f"points-{dr:g}dB.png": functools.partial(pp.point_images_figure, labels, names, stack, extents, dr)
            for dr in DYNAMIC_RANGES}
    draw["depths.png"] = functools.partial(pp.depth_figure, beams)
    if cysts is not None:
        draw["cysts.png"] = _cyst_view(objective, cysts, labels, images, met)
    return tables, draw


def _cyst_view(objective, cysts, labels: list[str], images: dict, met: dict):
    """``cysts.png``: one realisation of one cyst (the one nearest the cysts' median range, on the
    axis first) through each selection, its CR and gCNR in the titles."""
    from arraysel.objective.cysts import CystPhantom
    from arraysel.report import point_plots as pp

    setup = objective.setup
    ranges = [setup.range_of(i) for i in cysts.points]
    mid = float(np.median(ranges))
    j = min(range(len(ranges)), key=lambda n: (abs(ranges[n] - mid), sum(map(abs, setup.direction_of(cysts.points[n])))))
    i = cysts.points[j]
    ph = CystPhantom(setup.u, setup.v, setup.direction_of(i), setup.range_of(i), objective.scene.sector_geometry()["lobe"],
                     cysts, index=i)
    env = np.stack([ph.images(img)[0] for img in images[i]])
    r = setup.range_of(i) * 1e3
    u0, v0 = setup.direction_of(i)
    titles = [f"{lab}\nCR {met['CR_dB'][b, j]:.1f} dB, gCNR {met['gCNR'][b, j]:.2f}" for b, lab in enumerate(labels)]
    return functools.partial(pp.cyst_images_figure, labels, env, (setup.u[0] * r, setup.u[-1] * r, setup.v[0] * r,
                             setup.v[-1] * r), cysts.radius * 1e3, (u0 * r, v0 * r), 40.0, titles)
