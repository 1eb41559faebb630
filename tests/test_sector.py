"""Sector scenes (docs/sector.md): the scene keys and their errors, the exact PSFs of the points on
their surfaces over the sector (against PyMUST), the per-beam metrics on cases with a known answer,
the beam-pattern search objective and a tiny sector scene through compare."""
from __future__ import annotations

import copy
import json
import math

import numpy as np
import pandas as pd
import pytest
import torch

from arraysel.errors import ParameterError
from arraysel.objective.build import build_objective
from arraysel.objective.psf_objective import Objective
from arraysel.objective.sector_objective import BEAM_COLUMNS, SectorBeams, SectorObjective
from arraysel.physics.volume.sector import SURFACE, beam_point, sector_grid
from arraysel.report.beams import non_dominated
from arraysel.scenes.schema import load_scene
from scene_texts import TINY_SECTOR

TINY = copy.deepcopy(TINY_SECTOR)


def _scene(**over):
    tree = copy.deepcopy(TINY)
    for sec, keys in over.items():
        tree.setdefault(sec, {}).update(keys)
    return load_scene(tree)


@pytest.fixture(scope="module")
def tiny():
    return SectorObjective(_scene(), dtype=torch.float64)


# --------------------------------------------------------------------------- the scene
def test_builtin_sector_scene_and_its_geometry():
    s = load_scene("matrix-1024-sector")
    assert s.is_sector and not s.is_volume and s.k == 256
    geo = s.sector_geometry()
    assert geo["half_angles"] == (30.0, 30.0) and geo["tilts"] == (30.0, 30.0)
    lam = 1540.0 / 3e6
    assert geo["lobe"][0] == pytest.approx(lam / (31 * 0.3e-3 + 0.25e-3))
    assert geo["half_uv"][0] == pytest.approx(0.5 + 3 * geo["lobe"][0])   # three main lobes past the edge
    st = s.sector_setup()
    assert st.delays.shape == (25, 1024)
    assert len(st.points) == 11 and st.points[1] == pytest.approx((0.0, 0.0, 0.05))
    assert st.direction_of(10) == pytest.approx((-math.sin(math.radians(13)),) * 2)
    assert st.direction_of(5) == pytest.approx((math.sin(math.radians(13)),) * 2)
    # the grid: 0 on a sample, the step samples_per_lobe times finer than lambda / D, past the edge
    assert 0.0 in st.u and np.diff(st.u) == pytest.approx(geo["step"])
    assert st.u[-1] >= geo["half_uv"][0] and st.u[-1] - geo["step"] < geo["half_uv"][0]
    obj = build_objective(s)   # the one Objective, over the beam pattern, with its points' per-beam view
    assert type(obj) is Objective and isinstance(obj.beams, SectorBeams) and obj.n_points == 11


@pytest.mark.parametrize("over, key", [
    ({"sector": {"points": [[25.0, 0.0, "15 mm"]]}}, "sector.points[0]"),
    ({"sector": {"points": [[0.0, -21.0, "15 mm"]]}}, "sector.points[0]"),
    ({"sector": {"samples_per_lobe": 1.5}}, "sector.samples_per_lobe"),
    ({"transmit": {"max_tilt_deg": 50.0}}, "transmit.max_tilt_deg"),
    ({"transmit": {"max_tilt_deg_y": 47.0}}, "transmit.max_tilt_deg_y"),
    ({"sector": {"margin": 4.0}}, "sector.margin"),
    ({"volume": {"half_x": 4.0}}, "[volume]"),
    ({"medium": {"scatterer_z": "20 mm"}}, "medium.scatterer_z"),
    ({"sector": {"points": [[0.0, 0.0]]}}, "sector.points[0]"),
    ({"sector": {"points": [[0.0, 0.0, "-5 mm"]]}}, "sector.points[0].range"),
    ({"sector": {"half_angle_deg": 95.0}}, "sector.half_angle_deg"),
])
def test_scene_key_errors_name_the_key(over, key):
    with pytest.raises(ParameterError, match=key.replace("[", r"\[").replace("]", r"\]")):
        _scene(**over)


def test_steering_limit_follows_pitch_and_wavelength():
    # lambda0 / pitch - 1 = 0.711 at 3 MHz and 0.3 mm: steering up to 45.3 degrees is allowed
    _scene(transmit={"max_tilt_deg": 45.0}, sector={"half_angle_deg": 20.0})
    with pytest.raises(ParameterError, match="45.3"):
        _scene(transmit={"max_tilt_deg": 45.5}, sector={"half_angle_deg": 20.0})


def test_grid_and_point_helpers():
    u, v = sector_grid(0.5, 0.25, 0.1)
    assert u[0] == pytest.approx(-0.5) and u[-1] == pytest.approx(0.5) and len(v) == 7 and 0.0 in v
    assert beam_point(0, 0, 0.02) == pytest.approx((0, 0, 0.02))
    x, y, z = beam_point(30, 0, 0.02)
    assert (x, y, z) == pytest.approx((0.01, 0.0, 0.02 * math.cos(math.radians(30))))
    with pytest.raises(ParameterError, match="visible"):
        sector_grid(0.8, 0.8, 0.1)


# --------------------------------------------------------------------------- exact per-beam metrics
def test_full_array_per_beam_metrics(tiny):
    full = np.ones((1, tiny.n_elements), dtype=bool)
    m = tiny.beam_metrics(full)
    assert set(m) == set(BEAM_COLUMNS) and m["PSL_dB"].shape == (1, 2)
    # the main lobe is the point's own: its -6 dB widths near 0.9 lambda R / D (a two-way sinc, less
    # the compounding's narrowing), the same in x and y on the axis; no grating lobe in the sector
    lam = 1540.0 / 3e6
    d = 7 * 0.3e-3 + 0.25e-3
    for j in range(2):
        assert 0.4 * lam * 0.015 / d < m["width_x_6dB"][0, j] < 1.2 * lam * 0.015 / d
    assert m["width_y_6dB"][0, 0] == pytest.approx(m["width_x_6dB"][0, 0], rel=0.1)
    assert (m["GLL_dB"] <= -200).all()
    assert (m["PSL_dB"] < -10).all() and (m["ISLR_dB"] < 0).all()
    # the peak lies on the point's direction
    surf = tiny.exact.surfaces(torch.ones(1, tiny.n_elements, dtype=torch.float64), 1)[SURFACE][0].abs()
    i, j = np.unravel_index(int(surf.argmax()), surf.shape)
    assert tiny.setup.u[j] == pytest.approx(math.sin(math.radians(10)), abs=tiny.setup.u[1] - tiny.setup.u[0])
    assert tiny.setup.v[i] == pytest.approx(0.0, abs=1e-12)


def test_periodic_thinning_grating_lobe_where_predicted():
    # every third element of a 9 x 9 grid (pitch 0.9 mm): grating lobes at u0 +- lambda / 0.9 mm = +-0.570
    obj = SectorObjective(_scene(probe={"nx": 9, "ny": 9}, sector={"margin": 2.2, "half_angle_deg": 10.0,
                                                                              "points": [[0.0, 0.0, "15 mm"]]}),
                          dtype=torch.float64)
    grid = np.zeros((9, 9), dtype=bool)
    grid[::3, ::3] = True
    masks = np.stack([grid.ravel(), np.ones(81, dtype=bool)])
    m = obj.beam_metrics(masks)
    assert m["GLL_dB"][0, 0] > -12.0            # a grating lobe of the order of the main lobe (element factor, compounding)
    assert m["GLL_dB"][0, 0] == pytest.approx(m["PSL_dB"][0, 0], abs=1e-9)   # it is the worst side lobe
    assert m["GLL_dB"][1, 0] <= -200              # the full 0.3 mm lattice puts none in the region
    surf = obj.exact.surfaces(torch.tensor(masks[:1], dtype=torch.float64), 0)[SURFACE][0].abs()
    row = surf[len(obj.setup.v) // 2].numpy()
    u = obj.setup.u
    far = np.abs(u) > 0.35
    u_peak = abs(u[far][np.argmax(row[far])])
    lam = obj.pattern.wavelengths   # the band: the grating lobe runs from lambda_lo / 0.9 mm to lambda_hi / 0.9 mm
    lobe = (1540.0 / 3e6) / (8 * 0.3e-3 + 0.25e-3)
    assert float(lam.min()) / 0.9e-3 - lobe <= u_peak <= float(lam.max()) / 0.9e-3 + lobe


def test_beam_pattern_search_terms_and_gradient(tiny):
    masks = np.zeros((3, tiny.n_elements), dtype=bool)
    masks[0] = True
    masks[1:] = tiny.fresh_random_masks(2)
    r = tiny.evaluate(masks)
    assert r["L_PSF"][0] == pytest.approx(0.0, abs=1e-9)     # the full array against itself
    assert (r["L_PSF"][1:] > 0).all()
    assert r["Mean"] == pytest.approx((r["L_PSF"] + r["L_contrast"] + r["L_SLR_q"] + r["L_SLR_i"]) / 4)
    assert r["L_SLR_q"] == pytest.approx(10 ** (r["bp_PSL_dB"] / 20))
    w = torch.tensor(masks[1:] * 0.8 + 0.1, dtype=torch.float64, requires_grad=True)
    total, _ = tiny.mask_loss(w)
    total.sum().backward()
    assert torch.isfinite(w.grad).all() and w.grad.abs().sum() > 0


def test_the_sector_scene_is_the_one_objective_over_its_imagers(tiny):
    """The sector scene's search imager is its beam pattern (one plane in u-v), its points are the
    per-beam view's imagers (one plane on each point's surface), and it has no neighbourhood (its
    neighbours are scored as masks, as before); a scene without the view has no beam_metrics."""
    from arraysel.objective.contract import objective_info
    from arraysel.objective.sector_objective import SEARCH_COLUMNS, SectorPointImager
    from arraysel.physics.imaging import PATTERN_PLANE, PatternImager

    (im,) = tiny.imagers
    assert isinstance(im, PatternImager) and im.frame == "uv" and not im.moves_from_selection
    assert tiny.n_points == 2 and tiny.breakdown_names == SEARCH_COLUMNS and tiny.chunk == 64
    assert tiny.neighbourhood() is None and objective_info(tiny).kind == "beams"
    masks = np.zeros((2, tiny.n_elements), dtype=bool)
    masks[0] = True
    masks[1] = tiny.fresh_random_masks(1)[0]
    w = torch.tensor(masks, dtype=torch.float64)
    ps = im.image(w)
    assert ps.names == (PATTERN_PLANE,) and ps.kernel.shape == (2,) + ps.coords[PATTERN_PLANE].shape[:2]
    assert not ps.kernel.is_complex() and bool((ps.kernel >= 0).all())
    torch.testing.assert_close(im.reference().kernel, ps.kernel[:1])       # the full array's pattern
    got = tiny.evaluate(masks)
    want = tiny._metrics(0, ps)
    for name in got:
        np.testing.assert_allclose(got[name], want[name].double().numpy(), rtol=1e-12, err_msg=name)
    point = tiny.beams.imagers[1]
    assert isinstance(point, SectorPointImager)
    surf = point.image(w[:1], exact=True)
    assert surf.names == (SURFACE,) and surf.kernel.is_complex()
    assert tuple(surf.coords[SURFACE].shape) == tuple(surf.kernel.shape[1:]) + (3,)
    torch.testing.assert_close(surf.kernel, tiny.point_images(w[:1], 1, exact=True))
    other = build_objective(load_scene("matrix-1024"))
    assert other.beams is None and not hasattr(other, "beam_metrics") and objective_info(other).kind == "planes"


def test_non_dominated():
    a = [1.0, 2.0, 0.5, 3.0, np.nan]
    b = [1.0, 0.5, 2.0, 3.0, 0.0]
    assert non_dominated(a, b).tolist() == [True, True, True, False, False]


# --------------------------------------------------------------------------- against PyMUST
def test_sector_surface_matches_pymust(tiny):
    pytest.importorskip("pymust")
    from pymust_pipeline3 import PyMUSTScene3, si_mse

    st = tiny.setup
    rng = np.random.default_rng(3)
    masks = [np.ones(64)]
    for _ in range(2):
        m = np.zeros(64)
        m[rng.choice(64, 16, replace=False)] = 1
        masks.append(m)
    got = tiny.exact.surfaces(torch.tensor(np.stack(masks)), 1, exact=True)[SURFACE].numpy()
    oracle = PyMUSTScene3(st.probe, st.acq, st.delays, st.points[1], {SURFACE: tiny.exact.coords[1][SURFACE].numpy()})
    fast = None
    if tiny.fast_point(1):   # the fast path, when it passed its check, against the same oracle
        fast = tiny.point_images(torch.tensor(np.stack(masks)), 1).numpy()
    for i, m in enumerate(masks):
        ref = oracle.planes(m)[SURFACE]
        assert si_mse(got[i], ref) <= 1e-4, i
        if fast is not None:
            assert si_mse(fast[i], ref) <= 1e-4, i


# --------------------------------------------------------------------------- through compare
def test_tiny_sector_scene_through_compare(tmp_path):
    from arraysel.run.compare import compare
    from arraysel.selectors.contract import Budget

    obj = build_objective(_scene(), dtype=torch.float32)
    res = compare(obj, ["random", "uniform", "spiral", "swap"], out_dir=tmp_path, seeds=[0, 1],
                  budget=Budget(evaluations=40), progress=False)
    assert "Mean" in res.table.columns and "bp_PSL_dB" in res.runs.columns
    beams = pd.read_csv(tmp_path / "beams.csv")
    assert set(beams["config"]) == {"full", "random", "uniform", "spiral", "swap", "random (fresh median)"}
    assert (beams.groupby("config").size() == 2).all()
    assert np.isfinite(beams[["PSL_dB", "ISLR_dB", "width_x_mm", "width_y_mm"]].to_numpy()).all()
    assert "taper=none" in beams.loc[beams["config"] == "spiral", "options"].iloc[0]
    pareto = pd.read_csv(tmp_path / "pareto.csv")
    assert pareto["on_front"].any() and not pareto.loc[pareto["config"] == "full", "on_front"].any()
    assert pareto.loc[pareto["config"] == "full", "baseline"].all()
    front = pareto[pareto["on_front"] & (pareto["k"] == 16)]
    for _, r in pareto[pareto["k"] == 16].iterrows():   # nothing of k elements dominates the front
        assert not ((front["worst_PSL_dB"] > r["worst_PSL_dB"]) & (front["mean_width_mm"] > r["mean_width_mm"])).any() \
            or not r["on_front"]
    assert (tmp_path / "pareto.png").stat().st_size > 1000
    assert (tmp_path / "beampattern.png").stat().st_size > 1000
    assert not json.loads((tmp_path / "run.json").read_text()).get("figure_errors")


# --------------------------------------------------------------------------- every selector on it
def _selector_names():
    from arraysel.selectors.registry import get_registry

    reg = get_registry()
    out = []
    for name in sorted(reg.names()):
        try:
            reg[name].check_available()
        except Exception:  # an optional package that is not installed
            continue
        out.append(name)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("name", _selector_names())
def test_every_selector_on_a_tiny_sector_scene(tiny, name):
    """The conformance essentials on a sector objective: k distinct elements, the evaluation
    budget kept, a finite Mean, the same seed the same selection."""
    from arraysel.run.experiment import Experiment
    from arraysel.selectors.contract import Budget

    rows = [Experiment(tiny, name, budget=Budget(evaluations=60), seed=3).execute() for _ in range(2)]
    sel = list(rows[0]["elements"])
    assert not str(rows[0].get("error") or "").strip(), rows[0].get("error")
    assert len(sel) == tiny.k == len(set(sel)) and all(0 <= e < tiny.n_elements for e in sel)
    assert rows[0]["evaluations"] <= 60 and math.isfinite(rows[0]["Mean"])
    assert list(rows[1]["elements"]) == sel


def test_a_sector_scene_keeps_its_constraints():
    # a [constraints] section of a sector scene reaches the selectors: every run's selection holds
    # one element of each of the 16 channels of a 4-bank multiplexer of the 8 x 8 probe
    from arraysel.run.experiment import Experiment
    from arraysel.selectors.contract import Budget
    from arraysel.selectors.registry import get_registry

    obj = build_objective(_scene(constraints={"groups": "mux-64-4", "mode": "exactly-one"}), dtype=torch.float32)
    assert obj.constraints is not None and not obj.constraints.trivial
    for name in ("random", "swap", "uniform", "spiral"):
        row = Experiment(obj, get_registry()[name], options={}, budget=Budget(evaluations=30), seed=0, k=16).run()
        assert row["error"] == "", (name, row["error"])
        obj.constraints.check([int(i) for i in row["elements"].split()])
