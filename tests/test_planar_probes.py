"""Grids with blank rows and arbitrary planar layouts: geometry, the 3-D physics on them, probe
files, scene keys, and the uniform and spiral selectors and figures on them."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from arraysel.errors import ParameterError
from arraysel.physics.probe_files import load_probe
from arraysel.physics.probes import MatrixProbe, PlanarProbe, get_probe, list_probes, probe_from_positions

pytestmark = pytest.mark.usefixtures("one_thread")


def _holey(nx=6, ny=7, blank_rows=(3,), **kw):
    return get_probe("MATRIX-32x32", nx=nx, ny=ny, blank_rows=blank_rows, **kw)


# --------------------------------------------------------------------------- the grid with blank rows
def test_catalogue_32x35_has_1024_elements_in_four_banks():
    p = get_probe("MATRIX-32x35")
    assert "MATRIX-32x35" in list_probes() and isinstance(p, MatrixProbe)
    assert (p.nx, p.ny, p.blank_rows, p.n_elements, p.grid_shape, p.layout_grid) == (32, 35, (8, 17, 26), 1024,
                                                                                       (35, 32), None)
    ix, iy = p.element_grid(np.arange(1024))
    # four banks of 8 rows x 32 columns = 256 elements, each bank's rows contiguous in the grid
    for bank in range(4):
        rows = np.unique(iy[bank * 256:(bank + 1) * 256])
        assert rows.tolist() == list(range(9 * bank, 9 * bank + 8))
    pos = p.element_positions()
    assert pos.shape == (1024, 3) and np.all(pos[:, 2] == 0)
    # the gap: rows 7 and 9 are two pitches apart, the grid stays centred on (0, 0)
    y = np.unique(np.round(pos[:, 1], 12))
    assert np.isclose(np.max(np.diff(y)), 2 * p.pitch_y) and np.isclose(y[0], -17 * p.pitch_y)


def test_index_rule_skips_the_blank_cells():
    p = _holey()                                        # 6 x 7, row 3 blank: 36 elements
    assert p.n_elements == 36 and p.cells.tolist() == [c for c in range(42) if c // 6 != 3]
    e = np.arange(36)
    ix, iy = p.element_grid(e)
    assert np.array_equal(p.element_index(ix, iy), e)
    assert p.element_index(0, 4) == 18                  # first element after the blank row
    with pytest.raises(ParameterError, match="blank cell"):
        p.element_index(2, 3)
    with pytest.raises(ParameterError, match=r"\[0, 35\]"):
        p.element_grid(36)
    np.testing.assert_allclose(p.element_positions()[18], [-2.5 * p.pitch_x, 1 * p.pitch_y, 0])
    full = get_probe("MATRIX-32x32", nx=6, ny=7)
    assert np.array_equal(full.cells, np.arange(42)) and full.layout_grid == (7, 6)
    assert np.array_equal(full.element_index(ix, iy), iy * 6 + ix)   # iy * nx + ix without blank rows


def test_full_grid_repr_is_unchanged_and_blank_columns_work():
    full = get_probe("MATRIX-32x32")
    assert repr(full) == ("MatrixProbe(name='MATRIX-32x32', nx=32, ny=32, pitch_x=0.0003, pitch_y=0.0003, "
                          "width=0.00025, height=0.00025, fc=3000000.0, bandwidth=70.0, baffle='soft')")
    p = get_probe("MATRIX-32x32", nx=5, ny=4, blank_columns=[0, 4], blank_rows=[2])
    assert p.n_elements == 9 and "blank_columns=(0, 4)" in repr(p)
    assert p.element_grid(np.arange(9))[0].tolist() == [1, 2, 3] * 3


@pytest.mark.parametrize("kw, key", [(dict(blank_rows=[7]), "blank_rows"), (dict(blank_rows=[1, 1]), "repeats"),
                                     (dict(blank_rows=list(range(7))), "leaves no row"),
                                     (dict(blank_columns=[-1]), "blank_columns"), (dict(blank_rows="3"), "list")])
def test_blank_rows_are_checked(kw, key):
    with pytest.raises(ParameterError, match=key):
        get_probe("MATRIX-32x32", nx=6, ny=7, **kw)


# --------------------------------------------------------------------------- planar layouts
def test_planar_probe_and_its_checks():
    pos = [(0.0, 0.0), (1e-3, 0.0), (0.3e-3, 0.7e-3)]
    p = PlanarProbe("ring", pos, width=2.5e-4, height=2.5e-4, fc=3e6)
    assert p.n_elements == 3 and p.is_matrix and p.layout_grid is None
    np.testing.assert_array_equal(p.element_positions()[:, :2], np.array(pos))
    assert p.mask([2]).tolist() == [0, 0, 1] and p.aperture == (1e-3, 0.7e-3)
    with pytest.raises(ParameterError, match="elements 0 and 1 overlap"):
        PlanarProbe("x", [(0, 0), (2e-4, 0)], width=2.5e-4, height=2.5e-4, fc=3e6)
    with pytest.raises(ParameterError, match="positions must be an"):
        PlanarProbe("x", [0.0, 1.0], width=2.5e-4, height=2.5e-4, fc=3e6)
    with pytest.raises(ParameterError, match="z = 0"):
        PlanarProbe("x", [(0, 0, 1e-3)], width=2.5e-4, height=2.5e-4, fc=3e6)
    with pytest.raises(ParameterError, match="within 1 m"):
        PlanarProbe("x", [(0, 0), (5.0, 0)], width=2.5e-4, height=2.5e-4, fc=3e6)


def test_positions_become_the_simplest_probe():
    for p in (get_probe("MATRIX-32x35"), _holey(), get_probe("MATRIX-32x32", nx=5, ny=6, blank_rows=[0],
                                                               blank_columns=[2])):
        got = probe_from_positions(p.name, p.element_positions(), p.width, p.height, p.fc, p.bandwidth)
        assert got == p
    # blank rows on both edges leave the positions of a smaller grid: that grid (its files keep the fields)
    p = get_probe("MATRIX-32x32", nx=5, ny=6, blank_rows=[0, 5])
    got = probe_from_positions(p.name, p.element_positions(), p.width, p.height, p.fc, p.bandwidth)
    assert (got.ny, got.blank_rows) == (4, ()) and np.array_equal(got.element_positions(), p.element_positions())
    p = _holey()
    pos = p.element_positions()
    # another order, a shifted grid, a missing single element: a planar layout holding them exactly
    for q in (pos[::-1], pos + [1e-5, 0, 0], np.delete(pos, 7, axis=0)):
        got = probe_from_positions("x", q, p.width, p.height, p.fc)
        assert isinstance(got, PlanarProbe)
        np.testing.assert_array_equal(got.element_positions(), q)


def test_volume_physics_runs_on_a_planar_layout_as_on_the_grid():
    from arraysel.physics.probes import Acquisition
    from arraysel.physics.volume import MatrixPSF, MatrixPSFSetup, diverging_delays3, tilt_grid

    grid = _holey(nx=4, ny=5, blank_rows=(2,))
    planar = PlanarProbe("same", grid.element_positions(), grid.width, grid.height, grid.fc, grid.bandwidth)
    acq = Acquisition.for_probe(grid)
    ax, ay = tilt_grid(2, 1, 8, 8)
    lam = acq.c / grid.fc
    planes = []
    for p in (grid, planar):
        d = diverging_delays3(p, ax, ay, 5e-3, acq)
        setup = MatrixPSFSetup(p, acq, d, (0.0, 0.0, 12e-3), half_x=lam, half_y=lam, half_z=lam, pixel=lam / 2)
        planes.append(MatrixPSF(setup, dtype=torch.float64).planes(torch.ones(1, p.n_elements, dtype=torch.float64)))
    for name in planes[0]:
        torch.testing.assert_close(planes[0][name], planes[1][name], rtol=1e-12, atol=0)


# --------------------------------------------------------------------------- probe files and scenes
def test_load_probe_from_csv_npy_npz(tmp_path):
    p = _holey()
    pos = p.element_positions()
    (tmp_path / "p.csv").write_text("x,y\n" + "".join(f"{float(x)!r},{float(y)!r}\n" for x, y in pos[:, :2]))
    np.save(tmp_path / "p.npy", pos[:, :2])
    np.save(tmp_path / "must.npy", pos[:, :2].T)      # MUST's 2 x Ne layout
    np.savez(tmp_path / "p.npz", positions=pos[:, :2], width=p.width, height=p.height, fc=p.fc, bandwidth=70.0)
    fields = dict(width=p.width, height=p.height, fc=p.fc, bandwidth=70.0, name=p.name)
    for f in ("p.csv", "p.npy", "must.npy"):
        assert load_probe(tmp_path / f, **fields) == p
    assert load_probe(tmp_path / "p.npz", name=p.name) == p
    assert load_probe(tmp_path / "p.npy", width=p.width, height=p.height, fc=p.fc).name == "p"
    # fields in # lines, replaced by keyword arguments
    (tmp_path / "q.csv").write_text('# fc: 5e6\n# width: 2e-4\n# height: 2e-4\n# name: "ring"\n'
                                    "x,y\n0,0\n1e-3,0\n0.2e-3,0.9e-3\n")
    q = load_probe(tmp_path / "q.csv", fc=4e6)
    assert isinstance(q, PlanarProbe) and (q.name, q.fc, q.width, q.n_elements) == ("ring", 4e6, 2e-4, 3)


@pytest.mark.parametrize("name, text, match", [
    ("a.csv", "x,z\n0,0\n", "no column 'y'"),
    ("a.csv", "x,y\n0,abc\n", "row 1: y = 'abc' is not a number"),
    ("a.csv", "x,y\n0,0,1\n", "row 1 has 3 values"),
    ("a.csv", "x,y\n", "holds no element row"),
    ("a.csv", "x,y\n0,0\n0,0\n", "overlap"),
    ("a.txt", "x,y\n0,0\n", "must end with one of"),
    ("a.json", "{not json", "not valid JSON"),
    ("a.json", '{"elements": []}', "non-empty list"),
    ("a.npz", "garbage", "not a NumPy .npz"),
    ("a.mat", "garbage", "not a MATLAB .mat"),
    ("a.npy", "garbage", "not a NumPy array file"),
])
def test_bad_probe_files_are_refused_in_one_line(tmp_path, name, text, match):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ParameterError, match=match) as exc:
        load_probe(path, width=2.5e-4, height=2.5e-4, fc=3e6)
    msg = str(exc.value)
    assert msg.startswith(str(path)) and "\n" not in msg


def test_probe_files_name_missing_fields_and_paths(tmp_path):
    (tmp_path / "p.csv").write_text("x,y\n0,0\n")
    with pytest.raises(ParameterError, match="gives no fc"):
        load_probe(tmp_path / "p.csv", width=1e-4, height=1e-4)
    with pytest.raises(ParameterError, match="does not exist"):
        load_probe(tmp_path / "none.csv")
    with pytest.raises(ParameterError, match="cannot be given with a probe file"):
        load_probe(tmp_path / "p.csv", nx=4)
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object))
    with pytest.raises(ParameterError, match="not a NumPy array file"):
        load_probe(tmp_path / "obj.npy", width=1e-4, height=1e-4, fc=3e6)


def test_scene_keys_blank_rows_and_probe_file(tmp_path):
    from arraysel.scenes.schema import load_scene

    sc = load_scene({"base": "matrix-1024", "probe": {"name": "MATRIX-32x32", "ny": 35, "blank_rows": [8, 17, 26]}})
    assert sc.probe() == get_probe("MATRIX-32x35").replace(name="MATRIX-32x32")
    p = _holey()
    sub = tmp_path / "probes"
    sub.mkdir()
    (sub / "mine.csv").write_text("# width: 0.00025\n# height: 0.00025\nx,y\n"
                                  + "".join(f"{float(x)!r},{float(y)!r}\n" for x, y in p.element_positions()[:, :2]))
    (tmp_path / "s.toml").write_text('base = "matrix-1024"\n[probe]\nfile = "probes/mine.csv"\nname = "mine"\n'
                                     'fc = 3e6\nbandwidth = 70\n[selection]\nk = 12\n')
    sc = load_scene(str(tmp_path / "s.toml"))
    assert sc.probe() == p.replace(name="mine") and sc.matrix_setup().delays.shape == (9, 36)
    with pytest.raises(ParameterError, match="probe.nx cannot be set with probe.file"):
        load_scene({"base": "matrix-1024", "probe": {"file": str(sub / "mine.csv"), "nx": 4}}).probe()
    with pytest.raises(ParameterError, match=r"probe.blank_rows\[0\]"):
        load_scene({"base": "matrix-1024", "probe": {"blank_rows": ["a"]}})
    with pytest.raises(ParameterError, match="probe.blank_rows applies to matrix probes only"):
        load_scene({"base": "paper", "probe": {"blank_rows": [1]}}).probe()


# --------------------------------------------------------------------------- selectors and figures
def _run(name, obj, k, **options):
    from arraysel.run.experiment import Experiment
    from arraysel.selectors.contract import Budget
    from arraysel.selectors.registry import build_plugin_manager, get_registry

    reg = get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))
    row = Experiment(obj, reg[name], options=options, budget=Budget(evaluations=10), seed=0, k=k).run()
    assert row["error"] == "", row["error"]
    return [int(i) for i in row["elements"].split()]


def _toy_on(probe, k):
    """The toy objective with a 2-D array's layout: no full grid, the probe's element centres."""
    from arraysel.objective.toy import ToyObjective

    obj = ToyObjective(probe.n_elements, k)
    obj.element_positions = probe.element_positions()
    return obj


def test_uniform_and_spiral_on_a_grid_with_blank_rows():
    from arraysel.selectors.layouts import fermat_spiral_layout, uniform_layout

    p = get_probe("MATRIX-32x32", nx=8, ny=9, blank_rows=(4,))     # 64 elements: 8 x 8 connected
    sel = _run("uniform", _toy_on(p, 16), 16)
    assert sel == uniform_layout(64, 16, (8, 8))                   # the full-grid rule on the connected rows
    ix, iy = p.element_grid(np.array(sel))
    assert sorted(set(ix.tolist())) == [0, 2, 4, 6] and sorted(set(iy.tolist())) == [0, 2, 5, 7]
    sel = _run("spiral", _toy_on(p, 16), 16)
    assert sel == fermat_spiral_layout(p.element_positions(), 16, "none") and len(set(sel)) == 16
    # a grid missing single elements: the rule on the grid with holes; an irregular layout: spread
    pos = np.delete(get_probe("MATRIX-32x32", nx=6, ny=6).element_positions(), [3, 20], axis=0)
    holed = PlanarProbe("holed", pos, 2.5e-4, 2.5e-4, 3e6)
    rng = np.random.default_rng(0)
    ring = PlanarProbe("ring", np.c_[np.cos(np.arange(30) * 0.2), np.sin(np.arange(30) * 0.2)] * 5e-3
                       + rng.uniform(0, 1e-5, (30, 2)), 2.5e-4, 2.5e-4, 3e6)
    for probe, k in ((holed, 9), (ring, 7)):
        for name in ("uniform", "spiral"):
            sel = _run(name, _toy_on(probe, k), k)
            assert len(sel) == k == len(set(sel)) and max(sel) < probe.n_elements


def test_layout_masks_figure_and_compare_masks(tmp_path):
    from arraysel.report.layout_plots import layout_masks_figure
    from arraysel.report.plots import save_figure

    p = get_probe("MATRIX-32x35")
    masks = np.zeros((2, 1024), dtype=bool)
    masks[0, ::4] = masks[1, 1::4] = True
    fig = layout_masks_figure(["a", "b"], masks, p.element_positions())
    assert len(fig.axes) == 2 and fig.axes[0].get_title() == "a (256 of 1024)"
    save_figure(fig, tmp_path / "m.png")
    assert (tmp_path / "m.png").stat().st_size > 1000


def test_a_3d_scene_with_a_blank_row_end_to_end(tmp_path):
    """The objective of a scene whose probe has a blank row: no full grid, its element centres; the
    uniform and spiral selectors and compare's masks figure use them."""
    from scene_texts import TINY_MATRIX_SCENE

    from arraysel.objective.contract import element_layout
    from arraysel.objective.matrix_objective import MatrixObjective
    from arraysel.run.store import _masks_figure
    from arraysel.selection import Selection

    path = tmp_path / "holey.toml"
    path.write_text(TINY_MATRIX_SCENE.replace("ny = 4", "ny = 5\nblank_rows = [2]"))
    obj = MatrixObjective(str(path), dtype=torch.float64, fast=False)
    grid, pos = element_layout(obj)
    probe = obj.setup.probe
    assert grid is None and probe.n_elements == 16 and np.array_equal(pos, probe.element_positions())
    sel = {name: _run(name, obj, 4) for name in ("uniform", "spiral")}
    ix, iy = probe.element_grid(np.array(sel["uniform"]))
    assert sorted(set(ix.tolist())) == [0, 2] and sorted(set(iy.tolist())) == [0, 3]
    res = obj.evaluate(np.array([np.isin(np.arange(16), s) for s in sel.values()], dtype=float))
    assert np.isfinite(res["Mean"]).all()
    _masks_figure(obj, {k: Selection(tuple(v), 16) for k, v in sel.items()}, tmp_path)
    assert (tmp_path / "masks.png").stat().st_size > 1000


def test_beam_pattern_of_a_grid_with_blank_rows_and_of_a_planar_layout():
    """The beam pattern reads a blank-row grid's element nodes (not iy * nx + ix) and a planar
    layout's centres: both give the pattern of the same centres given as an array."""
    from arraysel.physics.beampattern import BeamPattern

    p = get_probe("MATRIX-32x32", nx=4, ny=5, blank_rows=(2,))
    planar = PlanarProbe("same", p.element_positions(), p.width, p.height, p.fc, p.bandwidth)
    w = torch.rand(2, p.n_elements, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    kw = dict(n_freq=3, dtype=torch.float64)
    ref = BeamPattern(p.element_positions(), fc=p.fc, bandwidth=p.bandwidth, **kw)
    for probe in (p, planar):
        bp = BeamPattern.from_probe(probe, step=((ref.du[1] - ref.du[0]).item(), (ref.dv[1] - ref.dv[0]).item()), **kw)
        torch.testing.assert_close(bp.pattern(w), ref.pattern(w), rtol=1e-9, atol=1e-12)
