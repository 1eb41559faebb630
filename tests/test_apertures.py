"""Separate transmit and receive apertures (docs/apertures.md): the scene's [aperture] section and its
errors, each mode's scores against the physics with the two masks (1-D exact path, 3-D fast and
exact paths, sector beam pattern), the shared default unchanged, the transmit/receive quota as
channel groups with counts, every built-in selector feasible on the virtual problem, and the
outputs (tx_elements / rx_elements columns, apertures.png)."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from arraysel.constraints import ConstraintError, Constraints, aperture_constraints
from arraysel.errors import ParameterError, SelectionError
from arraysel.objective.aperture import ApertureObjective, split_apertures, split_events
from arraysel.objective.build import build_objective
from arraysel.objective.toy import ToyObjective
from arraysel.run.experiment import Experiment
from arraysel.scenes.schema import load_scene
from arraysel.selectors.contract import Budget
from arraysel.selectors.relax import sequential_selection
from scene_texts import TINY_MATRIX_SCENE, TINY_SCENE


def _scene(tmp_path, text, name, **aperture):
    p = tmp_path / f"{name}.toml"
    lines = "".join(f"{k} = {v!r}\n".replace("'", '"') for k, v in aperture.items())
    p.write_text(text + ("\n[aperture]\n" + lines if aperture else ""))
    return load_scene(str(p))


def _masks(n, k, rows, seed):
    rng = np.random.default_rng(seed)
    out = np.zeros((rows, n), dtype=bool)
    for r in out:
        r[rng.choice(n, k, replace=False)] = True
    return out


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    d = tmp_path_factory.mktemp("apertures")
    return {mode: build_objective(_scene(d, TINY_SCENE, f"tiny-{mode}", **({} if mode == "none" else {"mode": mode})),
                                  dtype=torch.float64)
            for mode in ("none", "shared", "full-tx", "separate")}


# --------------------------------------------------------------------------- the scene keys
@pytest.mark.parametrize("aperture, needle", [
    ({"mode": "both"}, "aperture.mode = 'both' is not allowed; choose one of ['shared', 'full-tx', 'separate', 'per-transmit']"),
    ({"mode": "shared", "k_tx": 4}, "aperture.k_tx applies to aperture.mode = 'separate' or 'per-transmit' only"),
    ({"mode": "full-tx", "k_rx": 4}, "aperture.k_rx applies to aperture.mode = 'separate' or 'per-transmit' only"),
    ({"mode": "separate", "k_tx": 9}, "aperture.k_tx = 9 is out of range; allowed: [1, 8]"),
    ({"mode": "separate", "k_rx": 0}, "aperture.k_rx = 0 is out of range"),
    ({"mode": "separate", "width": 3}, "unknown scene key 'aperture.width'"),
])
def test_bad_aperture_keys_name_the_key(tmp_path, aperture, needle):
    with pytest.raises(ParameterError, match=needle.replace("[", r"\[").replace("]", r"\]").replace("(", r"\(")):
        _scene(tmp_path, TINY_SCENE, "bad", **aperture)


def test_separate_lifts_the_scene_constraints_onto_both_apertures(tmp_path):
    sp = build_objective(_scene(tmp_path, TINY_SCENE + '\n[constraints]\nforced_on = [0]\nforced_off = [7]\n', "both",
                                mode="separate", k_tx=3, k_rx=2), dtype=torch.float64)
    c = sp.constraints
    assert (c.n_elements, c.k) == (16, 5) and c.forced_on == (0, 8) and c.forced_off == (7, 15)
    for name in ("swap", "random", "ste"):
        row = Experiment(sp, name, budget=Budget(evaluations=30), seed=0, progress=False).run()
        assert row["error"] == "", row["error"]
        tx, rx = split_apertures([int(v) for v in row["elements"].split()], 8, "separate")
        assert (len(tx), len(rx)) == (3, 2) and 0 in tx and 0 in rx and 7 not in tx and 7 not in rx, (name, tx, rx)


def test_separate_keeps_channel_groups_in_each_aperture():
    each = Constraints(8, 4, groups=[0, 0, 1, 1, 2, 2, 3, 3])
    c = aperture_constraints(8, 4, 4, each)
    assert (c.n_elements, c.k) == (16, 8) and c.groups.tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7]
    masks = c.random_masks(np.random.default_rng(0), 50)
    assert c.feasible_rows(masks).all()
    for half in (masks[:, :8], masks[:, 8:]):   # one element of every channel in each aperture
        assert (half.reshape(50, 4, 2).sum(2) == 1).all()
    with pytest.raises(ConstraintError, match="constraint groups"):
        c.check([0, 1, 2, 4, 8, 10, 12, 14])     # channel 0 twice in the transmit aperture
    for name in ("swap", "anneal", "genetic", "ste", "random", "uniform"):
        obj = ToyObjective(16, c.k, grid=(4, 4), constraints=c)
        row = Experiment(obj, name, budget=Budget(evaluations=60), seed=1, progress=False).run()
        assert row["error"] == "" and c.feasible([int(v) for v in row["elements"].split()]), (name, row["error"])


@pytest.mark.parametrize("each, k_tx, needle", [
    (Constraints(8, 4, groups=[0, 0, 1, 1, 2, 2, 3, 3]), 3,
     r"aperture.k_tx = 3: the channel groups .* select exactly 4 elements in each aperture; allowed: 4"),
    (Constraints(8, 3, groups=[0, 0, 1, 1, 2, 2, 3, 3], group_mode="at-most-one"), 3,
     r"constraints.mode = 'at-most-one' together with aperture.mode = 'separate' is not supported"),
    (Constraints(8, 4, symmetry="x", positions=np.c_[np.arange(8.0) - 3.5, np.zeros(8)]), 4,
     r"constraints.symmetry = 'x' together with aperture.mode = 'separate' is not supported"),
])
def test_separate_constraints_it_cannot_lift_are_refused_by_name(each, k_tx, needle):
    with pytest.raises(ParameterError, match=needle):
        aperture_constraints(8, k_tx, 4, each)


# --------------------------------------------------------------------------- the physics of each mode
def test_shared_is_the_objective_of_before_bit_for_bit(tiny):
    none, shared = tiny["none"], tiny["shared"]
    assert type(none) is type(shared) and not isinstance(shared, ApertureObjective)
    m = _masks(8, 4, 3, 0)
    a, b = none.evaluate(m), shared.evaluate(m)
    assert all(np.array_equal(a[k], b[k]) for k in a)


def test_full_tx_is_the_exact_physics_of_an_all_ones_transmit(tiny):
    ft, psf = tiny["full-tx"], tiny["none"].psf
    assert (ft.n_elements, ft.k, ft.k_tx) == (8, 4, 8)
    rx = _masks(8, 4, 3, 1)
    ours = ft.evaluate(rx, return_kernels=True)["kernels"]
    ref = psf.kernels_exact(torch.ones(3, 8, dtype=torch.float64), receive=torch.tensor(rx, dtype=torch.float64))
    np.testing.assert_allclose(ours, ref.numpy(), rtol=0, atol=1e-12)
    shared = tiny["none"].evaluate(rx, return_kernels=True)["kernels"]   # and it is not the shared mask's
    assert np.abs(ours - shared).max() > 1e-3


def test_separate_is_the_physics_of_the_two_masks(tiny):
    sp, psf = tiny["separate"], tiny["none"].psf
    assert (sp.n_elements, sp.k) == (16, 8)
    tx, rx = _masks(8, 4, 3, 2), _masks(8, 4, 3, 3)
    ours = sp.evaluate(np.concatenate([tx, rx], 1), return_kernels=True)["kernels"]
    ref = psf.kernels_exact(torch.tensor(tx, dtype=torch.float64), receive=torch.tensor(rx, dtype=torch.float64))
    np.testing.assert_allclose(ours, ref.numpy(), rtol=0, atol=1e-12)
    # the same mask on both halves is the shared aperture (which the fast path gives within its bound)
    same = sp.evaluate(np.concatenate([tx, tx], 1))["Mean"]
    np.testing.assert_allclose(same, tiny["none"].evaluate(tx)["Mean"], rtol=2e-3)
    with pytest.raises(SelectionError, match="empty receive aperture"):
        sp.evaluate(np.concatenate([tx, np.zeros_like(rx)], 1))


def test_separate_losses_have_gradients_in_both_halves(tiny):
    sp = tiny["separate"]
    w = torch.full((2, 16), 0.5, dtype=torch.float64, requires_grad=True)
    total, _ = sp.mask_loss(w)
    total.sum().backward()
    assert w.grad[:, :8].abs().sum() > 0 and w.grad[:, 8:].abs().sum() > 0
    P = torch.zeros(16, 8, dtype=torch.float64)
    P[[0, 2, 4, 6, 9, 11, 13, 15], range(8)] = 1.0
    loss, terms = sp.selection_loss(P.requires_grad_(True), P.detach().clone(), 0)
    assert torch.isfinite(loss) and "L_PSF" in terms


@pytest.mark.slow
def test_3d_separate_fast_path_matches_the_exact_path(tmp_path):
    from arraysel.physics.volume import MatrixPSF

    sp = build_objective(_scene(tmp_path, TINY_MATRIX_SCENE, "tiny3d", mode="separate", k_tx=5, k_rx=4),
                         dtype=torch.float64)
    inner = sp.inner
    assert inner.fast, inner.exact_notice()
    tx, rx = _masks(16, 5, 3, 4), _masks(16, 4, 3, 5)
    exact = MatrixPSF(inner.model.setup if hasattr(inner.model, "setup") else inner.scene.matrix_setup(),
                      dtype=torch.float64)
    t, r = torch.tensor(tx, dtype=torch.float64), torch.tensor(rx, dtype=torch.float64)
    fast = inner.model.planes(t, receive=r)
    ref = exact.planes(t, receive=r)
    for name, img in ref.items():
        err = float((fast[name] - img).abs().max() / img.abs().max())
        assert err < 2e-2, (name, err)
    got = sp.evaluate(np.concatenate([tx, rx], 1))
    want = inner.evaluate(tx, receive=rx)
    assert np.array_equal(got["Mean"], want["Mean"])


PER_TX_SCENE = TINY_MATRIX_SCENE.replace("n_tx_x = 1\nn_tx_y = 1", "n_tx_x = 2\nn_tx_y = 1")


def test_per_transmit_apertures_on_a_matrix_scene(tmp_path):
    """Two transmit events, each with its own 3 of 16 elements, and a receive aperture of 4: the
    score is the physics of the three masks, the quota is kept by the selectors, the table's
    transmit column is the union of the events."""
    pt = build_objective(_scene(tmp_path, PER_TX_SCENE, "tiny3d-pt", mode="per-transmit", k_tx=3, k_rx=4),
                         dtype=torch.float64)
    inner = pt.inner
    assert (pt.n_events, pt.n_elements, pt.k) == (2, 48, 10) and pt.element_grid == (12, 4)
    assert pt.constraints.counts.tolist() == [3, 3, 4]
    ev, rx = _masks(16, 3, 4, 7).reshape(2, 2, 16), _masks(16, 4, 2, 8)
    got = pt.evaluate(np.concatenate([ev[:, 0], ev[:, 1], rx], 1))
    want = inner.evaluate(ev, receive=rx)
    assert np.array_equal(got["Mean"], want["Mean"])
    one = inner.evaluate(ev[:, 0], receive=rx)["Mean"]     # the first event's aperture for both events
    assert not np.allclose(got["Mean"], one)
    same = inner.evaluate(np.stack([ev[:, 0], ev[:, 0]], 1), receive=rx)["Mean"]
    np.testing.assert_allclose(same, one, rtol=1e-9)
    for name in ("swap", "random", "anneal"):
        row = Experiment(pt, name, budget=Budget(evaluations=30), seed=0, progress=False).run()
        assert row["error"] == "", row["error"]
        sel = [int(v) for v in row["elements"].split()]
        events, r = split_events(sel, 16, 2)
        assert [len(e) for e in events] == [3, 3] and len(r) == 4, (name, sel)
        assert split_apertures(sel, 16, "per-transmit", 2)[0] == sorted(set(events[0]) | set(events[1]))
    w = torch.tensor(np.concatenate([ev[:1, 0], ev[:1, 1], rx[:1]], 1), dtype=torch.float64).requires_grad_(True)
    total, _ = pt.mask_loss(w)
    total.sum().backward()
    assert bool(torch.isfinite(w.grad).all()) and float(w.grad[0, :16].abs().sum()) > 0 and float(w.grad[0, 16:32].abs().sum()) > 0
    assert torch.isfinite(total).all()
    with pytest.raises(SelectionError, match=r"empty transmit aperture .* \(batch position, transmit event\) \[\(0, 1\)\]"):
        pt.evaluate(np.concatenate([ev[:1, 0], 0 * ev[:1, 1], rx[:1]], 1))


def test_compare_and_export_of_per_transmit_apertures(tmp_path):
    import pandas as pd

    from arraysel.cli.main import main
    scene = tmp_path / "pt.toml"
    scene.write_text(PER_TX_SCENE + '\n[aperture]\nmode = "per-transmit"\nk_tx = 3\nk_rx = 4\n')
    out, exp = tmp_path / "cmp", tmp_path / "exp"
    assert main(["compare", "--scene", str(scene), "--selectors", "random", "--seeds", "0", "--budget-evals", "5",
                 "--out", str(out), "--no-progress", "--in-process", "--no-figures"]) == 0
    row = pd.read_csv(out / "table1.csv", dtype=str).set_index("config").loc["random"]
    events = [[int(v) for v in part.split()] for part in row["tx_elements"].split(" | ")]
    assert [len(e) for e in events] == [3, 3] and len(row["rx_elements"].split()) == 4
    assert main(["export", "--compare", str(out), "--config", "random", "--out", str(exp), "--formats", "csv"]) == 0
    lines = (exp / "transmit_events.csv").read_text().splitlines()[2:]
    assert [[int(v) for v in line.split(",")[1].split()] for line in lines] == events
    ch = pd.read_csv(exp / "channels.csv", comment="#")
    assert ch.loc[ch["transmit"] == 1, "element"].tolist() == sorted(set(events[0]) | set(events[1]))


def test_per_transmit_is_refused_on_a_1d_scene(tmp_path):
    with pytest.raises(ParameterError, match="aperture.mode = 'per-transmit' applies to matrix-probe scenes"):
        _scene(tmp_path, TINY_SCENE, "pt1d", mode="per-transmit")


def test_sector_separate_is_the_two_way_pattern_of_the_two_masks():
    from arraysel.objective.sector_objective import SectorBeams
    tree = {"name": "tiny-sector", "probe": {"name": "MATRIX-32x32", "nx": 8, "ny": 8},
            "acquisition": {"fs_over_fc": 4.0},
            "transmit": {"n_tx_x": 3, "n_tx_y": 3, "max_tilt_deg": 20.0, "max_tilt_deg_y": 20.0,
                         "source_distance": "5 mm"},
            "sector": {"points": [[0.0, 0.0, "15 mm"]], "n_freq": 4, "fresh_random": 2},
            "selection": {"k": 16}, "weights": {"L_PSF": 10.0, "L_contrast": 10.0, "L_SLR": 10.0},
            "aperture": {"mode": "separate", "k_tx": 20, "k_rx": 12}}
    sp = build_objective(load_scene(copy.deepcopy(tree)), dtype=torch.float64)
    assert isinstance(sp.inner.beams, SectorBeams) and (sp.n_elements, sp.k, sp.element_grid) == (128, 32, (16, 8))
    tx, rx = _masks(64, 20, 2, 6), _masks(64, 12, 2, 7)
    got = sp.evaluate(np.concatenate([tx, rx], 1))
    t, r = torch.tensor(tx, dtype=torch.float64), torch.tensor(rx, dtype=torch.float64)
    want = sp.inner.psf_terms(t, receive=r)
    np.testing.assert_allclose(got["Mean"], want["Mean"].numpy(), rtol=1e-12)
    other = sp.inner.psf_terms(r, receive=t)["Mean"].numpy()  # (rx, tx) swapped: the pattern T R is symmetric
    np.testing.assert_allclose(got["Mean"], other, rtol=1e-9)
    assert sp.fresh_random_masks().shape == (2, 128) and sp.constraints.feasible_rows(sp.fresh_random_masks()).all()


# --------------------------------------------------------------------------- the quota
def test_the_quota_is_channel_groups_with_counts():
    c = aperture_constraints(8, 3, 2)
    assert (c.n_elements, c.k) == (16, 5) and c.counts.tolist() == [3, 2]
    rng = np.random.default_rng(0)
    masks = c.random_masks(rng, 40)
    assert c.feasible_rows(masks).all()
    assert (masks[:, :8].sum(1) == 3).all() and (masks[:, 8:].sum(1) == 2).all()
    a, b = c.swap_pairs(masks[0])
    assert a.size == 3 * 5 + 2 * 6 and ((a < 8) == (b < 8)).all()   # a swap stays in its half
    assert c.feasible(c.crossover(masks[1], masks[2], rng)) and c.feasible(c.random_swaps(masks[3], 4, rng))
    assert c.project(np.arange(16.0)) == [5, 6, 7, 14, 15]           # the best of each half
    with pytest.raises(ConstraintError, match="group 1 of apertures.*holds 3 selected elements.*at most 2 are allowed"):
        c.check([0, 1, 8, 9, 10])
    with pytest.raises(ConstraintError, match="4 elements selected, the scene asks for 5"):
        c.check([0, 1, 8, 9])
    raw = _masks(16, 5, 300, 1)
    assert np.array_equal(c.feasible_rows(raw), [c.feasible(r) for r in raw])
    with pytest.raises(ParameterError, match="aperture.k_rx = 9 is out of range"):
        aperture_constraints(8, 3, 9)
    with pytest.raises(ParameterError, match="group_counts other than one need mode = 'exactly-one'"):
        Constraints(16, 5, groups=np.repeat([0, 1], 8), group_counts=[3, 2], group_mode="at-most-one")


def test_a_separate_neighbourhood_scores_the_selectors_units(tiny):
    """The wrapper's own neighbourhood and loss model, not the inner objective's (of 8 elements),
    reached through the attribute forwarding."""
    sp = tiny["separate"]
    mask = np.zeros(16, dtype=bool)
    mask[[0, 2, 5, 7, 9, 10, 12, 15]] = True
    out, into = np.array([[0], [9]]), np.array([[1], [11]])
    got = sp.neighbourhood().evaluate(mask, out, into)["Mean"]
    moved = np.stack([mask, mask])
    moved[0, [0, 1]] = [False, True]
    moved[1, [9, 11]] = [False, True]
    np.testing.assert_array_equal(got, sp.evaluate(moved)["Mean"])
    assert sp.loss_model().gradient(mask.astype(float)).shape == (16,)


def test_ste_columns_draw_within_their_half():
    logits = torch.randn(16, 5, generator=torch.Generator().manual_seed(0))
    logits[8:, :3] += 100.0     # the transmit columns would rather take receive units: they cannot
    rel = sequential_selection(logits, 1.0, groups=np.repeat([0, 1], 8), by_column=True, counts=[3, 2])
    assert sorted(i < 8 for i in rel.indices) == [False, False, True, True, True]
    assert all(i < 8 for i in rel.indices[:3]) and len(set(rel.indices)) == 5


# --------------------------------------------------------------------------- every selector
def _builtin_names():
    from arraysel.selectors.registry import get_registry
    return sorted(get_registry().names())


@pytest.mark.parametrize("name", _builtin_names())
def test_every_builtin_selector_gives_a_feasible_separate_selection(name):
    cons = aperture_constraints(8, 3, 2)
    obj = ToyObjective(16, cons.k, grid=(4, 4), constraints=cons)
    row = Experiment(obj, name, budget=Budget(evaluations=200), seed=1, progress=False).run()
    assert row["error"] == "", row["error"]
    sel = [int(v) for v in row["elements"].split()]
    assert cons.feasible(sel), (name, sel)


def test_a_separate_search_on_the_tiny_scene(tiny):
    sp = tiny["separate"]
    for name in ("swap", "ste", "uniform"):
        row = Experiment(sp, name, budget=Budget(evaluations=40), seed=0, progress=False).run()
        assert row["error"] == "", row["error"]
        tx, rx = split_apertures([int(v) for v in row["elements"].split()], 8, "separate")
        assert len(tx) == 4 and len(rx) == 4 and max(rx) < 8


def test_compare_writes_both_apertures(tmp_path):
    import pandas as pd

    from arraysel.report.tables import aperture_columns
    table = pd.DataFrame({"config": ["full", "a"], "elements": ["0 1 2 3 4 5", "0 2 4"], "Mean": [0.1, 0.2]})
    out = aperture_columns(table, {"scene": {"aperture": {"mode": "separate"}}, "n_elements": 6})
    assert list(out.columns) == ["config", "elements", "tx_elements", "rx_elements", "Mean"]
    assert out["tx_elements"].tolist() == ["0 1 2", "0 2"] and out["rx_elements"].tolist() == ["0 1 2", "1"]
    ft = aperture_columns(table, {"scene": {"aperture": {"mode": "full-tx"}}, "n_elements": 6})
    assert ft["tx_elements"].tolist() == ["0 1 2 3 4 5"] * 2
    assert ft["rx_elements"].tolist() == ["0 1 2 3 4 5", "0 2 4"]
    assert aperture_columns(table, {"scene": {}, "n_elements": 6}) is table


def test_apertures_figure_draws_both_masks():
    from arraysel.report.layout_plots import apertures_figure
    pos = ToyObjective(16, 4, grid=(4, 4)).element_positions
    tx, rx = np.zeros((1, 16), bool), np.zeros((1, 16), bool)
    tx[0, [0, 1, 2]], rx[0, [2, 3]] = True, True
    fig = apertures_figure(["a"], tx, rx, pos)
    faces = fig.axes[0].collections[0].get_facecolors()
    assert len(faces) == 16 and "tx 3, rx 2, both 1" in fig.axes[0].get_title()


@pytest.mark.slow
def test_compare_and_export_of_separate_apertures(tmp_path):
    """A separate comparison on a 4 x 4 matrix probe: table1.csv's tx_elements / rx_elements,
    apertures.png, and `arraysel export --compare` writing the two apertures."""
    import pandas as pd

    from arraysel.cli.main import main
    scene = tmp_path / "t3.toml"
    scene.write_text(TINY_MATRIX_SCENE + '\n[aperture]\nmode = "separate"\nk_tx = 6\nk_rx = 4\n')
    out, exp = tmp_path / "cmp", tmp_path / "exp"
    assert main(["compare", "--scene", str(scene), "--selectors", "uniform", "--seeds", "0", "--budget-evals", "5",
                 "--out", str(out), "--no-progress", "--in-process"]) == 0
    row = pd.read_csv(out / "table1.csv", dtype=str).set_index("config").loc["uniform"]
    tx, rx = [int(v) for v in row["tx_elements"].split()], [int(v) for v in row["rx_elements"].split()]
    assert len(tx) == 6 and len(rx) == 4
    assert (out / "apertures.png").is_file()
    assert main(["export", "--compare", str(out), "--config", "uniform", "--out", str(exp), "--formats", "csv"]) == 0
    ch = pd.read_csv(exp / "channels.csv", comment="#")
    assert ch.loc[ch["transmit"] == 1, "element"].tolist() == tx
    assert ch.loc[ch["receive"] == 1, "element"].tolist() == rx


def test_full_tx_keeps_the_scene_constraints_on_the_receive_aperture(tmp_path):
    obj = build_objective(_scene(tmp_path, TINY_SCENE + "\n[constraints]\nforced_on = [0]\nforced_off = [7]\n",
                                 "ftc", mode="full-tx"), dtype=torch.float64)
    assert obj.aperture_mode == "full-tx" and obj.constraints.forced_on == (0,)
    row = Experiment(obj, "swap", budget=Budget(evaluations=30), seed=0, progress=False).run()
    assert row["error"] == "", row["error"]
    sel = [int(v) for v in row["elements"].split()]
    assert 0 in sel and 7 not in sel and len(sel) == 4
