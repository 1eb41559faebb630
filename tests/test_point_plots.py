"""The points of a sector scene's comparison (arraysel.report.point_plots, arraysel.run.sector_points,
docs/sector.md): each point's image at 40 and 60 dB, the per-depth table, cysts.csv; the figures'
data against the images the scene scores."""
from __future__ import annotations

import copy
import json

import numpy as np
import pandas as pd
import pytest
import torch

from arraysel.errors import ParameterError
from arraysel.report.point_plots import depth_table, image_db, point_images_figure

from test_cysts import TINY


def test_image_db_is_relative_to_the_peak_and_clipped():
    img = np.array([[1.0, 0.1], [0.001, 1e-9]]) * (2 + 1j)
    got = image_db(img, 40.0)
    assert got == pytest.approx(np.array([[0.0, -20.0], [-40.0, -40.0]]))
    with pytest.raises(ParameterError, match="dynamic_range"):
        image_db(img, 0.0)
    with pytest.raises(ParameterError, match="all zero"):
        image_db(np.zeros((2, 2)), 40.0)


def test_point_images_figure_panels_and_data():
    rng = np.random.default_rng(0)
    imgs = rng.standard_normal((2, 3, 5, 7)) + 1j * rng.standard_normal((2, 3, 5, 7))
    ext = [(-1.0, 1.0, -2.0, 2.0)] * 3
    fig = point_images_figure(["full", "ste"], ["a", "b", "c"], imgs, ext, 60.0)
    panels = [ax for ax in fig.axes if ax.images and ax.get_title()]
    assert [ax.get_title() for ax in panels] == [f"{s}\n{p}" for s in ("full", "ste") for p in "abc"]
    for n, ax in enumerate(panels):
        assert np.asarray(ax.images[0].get_array()) == pytest.approx(image_db(imgs[n // 3, n % 3], 60.0))
        assert tuple(ax.images[0].get_extent()) == ext[n % 3]
    with pytest.raises(ParameterError, match="images must have shape"):
        point_images_figure(["full"], ["a"], imgs, ext[:1])


def test_depth_table_one_row_per_config_one_column_per_point_and_metric():
    rows = []
    for config, w in (("full", 1.0), ("ste", 1.5)):
        for pt, r, ax in (("0,0@50mm", 50.0, 0.0), ("0,0@20mm", 20.0, 0.0), ("13,0@50mm", 50.0, 13.0)):
            rows.append({"config": config, "point": pt, "theta_x_deg": ax, "theta_y_deg": 0.0, "range_mm": r,
                         "width_x_mm": w * r / 20, "width_y_mm": w, "PSL_dB": -30 + r / 10, "ISLR_dB": -20.0,
                         "GLL_dB": -240.0})
    t = depth_table(pd.DataFrame(rows))
    assert list(t["config"]) == ["full", "ste"]
    assert [c for c in t.columns if c.startswith("width_x_mm@")] == \
        ["width_x_mm@0,0@20mm", "width_x_mm@0,0@50mm", "width_x_mm@13,0@50mm"]   # by range
    assert t.loc[1, "width_x_mm@0,0@50mm"] == pytest.approx(1.5 * 50 / 20)
    assert t.loc[0, "PSL_dB@0,0@20mm"] == pytest.approx(-28.0)


@pytest.mark.slow
def test_tiny_sector_scene_with_cysts_through_compare(tmp_path):
    from arraysel.objective.build import build_objective
    from arraysel.objective.sector_objective import point_label
    from arraysel.report.plots import collect_figures
    from arraysel.run.compare import compare
    from arraysel.run.sector_points import FRESH_ONE
    from arraysel.scenes.schema import load_scene
    from arraysel.selectors.contract import Budget

    tree = copy.deepcopy(TINY)
    tree["cysts"] = {"radius": "2.5 mm", "realisations": 4}
    obj = build_objective(load_scene(tree), dtype=torch.float32)
    with collect_figures() as figs:
        compare(obj, ["random", "uniform", "swap"], out_dir=tmp_path, seeds=[0], budget=Budget(evaluations=30),
                progress=False)
    assert not json.loads((tmp_path / "run.json").read_text()).get("figure_errors")
    for name in ("points-40dB.png", "points-60dB.png", "depths.png", "cysts.png"):
        assert (tmp_path / name).stat().st_size > 1000, name
    cysts = pd.read_csv(tmp_path / "cysts.csv")
    assert list(cysts["config"].unique()) == ["full", "random", "uniform", "swap", FRESH_ONE]
    assert (cysts.groupby("config").size() == 2).all() and (cysts["radius_mm"] == 2.5).all()
    assert np.isfinite(cysts["CR_dB"]).all() and cysts["gCNR"].between(0, 1).all()
    depths = pd.read_csv(tmp_path / "depths.csv")
    beams = pd.read_csv(tmp_path / "beams.csv")
    full = beams[beams["config"] == "full"].set_index("point")
    row = depths[depths["config"] == "full"].iloc[0]
    for pt in full.index:
        assert row[f"width_x_mm@{pt}"] == pytest.approx(full.loc[pt, "width_x_mm"])
        assert row[f"PSL_dB@{pt}"] == pytest.approx(full.loc[pt, "PSL_dB"])
    # the panels show the images the scene scores: the full array's, point by point
    mask = np.ones((1, obj.n_elements), bool)
    for dr, stem in ((40.0, "points-40dB"), (60.0, "points-60dB")):
        panels = [ax for ax in figs[stem].axes if ax.images and ax.get_title()]
        assert len(panels) == 5 * obj.n_points
        for i in range(obj.n_points):
            want = image_db(obj.point_images(mask, i)[0].numpy(), dr)
            assert panels[i].get_title() == f"full\n{point_label(obj, i)}"
            assert np.asarray(panels[i].images[0].get_array()) == pytest.approx(want, abs=1e-3)
    # and the cysts are those of the same images
    from arraysel.objective.cysts import score_cysts

    again = score_cysts(obj, mask)
    assert cysts[cysts["config"] == "full"]["CR_dB"].to_numpy() == pytest.approx(again["CR_dB"][0], abs=1e-3)
    panels = [ax for ax in figs["cysts"].axes if ax.images]
    assert len(panels) == 5 and panels[0].get_title().startswith("full\nCR ")
