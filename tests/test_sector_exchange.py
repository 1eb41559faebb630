"""The exchange polish of a sector scene (``arraysel.run.sector_exchange``): random points in
the sector, a scan that equals the exact per-beam metrics, and rounds that add the worst scanned
points above the scene's own worst to the points polished on."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from arraysel.errors import ParameterError
from arraysel.run.sector_exchange import exchange_polish, random_sector_points, scan_points
from arraysel.objective.sector_objective import SectorObjective
from arraysel.run.sector_report import BeamPolish
from arraysel.scenes.schema import load_scene
from scene_texts import TINY_SECTOR


def _tiny():
    return load_scene(copy.deepcopy(TINY_SECTOR))


def _mask(seed: int = 0, n: int = 64, k: int = 16) -> np.ndarray:
    m = np.zeros(n, dtype=bool)
    m[np.random.default_rng(seed).choice(n, k, replace=False)] = True
    return m


def test_random_points_lie_in_the_sector_and_the_ranges():
    pts = random_sector_points(_tiny(), 200, np.random.default_rng(3), ranges=(12e-3, 18e-3), edge_deg=2.0)
    assert len(pts) == 200
    ax, ay = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
    r = np.array([float(p[2].split()[0]) for p in pts])
    assert np.abs(ax).max() <= 18.0 and np.abs(ay).max() <= 18.0       # the tiny sector's 20 degrees less 2
    assert ax.min() < -15 and ax.max() > 15 and ay.min() < -15 and ay.max() > 15   # spread over all of it
    assert r.min() >= 12.0 and r.max() <= 18.0 and r.max() - r.min() > 4.0
    again = random_sector_points(_tiny(), 200, np.random.default_rng(3), ranges=(12e-3, 18e-3), edge_deg=2.0)
    assert again == pts
    load_scene({**copy.deepcopy(TINY_SECTOR), "sector": {**TINY_SECTOR["sector"], "points": pts[:32]}})   # accepted


@pytest.mark.parametrize("kwargs, name", [({"n": 0}, "n"), ({"ranges": (20e-3, 10e-3)}, "ranges"),
                                          ({"edge_deg": 20.0}, "edge_deg"), ({"ranges": (0.0, 1e-2)}, "ranges")])
def test_random_points_refuse_bad_input(kwargs, name):
    args = {"n": 4, **kwargs}
    with pytest.raises(ParameterError, match=name):
        random_sector_points(_tiny(), args.pop("n"), np.random.default_rng(0), **args)


def test_the_scan_is_the_exact_per_beam_metrics_of_the_points():
    pts = [[5.0, -4.0, "16 mm"], [-12.0, 8.0, "13 mm"]]
    m = _mask(1)
    got = scan_points(_tiny(), m, pts)
    tree = {**copy.deepcopy(TINY_SECTOR), "sector": {**TINY_SECTOR["sector"], "points": pts}}
    ref = SectorObjective(load_scene(tree), dtype=torch.float32, fast=False).beam_metrics(m[None], exact=True)
    for k in ("PSL_dB", "ISLR_dB", "width_x_6dB", "width_y_6dB"):
        np.testing.assert_allclose(got[k], ref[k][0], rtol=1e-6, atol=1e-9, err_msg=k)


def test_exchange_adds_the_worst_scanned_points_above_the_scenes_worst():
    sc, start = _tiny(), _mask(2)
    res = exchange_polish(sc, start, rounds=2, scan=4, add=1, seconds=1.0, seed=5, ranges=(12e-3, 18e-3))
    assert res["mask"].sum() == 16 and res["points"][:2] == [list(p) for p in sc.get("sector", "points")]
    assert res["points"][2:] == res["added"]
    first = res["history"][0]
    obj = SectorObjective(sc, dtype=torch.float32)
    plan = BeamPolish(1.0, 1.048)
    plan.prepare(obj)
    worst = float(obj.beam_loss(start[None], plan.cap)[1]["worst_PSL_dB"][0])
    assert first["scene_worst_dB"] == pytest.approx(worst, abs=1e-6)
    scan = np.array(first["scan_PSL_dB"])
    np.testing.assert_allclose(scan, scan_points(sc, start, first["scan"])["PSL_dB"], atol=1e-9)
    above = [first["scan"][j] for j in np.argsort(-scan) if scan[j] > worst]
    assert above and first["added"] == above[:1]        # the worst first, at most `add`
    for h in res["history"]:
        if h["added"]:
            assert h["polish"]["loss"] <= h["polish"]["start_loss"] + 1e-9 and len(h["elements"]) == 16
        else:                                           # a scan with nothing above the scene's worst ends it
            assert h is res["history"][-1] and max(h["scan_PSL_dB"]) <= h["scene_worst_dB"]


@pytest.mark.parametrize("kwargs, name", [({"rounds": 0}, "rounds"), ({"scan": 0}, "scan"), ({"add": 17}, "add"),
                                          ({"seconds": -1.0}, "seconds"),
                                          ({"rounds": 11, "add": 3}, "rounds x add")])
def test_exchange_refuses_bad_input(kwargs, name):
    with pytest.raises(ParameterError, match=name):
        exchange_polish(_tiny(), _mask(), **kwargs)


def test_exchange_needs_a_sector_scene():
    with pytest.raises(ParameterError, match="sector"):
        exchange_polish("matrix-1024", np.ones(1024, dtype=bool))


def test_the_scan_scores_a_batch_of_selections_and_weights_as_one_at_a_time():
    pts = [[5.0, -4.0, "16 mm"], [-12.0, 8.0, "13 mm"]]
    masks = np.stack([_mask(1), _mask(2)])
    taper = np.hanning(10)[1:9]
    weights = np.outer(taper, taper).reshape(-1)          # an apodized full array, 8 x 8
    batch = scan_points(_tiny(), np.concatenate([masks, weights[None]]), pts)
    for j, one in enumerate([masks[0], masks[1], weights]):
        ref = scan_points(_tiny(), one, pts)
        for k, v in ref.items():
            assert batch[k].shape == (3, 2)
            np.testing.assert_allclose(batch[k][j], v, rtol=1e-6, atol=1e-9, err_msg=k)
    # the apodization widens the main lobe (a known answer of tapering)
    w_full = scan_points(_tiny(), np.ones(64), pts)["width_x_6dB"]
    assert np.all(batch["width_x_6dB"][2] > w_full)
    with pytest.raises(ParameterError, match="mask"):
        scan_points(_tiny(), np.ones((2, 2, 64)), pts)
