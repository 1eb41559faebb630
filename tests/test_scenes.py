"""Scenes (issue 17, parts 2-5): lengths with units, metric regions that fit, several field
points, the built-in scenes, the ``scenes`` command, the exact path's bounded memory and its
notice, and the refusal of scenes over the memory cap.

Everything physical runs on tiny scenes (8 elements, 16 x 16 grids) with the fast path off
and ``ARRAYSEL_CACHE=off``; the 128-element built-in scenes are only loaded, never simulated.
"""
from __future__ import annotations

import logging
import math

import numpy as np
import pandas as pd
import pytest
import torch

from arraysel.cli.main import main
from arraysel.errors import ParameterError
from arraysel.objective.psf_objective import METRIC_NAMES, Objective, point_metric_names
from arraysel.physics.psf import PSFModel
from arraysel.scenes.schema import SCHEMA, builtin_scenes, load_scene

TINY = {"base": "paper", "probe": {"n_elements": 8}, "selection": {"k": 4}, "transmit": {"n_tx": 2},
        "grid": {"n_x": 16, "n_z": 16, "window": 8, "pixel_per_wavelength_fs": 1.0},
        "metrics": {"r_main": 0.5, "r_guard": 1.0},
        "simulator": {"fast_margin": 2, "fast_block": 4}}
PIXEL = 1540 / 14e6  # TINY's pitch: c / fs, fs = 4 x 3.5 MHz
LAM = 1540 / 3.5e6


def tiny(**sections) -> dict:
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in TINY.items()}
    for sec, keys in sections.items():
        out.setdefault(sec, {}).update(keys)
    return out


@pytest.fixture(autouse=True)
def _no_disk_cache(monkeypatch):
    monkeypatch.setenv("ARRAYSEL_CACHE", "off")


MASKS = np.array([[1, 1, 1, 1, 1, 1, 1, 1], [1, 0, 1, 0, 1, 0, 1, 0], [1, 1, 0, 0, 0, 0, 1, 1]], dtype=float)


# ---------------------------------------------------------------------------
# lengths with units
# ---------------------------------------------------------------------------

def test_lengths_resolve_in_each_keys_unit():
    sc = load_scene({"base": "paper", "grid": {"window": "3.5 mm"}, "metrics": {"r_main": "24 px",
                                                                                 "r_guard": "1.1 mm"}})
    p, lam = sc.pixel, sc.wavelength
    assert p == pytest.approx(27.5e-6) and lam == pytest.approx(0.44e-3)
    assert sc.length("grid", "window") == round(3.5e-3 / p) == 127
    assert sc.length("metrics", "r_main") == pytest.approx(1.5)
    assert sc.length("metrics", "r_guard") == pytest.approx(2.5)
    assert sc.psf_setup().window == 127
    sc = load_scene({"base": "paper", "grid": {"pixel": "0.0625 wl", "n_x": "11 mm", "n_z": "400 px"}})
    assert sc.pixel == pytest.approx(27.5e-6)
    assert sc.psf_setup().n_x == 400 and sc.psf_setup().n_z == 400
    # bare numbers keep their old meaning: pixels, wavelengths, metres
    sc = load_scene({"base": "paper", "grid": {"window": 64}, "metrics": {"r_main": 1.0}})
    assert sc.length("grid", "window") == 64 and sc.length("metrics", "r_main") == 1.0
    sc = load_scene({"base": "paper", "medium": {"points": [["-5 mm", "40 mm"], [0.004, "100 wl"]]}})
    np.testing.assert_allclose(sc.points(), [(-0.005, 0.04), (0.004, 100 * LAM)], rtol=1e-12)
    assert [s.x_offset for s in sc.psf_setups()] == [round(-5e-3 / 27.5e-6), round(4e-3 / 27.5e-6)]
    with pytest.raises(ParameterError, match=r"medium\.points\[0\]\.x = '-2000 mm' is -2 m; allowed: \[-1, 1\] m"):
        load_scene({"base": "paper", "medium": {"points": [["-2000 mm", "40 mm"]]}})


@pytest.mark.parametrize("over,pattern", [
    ({"grid": {"window": "3.5 furlongs"}}, r"grid\.window = '3\.5 furlongs': unit 'furlongs' is not allowed"),
    ({"grid": {"window": "mm 3"}}, r"grid\.window must be a number \(px\) or a string with a unit"),
    ({"grid": {"pixel": "2 px"}}, r"grid\.pixel = '2 px': unit 'px' is not allowed"),
    ({"grid": {"window": "-3 mm"}}, r"grid\.window = -3\.0 is out of range"),
    ({"grid": {"window": "20 mm"}}, r"grid\.window = '20 mm' must not exceed grid\.n_x and grid\.n_z"),
    ({"grid": {"n_x": "1 km"}}, r"grid\.n_x = '1 km': unit 'km' is not allowed"),
    ({"grid": {"n_x": "300 mm"}}, r"grid\.n_x = '300 mm' is 10909 pixels; allowed: \[8, 8192\]"),
    ({"grid": {"pixel": "2 m"}}, r"grid\.pixel = 2\.0 is out of range; allowed: \(0, 1\]"),
    ({"grid": {"pixel": "2000 mm"}}, r"grid\.pixel = '2000 mm' is 2 m; allowed: \(0, 1\] m"),
    ({"metrics": {"r_main": "0 wl"}}, r"metrics\.r_main = 0\.0 is out of range"),
    ({"medium": {"points": [[0, "20 mm", 3]]}}, r"medium\.points\[0\] must be a pair \[x, z\]"),
    ({"medium": {"points": "20 mm"}}, r"medium\.points must be a list of 1 to 64 points"),
    ({"medium": {"points": [[0, "-2 mm"]]}}, r"medium\.points\[0\]\.z = -2\.0 is out of range"),
    ({"medium": {"points": [[0, "20 mm"]], "scatterer_z": 0.02}}, r"medium\.points and medium\.scatterer_z"),
    ({"medium": {"points": [[0, "20 mm"]]}, "grid": {"z_offset": 10}}, r"medium\.points and grid\.z_offset"),
    ({"metrics": {"aggregate": "median"}}, r"metrics\.aggregate = 'median' is not allowed"),
])
def test_bad_lengths_name_the_key(over, pattern):
    with pytest.raises(ParameterError, match=pattern):
        load_scene({"base": "paper", **over})


@pytest.mark.parametrize("over,pattern", [
    # the example: r_main = 100 wavelengths used to give zero contrast and SLR silently
    ({"metrics": {"r_main": 100, "r_guard": 120}}, r"metrics\.r_main = 100 \(1600\.0 px\) does not fit "
                                                   r"grid\.window = 128"),
    ({"metrics": {"r_guard": "6 wl"}}, r"metrics\.r_guard = '6 wl' \(96\.0 px\) does not fit grid\.window"),
    ({"grid": {"window": "1 mm"}}, r"metrics\.r_main = 1\.5 \(24\.0 px\) does not fit grid\.window = '1 mm'"),
])
def test_metric_regions_must_fit_the_window(over, pattern):
    with pytest.raises(ParameterError, match=pattern):
        load_scene({"base": "paper", **over})


def test_regions_that_fit_give_nonzero_side_terms():
    obj = Objective(load_scene(tiny()), fast=False)
    res = obj.evaluate(MASKS)
    assert all((res[k] > 0).all() for k in ("L_contrast", "L_SLR_q", "L_SLR_i"))


# ---------------------------------------------------------------------------
# schema defaults and the built-in scenes
# ---------------------------------------------------------------------------

def test_defaults_live_in_the_schema():
    sc = load_scene(tiny())
    assert sc.value("grid", "z_offset") == SCHEMA["grid"]["z_offset"].default == 0
    assert sc.value("metrics", "aggregate") == "mean"
    res = sc.resolved()
    assert res["grid"]["n_x"] == (16, None, "scene")
    assert res["grid"]["z_offset"] == (0, None, "default")
    assert res["acquisition"]["fs"][2] == "derived" and res["acquisition"]["fs"][0] == pytest.approx(14e6)


def test_builtin_scenes_load_by_name():
    assert {"paper", "paper-e2e", "l11-5v", "c5-2v", "p4-2v-depths"} <= set(builtin_scenes())
    l11 = load_scene("l11-5v")
    s = l11.psf_setup()
    assert (s.probe.name, s.probe.n_elements, l11.k, s.probe.fc, s.acq.fs) == ("L11-5v", 128, 64, 7.6e6, 30.4e6)
    assert len(s.tilts) == 7 and math.degrees(max(s.tilts)) == pytest.approx(10)
    assert s.scatterer_position == pytest.approx((0.0, 0.020))
    assert s.scatterer_pixel == (s.n_z // 2, s.n_x // 2)
    c5 = load_scene("c5-2v").psf_setup()
    assert c5.probe.name == "C5-2v" and math.isfinite(c5.probe.radius) and c5.probe.n_elements == 128
    assert c5.scatterer_position == pytest.approx((0.0, 0.050)) and load_scene("c5-2v").k == 64
    deep = load_scene("p4-2v-depths")
    setups = deep.psf_setups()
    assert [round(z, 6) for _, z in deep.points()] == [0.02, 0.04, 0.06]
    for st, (x, z) in zip(setups, deep.points()):
        assert st.scatterer_position == pytest.approx((x, z))
        assert st.scatterer_pixel == (st.n_z // 2, st.n_x // 2)
        assert st.window * st.pitch > 20e-3  # wide enough for the grating lobes' inner flank at 20 mm
    # the paper scene is untouched: same setup (and so the same fast-path cache key) as before
    paper = load_scene("paper").psf_setup()
    assert "x_offset" not in repr(paper) and paper.scatterer_position == pytest.approx((0.0, 200 * 27.5e-6))


def test_x_offset_shifts_the_grid():
    base = load_scene(tiny()).psf_setup()
    import dataclasses

    s = dataclasses.replace(base, x_offset=5)
    assert "x_offset=5" in repr(s)
    assert s.x[s.n_x // 2] == pytest.approx(5 * s.pitch)
    assert s.scatterer_position == pytest.approx((5 * s.pitch, base.scatterer_position[1]))
    assert s.scatterer_pixel == base.scatterer_pixel


def test_scenes_command(capsys):
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    for name in ("l11-5v", "c5-2v", "p4-2v-depths", "paper"):
        assert name in out
    assert main(["scenes", "p4-2v-depths"]) == 0
    out = capsys.readouterr().out
    assert 'window = "60 wl"' in out and "= 240 px" in out
    assert "z_offset = 0" in out and "# default" in out and "# derived" in out
    assert main(["scenes", "l11-5v", "--json"]) == 0
    import json

    data = json.loads(capsys.readouterr().out)
    assert data["sections"]["probe"]["n_elements"]["value"] == 128
    assert main(["scenes", "nosuchscene"]) == 2


# ---------------------------------------------------------------------------
# several field points
# ---------------------------------------------------------------------------

POINTS = [[0.0, "1.2 mm"], ["0.3 mm", "1.6 mm"]]


@pytest.fixture(scope="module")
def two_points():
    import os

    os.environ["ARRAYSEL_CACHE"] = "off"
    return Objective(load_scene(tiny(medium={"points": POINTS})), fast=False)


def test_one_point_of_points_is_the_one_scatterer_scene():
    # the same physical pixels around the scatterer: a grid shifted by whole pixels
    x, z = 3 * PIXEL, 10 * PIXEL
    a = Objective(load_scene(tiny(medium={"points": [[x, z]]})), fast=False)
    b = Objective(load_scene(tiny(medium={"scatterer_x": x, "scatterer_z": z}, grid={"z_offset": 2})), fast=False)
    assert a.setup.x_offset == 3 and a.setup.z_offset == 2 and b.setup.x_offset == 0
    ka, kb = a.kernels(MASKS), b.kernels(MASKS)
    assert ka.shape == kb.shape == (3, 8, 8)
    # masks 0 and 1 peak on the scatterer; the degenerate mask 2 peaks elsewhere on grids that differ
    torch.testing.assert_close(ka[:2], kb[:2], rtol=1e-5, atol=1e-6)
    assert a.breakdown_names == () and set(a.evaluate(MASKS)) == set(METRIC_NAMES)


def test_several_points_report_each_point_mean_and_worst(two_points):
    obj = two_points
    assert obj.n_points == 2 and len(obj.psfs) == 2
    res = obj.evaluate(MASKS)
    assert set(res) == set(METRIC_NAMES) | set(point_metric_names(2))
    for name in METRIC_NAMES:
        per = np.stack([res[f"{name}@p0"], res[f"{name}@p1"]], 1)
        np.testing.assert_allclose(res[f"{name}@mean"], per.mean(1), rtol=1e-12)
        np.testing.assert_allclose(res[f"{name}@worst"], per.max(1), rtol=1e-12)
        np.testing.assert_allclose(res[name], res[f"{name}@mean"], rtol=1e-12)  # aggregate = "mean"
    # each point scores as the one-point scene of that point
    for i, pt in enumerate(POINTS):
        one = Objective(load_scene(tiny(medium={"points": [pt]})), fast=False)
        r1 = one.evaluate(MASKS)
        for name in METRIC_NAMES:
            np.testing.assert_allclose(res[f"{name}@p{i}"], r1[name], rtol=1e-6, atol=1e-9)
    k = obj.kernels(MASKS)
    assert k.shape == (3, 2, 8, 8) and obj.reference_kernel().shape == (2, 8, 8)
    assert obj.kernels(MASKS, point=1).shape == (3, 8, 8)
    met = obj.metrics_of_kernels(k)
    np.testing.assert_allclose(met["Mean"].double().numpy(), np.stack([res["Mean@p0"], res["Mean@p1"]], 1),
                               rtol=1e-5)
    with pytest.raises(ParameterError, match=r"point = 2 is out of range"):
        obj.kernels(MASKS, point=2)


def test_worst_aggregate_and_gradients():
    obj = Objective(load_scene(tiny(medium={"points": POINTS}, metrics={"aggregate": "worst"})), fast=False)
    res = obj.evaluate(MASKS)
    np.testing.assert_allclose(res["Mean"], res["Mean@worst"])
    w = torch.full((1, 8), 0.6, requires_grad=True)
    total, terms = obj.mask_loss(w)
    total.sum().backward()
    assert torch.isfinite(w.grad).all() and w.grad.abs().sum() > 0
    P = torch.zeros(8, 4)
    P[[0, 2, 4, 6], [0, 1, 2, 3]] = 1
    P.requires_grad_(True)
    t, _ = obj.selection_loss(P, P.softmax(0))
    t.backward()
    assert torch.isfinite(P.grad).all()


def test_runs_csv_keeps_the_per_point_breakdown(two_points, tmp_path):
    from arraysel.selectors.registry import build_plugin_manager, get_registry
    from arraysel.report.columns import ROW_COLUMNS
    from arraysel.run.compare import compare
    from arraysel.selectors.contract import Budget

    reg = get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))
    compare(two_points, ["uniform"], out_dir=tmp_path, budget=Budget(evaluations=4), registry=reg,
            progress=False, figures=False)
    runs = pd.read_csv(tmp_path / "runs.csv")
    assert tuple(runs.columns[:len(ROW_COLUMNS)]) == ROW_COLUMNS
    assert tuple(runs.columns[len(ROW_COLUMNS):]) == point_metric_names(2)
    for _, row in runs.iterrows():
        assert row["Mean"] == pytest.approx((row["Mean@p0"] + row["Mean@p1"]) / 2)
    t1 = pd.read_csv(tmp_path / "table1.csv")
    assert list(t1["config"]) == ["full", "uniform"]


def test_end_to_end_scenes_take_one_point():
    with pytest.raises(ParameterError, match=r"end-to-end scenes .* take one field point"):
        load_scene({"base": "paper-e2e", "medium": {"points": POINTS}})


# ---------------------------------------------------------------------------
# the exact path: bounded memory, notice, refusal
# ---------------------------------------------------------------------------

def test_exact_path_chunks_follow_the_memory_cap_and_agree(monkeypatch):
    import arraysel.physics.psf.sizing as psf_module  # the exact path's memory model

    setup = load_scene(tiny()).psf_setup()
    big = PSFModel(setup, fast=False)
    small = PSFModel(setup, fast=False)
    # a cap just above the fixed costs: batches of one mask; DAS calls of a few rows
    monkeypatch.setattr(psf_module, "_DAS_BYTES", psf_module._DAS_TEMPS * 8 * 8 * 40)
    small.memory_limit = small.exact_bytes(1) + 1000
    b, px = small.exact_chunking()
    assert b == 1 and setup.n_x <= px < setup.n_x * setup.n_z
    assert small.exact_bytes(b, px) <= small.memory_limit
    assert big.exact_chunking()[0] > 1 and big.exact_bytes(*big.exact_chunking()) <= big.memory_limit
    w = torch.as_tensor(MASKS, dtype=torch.float32)
    torch.testing.assert_close(small.image(w), big.image(w), rtol=1e-5, atol=1e-6)


def test_exact_path_says_so_once_with_time_estimates(caplog):
    with caplog.at_level(logging.WARNING, logger="arraysel.objective.psf_objective"):
        obj = Objective(load_scene(tiny()), fast=False)
        obj.evaluate(MASKS)
        obj.evaluate(MASKS)
    msgs = [r.getMessage() for r in caplog.records if r.name == "arraysel.objective.psf_objective"]
    assert len(msgs) == 2, msgs
    assert "fast path disabled (fast=False); using the exact path: about" in msgs[0]
    assert "per mask (estimated)" in msgs[0] and "ARRAYSEL_MEMORY_GIB" in msgs[0]
    assert msgs[1].startswith("evaluating 3 masks on the exact PSF path: about")
    est = obj.estimate_seconds(10)
    assert math.isfinite(est) and est > 0
    assert "10 mask(s): about" in obj.exact_notice(10)


def test_a_grid_over_the_memory_cap_is_refused_up_front(monkeypatch):
    import time

    monkeypatch.setenv("ARRAYSEL_MEMORY_GIB", "1")
    t0 = time.perf_counter()
    # from the sizes alone, when the scene's setups are made (scenes.schema, settings.grid_bytes)
    with pytest.raises(ParameterError, match=r"grid\.n_x x grid\.n_z = 8192 x 8192 pixels needs about .* GiB .*"
                                             r"more than the 1\.0 GiB allowed by ARRAYSEL_MEMORY_GIB.*"
                                             r"reduce grid\.n_x / grid\.n_z"):
        Objective(load_scene({"base": "paper", "grid": {"n_x": 8192, "n_z": 8192}}))
    # a grid within that bound still meets the exact path's own guard (its plan cache and image)
    with pytest.raises(ParameterError, match=r"needs about .* GiB for one mask .*grid 3000 x 3000 pixels.* "
                                             r"memory cap of 1\.0 GiB: reduce grid\.n_x / grid\.n_z .* "
                                             r"ARRAYSEL_MEMORY_GIB"):
        Objective(load_scene({"base": "paper", "grid": {"n_x": 3000, "n_z": 3000}}))
    assert time.perf_counter() - t0 < 30
    monkeypatch.setenv("ARRAYSEL_MEMORY_GIB", "lots")
    with pytest.raises(ParameterError, match=r"ARRAYSEL_MEMORY_GIB = 'lots' must be a number of GiB"):
        Objective(load_scene(tiny()), fast=False)


@pytest.mark.slow
def test_deep_scene_windows_show_what_sparse_masks_lose():
    """p4-2v-depths: the uniform mask scores worse than the full array on contrast at every depth,
    and the scene's three points are reported. (Measured: Mean 0.0191 against 0.0019 at 20 mm,
    where the window holds the grating lobes' inner flank; 0.0035 / 0.0030 at 40 mm and
    0.0092 / 0.0087 at 60 mm, where the lobes, near x = +-1.07 z, lie outside the window.)"""
    obj = Objective("p4-2v-depths", fast=False)
    m = np.zeros((1, 64))
    m[0, ::2] = 1
    res = obj.evaluate(m)  # the uniform mask (and the three full-array references)
    full = obj.metrics_of_kernels(obj.reference_kernel()[None])  # (1, 3) values
    for p in range(3):
        assert res[f"L_contrast@p{p}"][0] > float(full["L_contrast"][0, p])
        assert res[f"L_PSF@p{p}"][0] > 1e-4
        assert float(full["L_PSF"][0, p]) < 1e-6


def test_compare_ranks_by_the_chosen_aggregate(tmp_path, capsys):
    scene = tmp_path / "two.toml"
    scene.write_text('base = "paper"\n[probe]\nn_elements = 8\n[selection]\nk = 4\n[transmit]\nn_tx = 2\n'
                     '[grid]\nn_x = 16\nn_z = 16\nwindow = 8\npixel_per_wavelength_fs = 1.0\n'
                     '[metrics]\nr_main = 0.5\nr_guard = 1.0\n'
                     '[medium]\npoints = [[0.0, "1.2 mm"], ["0.3 mm", "1.6 mm"]]\n')
    out = tmp_path / "out"
    rc = main(["compare", "--selectors", "uniform", "--scene", str(scene), "--budget-evals", "2",
               "--aggregate", "worst", "--out", str(out), "--no-figures", "--no-progress"])
    assert rc == 0
    runs = pd.read_csv(out / "runs.csv")
    np.testing.assert_allclose(runs["Mean"], runs["Mean@worst"])
    assert (runs["Mean@worst"] >= runs["Mean@mean"]).all()


def test_compare_says_how_long_the_exact_path_takes(two_points):
    from arraysel.cli.compare import _exact_run_notice
    from arraysel.selectors.contract import Budget

    text = _exact_run_notice(two_points, Budget(evaluations=50), 3)
    assert "using the exact path" in text and "150 mask(s): about" in text and "(3 run(s) of 50)" in text
    text = _exact_run_notice(two_points, Budget(seconds=60), 2)
    assert "each of the 2 run(s) stops at its 60 s budget after about" in text


def test_end_to_end_scenes_only_warn_about_regions(caplog):
    with caplog.at_level(logging.WARNING, logger="arraysel.scenes.schema"):
        load_scene({"base": "paper-e2e", "grid": {"n_x": 64, "n_z": 64, "window": 32}})
    assert any("metrics.r_main = 1.5 (24.0 px) does not fit grid.window = 32" in r.getMessage()
               for r in caplog.records)
    with pytest.raises(ParameterError, match=r"metrics\.r_main = 1\.5 \(24\.0 px\) does not fit grid\.window = 32"):
        load_scene({"base": "paper", "grid": {"n_x": 64, "n_z": 64, "window": 32}})


def test_best_known_selections_are_selections_of_their_scenes():
    from arraysel.scenes.best_known import best_known, load_best_known

    table = load_best_known()
    assert "paper" in table
    for name, entry in table.items():
        scene = load_scene(name)
        n = scene.probe().n_elements
        el = entry["elements"]
        assert entry["k"] == scene.k == len(el) == len(set(el)) and all(0 <= i < n for i in el), name
        assert 0 < entry.get("reference_Mean", entry["Mean"]) <= entry["Mean"] and entry["command"], name
        assert best_known(name, scene.k)["Mean"] == entry["Mean"] and best_known(name, scene.k + 1) is None
    assert best_known("no-such-scene") is None
