"""Deterministic layouts (arraysel.selectors.layouts), the layout capability of the objectives,
and the uniform and spiral selectors on 1-D and matrix arrays."""
from __future__ import annotations

import numpy as np
import pytest

from arraysel.errors import ParameterError
from arraysel.objective.contract import HasLayout, check_element_grid, element_layout
from arraysel.objective.toy import TOY_PITCH, ToyObjective, ToyObjectiveFactory
from arraysel.selectors.layouts import (CHIRP_PERIODS, GOLDEN_ANGLE_DEG, TAPERS, chirped_layouts,
                                        fermat_spiral_layout, fermat_spiral_points,
                                        snap_to_elements, taper_density, tapered_line_layout, uniform_layout,
                                        uniform_subgrid)

GRIDS = [(32, 32), (8, 8), (3, 4), (16, 64), (5, 7), (1, 9), (9, 1)]


def _check(sel, n, k):
    assert len(sel) == k and len(set(sel)) == k, sel
    assert all(isinstance(i, int) and 0 <= i < n for i in sel), sel
    assert sel == sorted(sel)


# ------------------------------------------------------------------ uniform


def test_uniform_1d_is_the_paper_rule():
    for n in (12, 64, 128, 7):
        for k in range(1, n + 1):
            assert uniform_layout(n, k) == [(i * n) // k for i in range(k)]
    assert uniform_layout(64, 32) == list(range(0, 64, 2))


def test_uniform_on_a_grid_thins_both_directions():
    sel = uniform_layout(1024, 256, (32, 32))
    iy, ix = np.divmod(sel, 32)
    assert sorted(set(iy)) == list(range(0, 32, 2)) and sorted(set(ix)) == list(range(0, 32, 2))
    assert len(sel) == 256
    assert uniform_subgrid((32, 32), 256) == (16, 16)
    # equal thinning factors on a non-square grid: every second element both ways
    assert uniform_subgrid((16, 64), 256) == (8, 32)
    sel = uniform_layout(16 * 64, 256, (16, 64))
    iy, ix = np.divmod(sel, 64)
    assert sorted(set(iy)) == list(range(0, 16, 2)) and sorted(set(ix)) == list(range(0, 64, 2))


@pytest.mark.parametrize("grid", GRIDS)
def test_uniform_grid_exactly_k_distinct_for_every_k(grid):
    n = grid[0] * grid[1]
    ks = range(1, n + 1) if n <= 64 else [1, 2, 3, 17, 100, 250, 255, 256, 257, 511, n - 1, n]
    for k in ks:
        sel = uniform_layout(n, k, grid)
        _check(sel, n, k)
        assert sel == uniform_layout(n, k, grid)             # deterministic
    assert uniform_layout(n, n, grid) == list(range(n))


def test_uniform_fewest_changes_rule():
    # 250 of 32 x 32: sub-grid 15 x 17 (255, the product closest to 250), then the 5 elements
    # farthest from the centre go (corners first)
    assert uniform_subgrid((32, 32), 250) == (15, 17)
    sub = set(int(iy * 32 + ix) for iy in (np.arange(15) * 32) // 15 for ix in (np.arange(17) * 32) // 17)
    sel = uniform_layout(1024, 250, (32, 32))
    removed = sub - set(sel)
    assert len(removed) == 5 and set(sel) <= sub
    corners = {0, 31, 30 * 32, 30 * 32 + 30}   # the sub-grid's corners (rows 0..30, columns 0..30)
    assert corners & removed
    # too few: the added element fills the largest gap
    assert uniform_subgrid((3, 4), 5) in {(1, 4), (2, 3), (2, 2), (1, 5)}
    sel = uniform_layout(12, 5, (3, 4))
    _check(sel, 12, 5)


def test_uniform_on_a_row_grid_equals_1d():
    for k in range(1, 10):
        assert uniform_layout(9, k, (1, 9)) == uniform_layout(9, k)


def test_uniform_bad_input():
    with pytest.raises(ParameterError, match="k = 0 is out of range"):
        uniform_layout(12, 0)
    with pytest.raises(ParameterError, match="k = 13 is out of range"):
        uniform_layout(12, 13, (3, 4))
    with pytest.raises(ParameterError, match=r"element_grid = \(3, 5\) holds 15 elements, but n_elements = 12"):
        uniform_layout(12, 4, (3, 5))
    with pytest.raises(ParameterError, match="element_grid must be"):
        uniform_layout(12, 4, 12)


# ------------------------------------------------------------------ spiral


def test_spiral_points_follow_the_golden_angle_and_the_sunflower_radii():
    pts = fermat_spiral_points(100, taper="none")
    r = np.hypot(pts[:, 0], pts[:, 1])
    np.testing.assert_allclose(r, np.sqrt(np.arange(100) / 100), atol=1e-6)
    theta = np.arctan2(pts[1:, 1], pts[1:, 0])
    step = np.rad2deg(np.mod(np.diff(theta), 2 * np.pi))
    np.testing.assert_allclose(step, GOLDEN_ANGLE_DEG, atol=1e-9)
    assert GOLDEN_ANGLE_DEG == pytest.approx(137.5078, abs=1e-4)


@pytest.mark.parametrize("taper", TAPERS)
def test_spiral_points_density_follows_the_taper(taper):
    k = 4000
    r = np.hypot(*fermat_spiral_points(k, taper=taper).T)
    assert r.max() <= 1.0 and np.all(np.diff(r) > 0)
    # points per unit area in rings, against the taper (normalised to the centre ring)
    edges = np.linspace(0, 1, 11)
    counts = np.histogram(r, edges)[0]
    area = np.pi * np.diff(edges ** 2)
    mid = 0.5 * (edges[1:] + edges[:-1])
    dens = counts / area
    w = taper_density(mid, taper)
    np.testing.assert_allclose(dens[:8] / dens[0], w[:8] / w[0], rtol=0.08, atol=0.01)


@pytest.mark.parametrize("grid", GRIDS)
@pytest.mark.parametrize("taper", TAPERS)
def test_spiral_exactly_k_distinct_inside_the_grid(grid, taper):
    n = grid[0] * grid[1]
    for k in sorted({1, 2, n // 4 or 1, n // 2 or 1, n - 1 or 1, n}):
        sel = fermat_spiral_layout(grid, k, taper)
        _check(sel, n, k)
        assert sel == fermat_spiral_layout(grid, k, taper)   # deterministic
    assert fermat_spiral_layout(grid, n, taper) == list(range(n))


def test_spiral_k1_is_the_central_element():
    assert fermat_spiral_layout((5, 5), 1) == [12]
    assert fermat_spiral_layout((5, 7), 1) == [17]


@pytest.mark.parametrize("taper", ["none", "cosine"])
def test_spiral_covers_the_aperture_symmetrically(taper):
    sel = fermat_spiral_layout((32, 32), 256, taper)
    iy, ix = np.divmod(np.array(sel), 32)
    # the centroid near the grid's centre (15.5, 15.5), every quadrant used about equally
    assert abs(iy.mean() - 15.5) < 1.0 and abs(ix.mean() - 15.5) < 1.0
    quads = np.bincount((iy >= 16) * 2 + (ix >= 16), minlength=4)
    assert quads.min() >= 0.85 * quads.max(), quads
    # the untapered spiral reaches the rim of the inscribed circle
    r = np.hypot(iy - 15.5, ix - 15.5)
    if taper == "none":
        assert r.max() > 14


def test_the_taper_thins_the_rim():
    for taper in ("cosine", "blackman"):
        sel = fermat_spiral_layout((32, 32), 256, taper)
        iy, ix = np.divmod(np.array(sel), 32)
        r = np.hypot(iy - 15.5, ix - 15.5)
        yy, xx = np.mgrid[:32, :32]
        rr = np.hypot(yy - 15.5, xx - 15.5)
        fill = lambda lo, hi: ((r >= lo) & (r < hi)).sum() / ((rr >= lo) & (rr < hi)).sum()  # noqa: E731
        assert fill(10, 16) < 0.5 * fill(0, 5), taper
    # and tapered vs plain: fewer rim elements
    rim = lambda sel: (np.hypot(*(np.divmod(np.array(sel), 32) - np.array([[15.5], [15.5]]))) > 10).sum()  # noqa: E731
    assert rim(fermat_spiral_layout((32, 32), 256, "blackman")) < rim(fermat_spiral_layout((32, 32), 256, "cosine")) \
        < rim(fermat_spiral_layout((32, 32), 256, "none"))


def test_spiral_on_positions_equals_the_grid_for_a_square_pitch():
    ny, nx, pitch = 8, 12, 3e-4
    iy, ix = np.divmod(np.arange(ny * nx), nx)
    pos = np.stack([(ix - (nx - 1) / 2) * pitch, (iy - (ny - 1) / 2) * pitch, np.zeros(ny * nx)], axis=1)
    for k in (1, 10, 24, 50, 96):
        assert fermat_spiral_layout(pos, k) == fermat_spiral_layout((ny, nx), k)
    with pytest.raises(ParameterError, match="positions must be"):
        fermat_spiral_layout(np.zeros((4, 4)), 2)
    with pytest.raises(ParameterError, match="taper"):
        fermat_spiral_layout((4, 4), 2, taper="kaiser")


def test_snapping_takes_the_nearest_free_element():
    pos = np.arange(5.0)[:, None]
    assert snap_to_elements(np.array([[2.2], [2.1], [2.0], [1.6]]), pos) == [2, 3, 1, 0]
    assert snap_to_elements(np.array([[2.5], [2.5]]), pos) == [2, 3]      # ties: the smaller index
    with pytest.raises(ParameterError):
        snap_to_elements(np.zeros((6, 1)), pos)


def test_tapered_line_layout():
    for n in (1, 2, 7, 12, 64):
        for k in range(1, n + 1):
            for taper in TAPERS:
                _check(tapered_line_layout(n, k, taper), n, k)
    assert tapered_line_layout(64, 16, "none") == list(range(1, 64, 4))
    sel = np.array(tapered_line_layout(128, 32, "blackman"))
    # denser in the middle than at the ends, symmetric about the centre
    assert ((sel > 32) & (sel < 96)).sum() > 2 * ((sel <= 32) | (sel >= 96)).sum()
    assert abs(sel.mean() - 63.5) < 1.0


# ------------------------------------------------------------------ the layout capability


def test_toy_layout_attributes():
    obj = ToyObjective(12, 6)
    assert obj.element_grid is None and isinstance(obj, HasLayout)
    grid, pos = element_layout(obj)
    assert grid is None and pos.shape == (12, 3)
    np.testing.assert_allclose(np.diff(pos[:, 0]), TOY_PITCH)
    mat = ToyObjective(12, 6, grid=(3, 4))
    grid, pos = element_layout(mat)
    assert grid == (3, 4)
    # element index iy * nx + ix: element 5 is (iy, ix) = (1, 1)
    np.testing.assert_allclose(pos[5], [-0.5 * TOY_PITCH, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(pos[4], [-1.5 * TOY_PITCH, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(pos[0, 1], -TOY_PITCH)
    assert ToyObjectiveFactory(12, 6, grid=(3, 4))().element_grid == (3, 4)
    assert mat.worker_factory()().element_grid == (3, 4)
    assert mat.worker_factory().key() != obj.worker_factory().key()
    with pytest.raises(ParameterError, match=r"element_grid = \(3, 3\) holds 9 elements"):
        ToyObjective(12, 6, grid=(3, 3))


def test_toy_matrix_uses_the_2d_array_factor():
    # a mask and its transpose on a square grid score the same on the 2-D array factor's lobe terms
    obj = ToyObjective(16, 4, grid=(4, 4))
    a = np.zeros((4, 4))
    a[0, :] = 1                        # one row: narrow in x, wide in y
    res = obj.evaluate(np.stack([a.ravel(), a.T.ravel()]))
    for name in ("L_contrast", "L_SLR_i"):
        assert res[name][0] == pytest.approx(res[name][1], rel=1e-5), name
    line = ToyObjective(16, 4).evaluate(np.stack([a.ravel(), a.T.ravel()]))
    assert line["L_SLR_i"][0] != pytest.approx(line["L_SLR_i"][1], rel=1e-3)


def test_element_layout_checks():
    class Bare:
        n_elements = 4

    assert element_layout(Bare()) == (None, None)
    bad = Bare()
    bad.element_grid = (2, 3)
    with pytest.raises(ParameterError, match="element_grid"):
        element_layout(bad)
    bad = Bare()
    bad.element_positions = np.zeros((3, 3))
    with pytest.raises(ParameterError, match=r"element_positions must be a finite \(4, 3\)"):
        element_layout(bad)
    assert check_element_grid([2, 2], 4) == (2, 2)


# ------------------------------------------------------------------ the selectors


def _run(name, obj, k, **options):
    from arraysel.run.experiment import Experiment
    from arraysel.selectors.contract import Budget
    from arraysel.selectors.registry import build_plugin_manager, get_registry

    reg = get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))
    exp = Experiment(obj, reg[name], options=options, budget=Budget(evaluations=10), seed=0, k=k)
    row = exp.run()
    assert row["error"] == "", row["error"]
    return [int(i) for i in row["elements"].split()], row


def test_uniform_selector_is_unchanged_in_1d_and_thins_a_matrix():
    sel, row = _run("uniform", ToyObjective(64, 32), 32)
    assert sel == list(range(0, 64, 2)) and row["evaluations"] == 1
    sel, _ = _run("uniform", ToyObjective(64, 16, grid=(8, 8)), 16)
    assert sel == uniform_layout(64, 16, (8, 8))
    iy, ix = np.divmod(sel, 8)
    assert sorted(set(iy)) == [0, 2, 4, 6] and sorted(set(ix)) == [0, 2, 4, 6]


def test_spiral_selector_on_a_matrix_and_on_a_line():
    sel, row = _run("spiral", ToyObjective(64, 16, grid=(8, 8)), 16)
    assert sel == fermat_spiral_layout((8, 8), 16, "none") and row["evaluations"] == 1
    sel, _ = _run("spiral", ToyObjective(64, 16, grid=(8, 8)), 16, taper="none", rotation_deg=30.0)
    assert sel == fermat_spiral_layout((8, 8), 16, "none", 30.0)
    sel, _ = _run("spiral", ToyObjective(64, 16), 16, taper="blackman")
    assert sel == tapered_line_layout(64, 16, "blackman")


def test_the_psf_objective_declares_a_1d_layout(paper_objective):
    grid, pos = element_layout(paper_objective)
    assert grid is None and isinstance(paper_objective, HasLayout)
    # P4-2v: 64 elements, 0.3 mm pitch, on the x axis centred on 0
    assert pos.shape == (64, 3)
    np.testing.assert_allclose(np.diff(pos[:, 0]), paper_objective.setup.probe.pitch, rtol=1e-12)
    assert pos[:, 0].mean() == pytest.approx(0.0, abs=1e-15) and not pos[:, 1:].any()


# ------------------------------------------------------------------ chirped


@pytest.mark.parametrize("n,k,grid", [(64, 32, None), (128, 64, None), (128, 20, None), (7, 1, None), (7, 7, None),
                                      (1, 1, None), (1024, 256, (32, 32)), (12, 5, (3, 4)), (9, 4, (1, 9))])
def test_chirped_layouts_hold_exactly_k_distinct_elements(n, k, grid):
    masks = chirped_layouts(np.random.default_rng(0), n, k, 16, grid)
    assert masks.shape == (16, n) and masks.dtype == bool
    assert (masks.sum(axis=1) == k).all()
    again = chirped_layouts(np.random.default_rng(0), n, k, 16, grid)
    assert (masks == again).all()  # reproducible from the generator


def _mean_run(masks) -> float:
    runs = [len(r) for m in masks for r in "".join("#" if v else "." for v in m).split(".") if r]
    return float(np.mean(runs))


def test_chirped_layouts_span_alternation_to_blocks():
    """Half the elements: the family holds nearly alternating layouts (runs of one element, the
    finest period of two pitches) and block layouts (runs of several adjacent elements), and
    layouts whose runs grow from the centre to the edges."""
    masks = chirped_layouts(np.random.default_rng(1), 128, 64, 256)
    runs = np.array([_mean_run(m[None]) for m in masks])
    assert runs.min() < 1.3 and runs.max() > 3.0
    centre = np.array([_mean_run(m[None, 48:80]) for m in masks])
    edges = np.array([_mean_run(np.concatenate([m[:24], m[-24:]])[None]) for m in masks])
    assert (edges > 2 * centre).any() and (centre > 2 * edges).any()
    assert CHIRP_PERIODS["centre"][0] == CHIRP_PERIODS["edge"][0] == 1.0  # the finest period is drawn too


def test_chirped_layouts_scale_with_the_duty():
    """The finest period is 1 / min(k/Ne, 1 - k/Ne): with a quarter of the elements the active
    runs stay short, and with three quarters the inactive runs do (the complement's pattern)."""
    few = chirped_layouts(np.random.default_rng(2), 128, 32, 64)
    many = chirped_layouts(np.random.default_rng(2), 128, 96, 64)
    assert _mean_run(few) < 2.5 and _mean_run(~many) < 2.5
    assert _mean_run(many) > _mean_run(few)


def test_chirped_layouts_name_a_bad_parameter():
    with pytest.raises(ParameterError, match="k"):
        chirped_layouts(np.random.default_rng(0), 8, 9, 4)
    with pytest.raises(ParameterError, match="m"):
        chirped_layouts(np.random.default_rng(0), 8, 4, 0)
    with pytest.raises(ParameterError):
        chirped_layouts(np.random.default_rng(0), 12, 4, 4, (5, 5))


def test_tukey_density_is_flat_then_a_cosine_fall():
    rho = np.array([0.0, 0.3, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(taper_density(rho, "tukey", 0.5), [1.0, 1.0, 1.0, 0.5, 0.0], atol=1e-12)
    # alpha = 1 is the Hann window, cos^2(pi rho / 2)
    r = np.linspace(0, 1, 21)
    np.testing.assert_allclose(taper_density(r, "tukey", 1.0), np.cos(0.5 * np.pi * r) ** 2, atol=1e-12)
    for bad in (0.0, -0.1, 1.5):
        with pytest.raises(ParameterError, match="alpha"):
            taper_density(r, "tukey", bad)


def test_tukey_spiral_fills_the_centre_and_thins_the_rim_with_alpha():
    yy, xx = np.mgrid[:32, :32]
    rr = np.hypot(yy - 15.5, xx - 15.5)

    def rim(sel):
        iy, ix = np.divmod(np.array(sel), 32)
        return (np.hypot(iy - 15.5, ix - 15.5) > 11).sum()
    sels = {a: fermat_spiral_layout((32, 32), 256, "tukey", alpha=a) for a in (0.1, 0.5, 1.0)}
    for sel in sels.values():
        _check(sel, 1024, 256)
    # a wider fall leaves fewer elements near the rim; alpha -> 0 approaches the plain sunflower
    assert rim(sels[1.0]) < rim(sels[0.5]) < rim(sels[0.1]) <= rim(fermat_spiral_layout((32, 32), 256, "none")) + 3
    assert rr.size == 1024


def test_spiral_selector_uses_the_tukey_option():
    from arraysel.selectors.registry import get_registry
    cls = get_registry()["spiral"]
    obj = ToyObjective(1024, 256, grid=(32, 32))
    for alpha in (0.25, 1.0):
        chosen = cls(taper="tukey", tukey_alpha=alpha).select(obj, 256, 0)
        assert chosen == fermat_spiral_layout((32, 32), 256, "tukey", alpha=alpha)
    with pytest.raises(ParameterError, match="tukey_alpha"):
        cls(taper="tukey", tukey_alpha=0.0)
