"""3-D scenes ([volume]), the matrix-1024 scene and MatrixObjective: validation, the fast path
against the exact path through the objective, the contract (losses, gradient, counters), the
on-disk cache, the CLI's 3-D outputs, and every registered selector on a small matrix scene."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from arraysel.errors import ParameterError, SelectionError
from arraysel.objective.build import build_objective
from arraysel.objective.matrix_objective import MatrixObjective
from arraysel.objective.metrics3d import MERIT_NAMES
from arraysel.objective.metrics import METRIC_NAMES
from arraysel.run.experiment import Experiment
from arraysel.scenes.schema import load_scene
from arraysel.selectors.contract import Budget
from scene_texts import TINY_MATRIX_SCENE


@pytest.fixture(scope="module")
def tiny_path(tmp_path_factory):
    p = tmp_path_factory.mktemp("scenes") / "tiny3d.toml"
    p.write_text(TINY_MATRIX_SCENE)
    return str(p)


@pytest.fixture(scope="module")
def tiny(tiny_path):
    return MatrixObjective(tiny_path, dtype=torch.float64)


def _scene(tiny_path, **over):
    return load_scene(tiny_path, overrides=over)


def test_matrix_1024_scene_is_the_issue_geometry():
    s = load_scene("matrix-1024")
    setup = s.matrix_setup()
    assert s.is_volume and s.k == 256
    assert setup.probe.n_elements == 1024 and setup.probe.grid_shape == (32, 32)
    assert setup.probe.fc == 3e6 and setup.probe.pitch_x == pytest.approx(300e-6)
    assert setup.n_tx == 9 and setup.scatterer == (0.0, 0.0, pytest.approx(0.03))
    assert setup.planes == ("xy", "xz", "yz")
    assert not load_scene("paper").is_volume


@pytest.mark.parametrize("over, key", [
    ({"probe": {"name": "L11-5v"}}, "probe.name"),
    ({"grid": {"n_x": 64}}, "grid.n_x"),
    ({"transmit": {"n_tx": 3}}, "transmit.n_tx"),
    ({"volume": {"planes": "xy,xw"}}, "volume.planes"),
    ({"volume": {"planes": "xy,xy"}}, "volume.planes"),
    ({"selection": {"k": 17}}, "selection.k"),
    ({"metrics": {"r_guard": 5.0}}, "metrics.r_guard"),
    ({"metrics": {"r_main": 2.5, "r_guard": 2.8}}, "metrics.r_main"),
    ({"volume": {"half_x": -1.0}}, "volume.half_x"),
    ({"volume": {"half_x": 900.0, "pixels_per_wavelength": 3.0}}, "volume.half_x"),
    ({"volume": {"half_z": 100.0}}, "volume.half_z"),
])
def test_bad_3d_scenes_name_the_key(tiny_path, over, key):
    with pytest.raises(ParameterError, match=key.replace(".", r"\.")):
        _scene(tiny_path, **over)


def test_3d_only_keys_are_refused_in_a_1d_scene():
    with pytest.raises(ParameterError, match=r"medium\.scatterer_y"):
        load_scene("paper", overrides={"medium": {"scatterer_y": 0.001}})
    with pytest.raises(ParameterError, match=r"transmit\.source_distance"):
        load_scene("paper", overrides={"transmit": {"source_distance": "10 mm"}})


def test_a_3d_scene_needs_its_depth(tmp_path):
    text = TINY_MATRIX_SCENE.replace('base = "matrix-1024"', "").replace('name = "tiny3d"', 'name = "x"\n'
                                                                         '[probe]\nname = "MATRIX-32x32"')
    text = text.replace('[probe]\nnx = 4', 'nx = 4', 1)
    p = tmp_path / "x.toml"
    p.write_text(text.replace('scatterer_z = "10 mm"', ""))
    with pytest.raises(ParameterError, match=r"medium\.scatterer_z"):
        load_scene(str(p))


def test_one_objective_scores_1d_and_3d_scenes(tiny_path, tiny):
    """A 3-D scene is the same Objective over its volume imager: kernels are refused, planes given."""
    from arraysel.objective.psf_objective import Objective, build_objective as build_1d
    from arraysel.physics.imaging import VolumeImager

    obj = build_objective(tiny_path, dtype=torch.float64)
    assert type(obj) is Objective and type(build_1d(tiny_path)) is Objective and type(tiny) is Objective
    assert obj.image_kind == "planes" and [type(im) for im in obj.imagers] == [VolumeImager]
    assert obj.breakdown_names == MERIT_NAMES
    with pytest.raises(ParameterError, match="planes, not a 2-D kernel"):
        obj.kernels(np.ones((1, 16)))
    with pytest.raises(ParameterError, match=r"no \[volume\] section"):
        MatrixObjective("paper")


def test_fast_objective_equals_the_exact_path(tiny_path, tiny):
    exact = MatrixObjective(tiny_path, dtype=torch.float64, fast=False)
    assert tiny.fast and not exact.fast and "disabled" in exact.exact_notice()
    rng = np.random.default_rng(3)
    masks = np.zeros((6, 16))
    for i in range(5):
        masks[i, rng.choice(16, 4, replace=False)] = 1
    masks[5] = 1
    a, b = tiny.evaluate(masks), exact.evaluate(masks)
    assert tiny.model.check["max_relative_error"] <= 1e-6   # planes: relative squared error
    for name in METRIC_NAMES:
        np.testing.assert_allclose(a[name], b[name], rtol=5e-3, atol=1e-6, err_msg=name)  # side-lobe ratios: 0.5 %
    np.testing.assert_allclose(a["PSL_dB"], b["PSL_dB"], atol=0.05)                    # dB
    assert a["L_PSF"][5] == pytest.approx(0.0, abs=1e-9)   # the full array against itself


def test_evaluate_returns_every_metric_and_the_figures_of_merit(tiny):
    masks = np.zeros((3, 16))
    masks[0, [0, 5, 10, 15]] = 1
    masks[1, [0, 3, 12, 15]] = 1
    masks[2, [5]] = 1   # k = 1
    res = tiny.evaluate(masks, return_planes=True)
    assert set(res) == {*METRIC_NAMES, *MERIT_NAMES, "planes"}
    for name in METRIC_NAMES:
        assert res[name].shape == (3,) and np.isfinite(res[name]).all()
    assert (res["PSL_dB"] <= 0).all()
    assert res["planes"]["xy"].shape == (3, *tiny.coords["xy"].shape[:2])
    assert tiny.breakdown_names == MERIT_NAMES and tiny.element_grid == (4, 4)


def test_bad_selections_are_refused(tiny):
    with pytest.raises(SelectionError, match="shape"):
        tiny.evaluate(np.ones((1, 17)))
    with pytest.raises(SelectionError, match="empty"):
        tiny.evaluate(np.zeros((1, 16)))
    with pytest.raises(SelectionError, match="NaN"):
        tiny.evaluate(np.full((1, 16), np.nan))
    with pytest.raises(ParameterError, match="planes"):
        tiny.kernels(np.ones((1, 16)))


def test_mask_loss_gradient_and_counters(tiny):
    tiny.reset_counters()
    w = torch.full((2, 16), 0.3, dtype=torch.float64, requires_grad=True)
    total, terms = tiny.mask_loss(w)
    total.sum().backward()
    assert torch.isfinite(w.grad).all() and float(w.grad.abs().max()) > 0
    assert set(terms) <= {"L_PSF", "L_contrast", "L_SLR"}
    assert tiny.evaluations == 2 and tiny.gradient_steps == 1
    P = torch.full((16, 4), 0.25, dtype=torch.float64, requires_grad=True)
    total, _ = tiny.selection_loss(P, P, 0)
    total.backward()
    assert torch.isfinite(P.grad).all()


def test_psf_terms_gradcheck(tiny_path, tiny):
    w = torch.rand(1, 16, dtype=torch.float64).mul(0.5).add(0.3).requires_grad_(True)

    def f(x):
        t = tiny.psf_terms(x, terms=["L_PSF", "L_contrast"])
        return t["L_PSF"] + t["L_contrast"]

    assert torch.autograd.gradcheck(f, (w,), eps=1e-6, atol=1e-5, rtol=1e-3)


def test_the_fast_path_is_cached_and_restored(tiny_path, tmp_path, monkeypatch):
    monkeypatch.setenv("ARRAYSEL_CACHE", str(tmp_path))
    a = MatrixObjective(tiny_path, dtype=torch.float64)
    names = [p.name for p in tmp_path.iterdir() if p.name.startswith("psf3-fast-") and "." not in p.name]
    assert len(names) == 1
    b = MatrixObjective(tiny_path, dtype=torch.float64)
    assert b.model.check.get("restored") and b.model.exact is None
    m = np.zeros((1, 16))
    m[0, [1, 4, 6, 11]] = 1
    np.testing.assert_allclose(a.evaluate(m)["Mean"], b.evaluate(m)["Mean"], rtol=1e-12)


def test_worker_factory_rebuilds_the_matrix_objective(tiny):
    f = tiny.worker_factory()
    again = f()
    assert again.image_kind == "planes" and again.chunk == tiny.chunk and hash(f) == hash(tiny.worker_factory())


def _registry():
    from test_conformance import REGISTRY
    return REGISTRY


@pytest.mark.parametrize("name", _registry().names())
def test_every_selector_runs_on_a_small_matrix_scene(name, tiny_path):
    obj = build_objective(tiny_path)
    cls = _registry()[name]
    row = Experiment(obj, cls, options={}, budget=Budget(evaluations=24), seed=0, k=4).run()
    assert row["error"] == "", row["error"]
    sel = [int(i) for i in row["elements"].split()]
    assert len(sel) == 4 and len(set(sel)) == 4 and all(0 <= i < 16 for i in sel)
    assert np.isfinite(row["Mean"]) and "PSL_dB" in row


def test_a_comparison_of_neighbourhood_searches_prepares_a_matrix_objective(tiny_path, tmp_path):
    # swap, memetic and polish score neighbourhoods: the runner prepares the objective first,
    # which a 3-D scene does by doing nothing (its neighbourhoods are its masks)
    from arraysel.run.compare import compare

    obj = build_objective(tiny_path)
    assert obj.prepare_neighbourhoods() is True
    res = compare(obj, ["swap", "memetic"], out_dir=tmp_path / "c", seeds=[0], budget=Budget(evaluations=30),
                  progress=False, figures=False)
    assert not res.failures
    assert set(res.table["config"]) >= {"swap", "memetic"}


def test_cli_psf_and_evaluate_write_every_plane_with_its_coordinates(tiny_path, tmp_path):
    from arraysel.cli.main import main

    out = tmp_path / "p.npz"
    assert main(["psf", "--scene", tiny_path, "--elements", "0,5,10,15", "--out", str(out)]) == 0
    z = np.load(out)
    for k in ("xy", "xz", "yz"):
        assert z[f"psf_{k}"].shape == z[f"coords_{k}"].shape[:2] == z[f"psf_ref_{k}"].shape
    assert float(z["coords_xy"][..., 2].std()) == 0.0   # the C-plane lies at one depth
    masks = tmp_path / "m.txt"
    masks.write_text("0 5 10 15\n1 2 3 4\n")
    csv, npz = tmp_path / "e.csv", tmp_path / "e.npz"
    assert main(["evaluate", "--scene", tiny_path, "--masks", str(masks), "--out", str(csv),
                 "--psf-out", str(npz)]) == 0
    head = csv.read_text().splitlines()[0].split(",")
    assert head == ["elements", *METRIC_NAMES, *MERIT_NAMES]
    e = np.load(npz)
    assert e["psf"].shape == (2, e["coords"].shape[0])
    np.testing.assert_allclose(e["psf"][0][: z["psf_xy"].size], z["psf_xy"].reshape(-1), rtol=1e-5, atol=1e-7)
    bad = tmp_path / "bad.txt"
    bad.write_text("0 5 10 16\n")   # an index >= nx * ny
    assert main(["evaluate", "--scene", tiny_path, "--masks", str(bad), "--out", str(tmp_path / "b.csv")]) != 0
    assert not (tmp_path / "b.csv").exists()
