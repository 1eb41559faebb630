"""PSFs and planes as netCDF-4 files (arraysel.report.netcdf): coordinates, units, the scene, and the
complex kernels read back equal to the .npz the same command writes."""
from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("xarray")
pytest.importorskip("h5netcdf")

from scene_texts import TINY_MATRIX_SCENE, TINY_SCENE  # noqa: E402

from arraysel.cli.main import main  # noqa: E402
from arraysel.report.netcdf import open_psf  # noqa: E402


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    d = tmp_path_factory.mktemp("scenes")
    (d / "tiny.toml").write_text(TINY_SCENE)
    (d / "tiny3d.toml").write_text(TINY_MATRIX_SCENE)
    return {"1d": str(d / "tiny.toml"), "3d": str(d / "tiny3d.toml")}


def test_psf_of_a_1d_scene_as_netcdf_reads_back_as_the_npz(scenes, tmp_path):
    import xarray as xr

    nc, npz = tmp_path / "psf.nc", tmp_path / "psf.npz"
    for out in (nc, npz):
        assert main(["psf", "--scene", scenes["1d"], "--elements", "0,2,5,7", "--out", str(out)]) == 0
    z = np.load(npz)
    ds = open_psf(nc)
    assert ds["psf"].dtype == np.complex64 and ds["psf"].dims == ("z", "x")
    np.testing.assert_array_equal(ds["psf"].values, z["psf"])          # real and imaginary parts, bit for bit
    np.testing.assert_array_equal(ds["psf_ref"].values, z["psf_ref"])
    assert ds["elements"].values.tolist() == [0, 2, 5, 7]
    assert float(ds["L_PSF"]) == pytest.approx(float(z["L_PSF"]))
    # coordinates in metres from the peak, one pixel apart
    assert ds["x"].attrs["units"] == "m" and ds["z"].attrs["units"] == "m"
    assert np.diff(ds["x"].values) == pytest.approx(float(z["pixel"])) and float(ds["x"][16 // 2]) == 0.0
    assert ds.attrs["scene"] == "tiny" and ds.attrs["k"] == 4 and ds.attrs["n_elements"] == 8
    assert ds.attrs["pixel_pitch_m"] == pytest.approx(float(z["pixel"]))
    assert json.loads(ds.attrs["scene_json"])["probe"]["n_elements"] == 8
    raw = xr.open_dataset(nc, engine="h5netcdf")   # any netCDF reader: the parts as float variables
    assert {"psf_real", "psf_imag"} <= set(raw.data_vars) and raw["psf_real"].attrs["units"] == "1"
    raw.close()


def test_a_scene_with_several_points_has_a_point_dimension(scenes, tmp_path):
    scene = tmp_path / "two.toml"
    scene.write_text(TINY_SCENE.replace('name = "tiny"', 'name = "two"') +
                     '[medium]\npoints = [[0.0, "20 mm"], ["1 mm", "30 mm"]]\n')
    nc, npz = tmp_path / "p.nc", tmp_path / "p.npz"
    for out in (nc, npz):
        assert main(["psf", "--scene", str(scene), "--elements", "0,2,5,7", "--out", str(out)]) == 0
    ds, z = open_psf(nc), np.load(npz)
    assert ds["psf"].dims == ("point", "z", "x") and ds.sizes["point"] == 2
    np.testing.assert_array_equal(ds["psf"].values, z["psf"])
    assert ds["point_z"].values == pytest.approx([0.020, 0.030]) and ds["point_x"].values == pytest.approx([0, 1e-3])


def test_evaluate_streams_one_selection_per_mask_into_netcdf(scenes, tmp_path):
    masks = tmp_path / "m.txt"
    masks.write_text("0 2 5 7\n1 2 3 4\n# a comment\n0 1 6 7\n")
    csv, nc, npz = tmp_path / "e.csv", tmp_path / "e.nc", tmp_path / "e.npz"
    assert main(["evaluate", "--scene", scenes["1d"], "--masks", str(masks), "--out", str(csv),
                 "--psf-out", str(nc)]) == 0
    first = csv.read_text()
    assert main(["evaluate", "--scene", scenes["1d"], "--masks", str(masks), "--out", str(csv),
                 "--psf-out", str(npz)]) == 0
    assert csv.read_text() == first                                 # the same CSV either way
    ds, z = open_psf(nc), np.load(npz)
    assert ds["psf"].dims == ("selection", "z", "x") and ds.sizes["selection"] == 3
    np.testing.assert_array_equal(ds["psf"].values, z["psf"])
    assert ds["elements"].values.tolist() == [[0, 2, 5, 7], [1, 2, 3, 4], [0, 1, 6, 7]]
    import pandas as pd

    np.testing.assert_allclose(ds["Mean"].values, pd.read_csv(csv)["Mean"].to_numpy(), rtol=1e-7)


def test_planes_of_a_3d_scene_as_netcdf(scenes, tmp_path):
    nc, npz = tmp_path / "p.nc", tmp_path / "p.npz"
    for out in (nc, npz):
        assert main(["psf", "--scene", scenes["3d"], "--elements", "0,5,10,15", "--out", str(out)]) == 0
    z, ds = np.load(npz), open_psf(nc)
    for p in ("xy", "xz", "yz"):
        np.testing.assert_array_equal(ds[f"psf_{p}"].values, z[f"psf_{p}"])
        np.testing.assert_array_equal(ds[f"psf_ref_{p}"].values, z[f"psf_ref_{p}"])
        for i, axis in enumerate("xyz"):
            c = ds[f"{p}_{axis}"]
            assert c.attrs["units"] == "m" and c.dims == (f"{p}_row", f"{p}_col")
            np.testing.assert_array_equal(c.values, z[f"coords_{p}"][..., i])
    assert ds["PSL_dB"].attrs["units"] == "dB" and ds["width_x_6dB"].attrs["units"] == "m"
    masks = tmp_path / "m.txt"
    masks.write_text("0 5 10 15\n1 2 3 4\n")
    assert main(["evaluate", "--scene", scenes["3d"], "--masks", str(masks), "--out", str(tmp_path / "e.csv"),
                 "--psf-out", str(tmp_path / "e.nc")]) == 0
    e = open_psf(tmp_path / "e.nc")
    assert e["psf_xy"].dims == ("selection", "xy_row", "xy_col") and e.sizes["selection"] == 2
    np.testing.assert_allclose(e["psf_xy"].values[0], z["psf_xy"], rtol=1e-5, atol=1e-7)


def test_a_missing_netcdf_package_is_refused_before_any_work(scenes, tmp_path, capsys, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "h5netcdf" else real(name, *a))
    assert main(["psf", "--scene", "no-such-scene", "--out", str(tmp_path / "p.nc")]) == 2
    err = capsys.readouterr().err
    assert "needs h5netcdf" in err and "pip install 'arraysel[netcdf]'" in err
    assert main(["psf", "--scene", scenes["1d"], "--out", str(tmp_path / "p.txt")]) == 2
    assert "--out must end with .npz or a netCDF ending" in capsys.readouterr().err
