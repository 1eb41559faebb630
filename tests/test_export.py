"""``arraysel export``: channel maps, MUST parameter sets and mask images, their round trips, and
the PSF of an exported selection simulated by PyMUST against arraysel's exact 3-D path."""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import torch

from arraysel.cli.main import main
from arraysel.errors import ParameterError
from arraysel.physics.probe_files import Aperture, read_aperture
from arraysel.physics.probes import Acquisition, PlanarProbe, get_probe
from arraysel.report.export import EXPORT_FILES, channel_rows, export_selection, must_param

pytestmark = pytest.mark.usefixtures("one_thread")

ROUND_TRIP = ("csv", "json", "mat", "npz")


def _holey():
    return get_probe("MATRIX-32x32", nx=6, ny=7, blank_rows=[3])          # 36 elements


def _apertures():
    rng = np.random.default_rng(3)
    p = _holey()
    planar = PlanarProbe("spiral", [(3e-3 * np.sqrt(i / 20) * np.cos(2.4 * i), 3e-3 * np.sqrt(i / 20) * np.sin(2.4 * i))
                                    for i in range(20)], width=2e-4, height=2e-4, fc=3e6, bandwidth=60, baffle=1.5)
    return {
        "shared": Aperture.of(p, rng.choice(36, 12, replace=False)),
        "weighted": Aperture.of(p, rng.choice(36, 12, replace=False), weights=rng.uniform(0.2, 1.0, 12)),
        "tx-rx": Aperture.of(p, transmit=np.arange(36), receive=[1, 5, 9, 30], weights=rng.uniform(0.5, 2, 36)),
        "channels": Aperture.of(p, [0, 7, 20], channels=np.arange(36) % 9),
        "planar": Aperture.of(planar, [0, 3, 4, 19], weights=[1, 0.5, 0.25, 2]),
        "grid-32x35": Aperture.of(get_probe("MATRIX-32x35"), rng.choice(1024, 256, replace=False)),
    }


@pytest.mark.parametrize("name", list(_apertures()))
def test_export_then_import_returns_the_same_probe_selection_and_weights(tmp_path, name):
    ap = _apertures()[name]
    paths = export_selection(ap, tmp_path, acquisition=Acquisition.for_probe(ap.probe))
    assert set(paths) == set(EXPORT_FILES) and all(p.stat().st_size > 0 for p in paths.values())
    for fmt in ROUND_TRIP:
        back = read_aperture(paths[fmt])
        assert back.same_as(ap), fmt
        assert type(back.probe) is type(ap.probe) and back.probe == ap.probe, fmt


def test_channel_map_columns_and_rules():
    ap = _apertures()["tx-rx"]
    rows = channel_rows(ap)
    assert list(rows[0]) == ["channel", "element", "ix", "iy", "x", "y", "transmit", "receive", "weight"]
    assert [r["element"] for r in rows] == list(range(36))
    # without channel groups: the active elements numbered in element order
    assert [r["channel"] for r in rows] == list(range(36))
    assert rows[18]["ix"] == 0 and rows[18]["iy"] == 4                      # the row after the blank one
    assert sum(r["receive"] for r in rows) == 4 and all(r["transmit"] == 1 for r in rows)
    shared = _apertures()["shared"]
    chans = [r["channel"] for r in channel_rows(shared) if r["channel"] is not None]
    assert chans == list(range(12))
    with pytest.raises(ParameterError, match=r"elements \[0, 9\] both transmit on channel 0"):
        Aperture.of(_holey(), [0, 9], channels=np.arange(36) % 9)
    with pytest.raises(ParameterError, match="element 4 is active .* but has no channel"):
        Aperture.of(_holey(), [4], channels=np.full(36, -1))
    with pytest.raises(ParameterError, match="element 2 is active but its weight is 0"):
        Aperture.of(_holey(), [1, 2], weights=[1.0, 0.0])
    with pytest.raises(ParameterError, match="give 36 values .* or 2"):
        Aperture.of(_holey(), [1, 2], weights=[1.0, 1.0, 1.0])
    with pytest.raises(ParameterError, match="no element"):
        Aperture.of(_holey(), [])


def test_must_param_fields():
    ap = _apertures()["tx-rx"]
    acq = Acquisition.for_probe(ap.probe, attenuation=0.5)
    d = must_param(ap, acq, np.zeros((2, 36)))
    assert d["elements"].shape == (2, 36) and d["Nelements"] == 36 and d["baffle"] == "soft"
    np.testing.assert_array_equal(d["elements"].T, ap.probe.element_positions()[:, :2])
    np.testing.assert_array_equal(d["TXapodization"][0], ap.weights)
    np.testing.assert_array_equal(d["RXapodization"][0], np.where(ap.receive, ap.weights, 0))
    assert (d["c"], d["fs"], d["attenuation"], d["TXnow"]) == (acq.c, acq.fs, 0.5, 1.0)
    assert d["TXdelays"].shape == (2, 36) and d["blank_rows"].tolist() == [[3.0]]
    with pytest.raises(ParameterError, match="delays must be finite"):
        must_param(ap, acq, np.zeros((2, 35)))


@pytest.mark.parametrize("name, text, match", [
    ("c.csv", "x,y,transmit,receive,weight\n0,0,1,1,0\n", "element 0 is active but its weight is 0"),
    ("c.csv", "x,y,transmit\n0,0,2\n", "transmit = '2' must be 0 or 1"),
    ("c.csv", "element,x,y,transmit\n1,0,0,1\n", "must list 0, 1"),
    ("c.json", '{"probe": {}, "elements": [{"x": 0}]}', "must be an object with x and y"),
])
def test_bad_channel_maps_are_refused_naming_the_file(tmp_path, name, text, match):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ParameterError, match=match) as exc:
        read_aperture(path, width=1e-4, height=1e-4, fc=3e6)
    assert str(exc.value).startswith(str(path)) and "\n" not in str(exc.value)


def test_bad_must_parameter_sets_are_refused(tmp_path):
    from scipy.io import savemat

    base = dict(elements=np.array([[0.0, 1e-3], [0.0, 0.0]]), width=2e-4, height=2e-4, fc=3e6)
    for extra, match in ((dict(TXapodization=np.array([[1.0, -1.0]])), ">= 0"),
                         (dict(TXapodization=np.array([[1.0, 2.0]]), RXapodization=np.array([[1.0, 1.0]])),
                          "element 1 transmits and receives with different weights"),
                         (dict(TXapodization=np.array([[1.0, 2.0, 3.0]])), "must hold 2 numbers"),
                         (dict(elements=np.zeros((3, 2))), "must be 2 x Ne")):
        path = tmp_path / "m.mat"
        savemat(path, {**base, **extra})
        with pytest.raises(ParameterError, match=match) as exc:
            read_aperture(path)
        assert str(exc.value).startswith(str(path))
    savemat(tmp_path / "probe.mat", base)
    with pytest.raises(ParameterError, match="holds a probe but no selection"):
        read_aperture(tmp_path / "probe.mat")


def test_mask_image_and_formats(tmp_path):
    ap = _apertures()["tx-rx"]
    paths = export_selection(ap, tmp_path / "out", ["png"])
    assert list(paths) == ["png"] and paths["png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ParameterError, match="formats"):
        export_selection(ap, tmp_path, ["pdf"])


# --------------------------------------------------------------------------- PyMUST loads the parameter set
def _pymust():
    pymust = pytest.importorskip("pymust")
    logging.getLogger().setLevel(logging.ERROR)
    return pymust


def _load_param(path):
    """The parameter set as PyMUST's functions take it: plain scipy / numpy, nothing of arraysel."""
    if str(path).endswith(".mat"):
        from scipy.io import loadmat

        d = loadmat(path, squeeze_me=True)
        return {k: v for k, v in d.items() if not k.startswith("__")}
    with np.load(path) as z:
        return {k: (z[k].item() if z[k].ndim == 0 else z[k]) for k in z.files}


def _pymust_image(pymust, param: dict, scatterer, coords):
    """simus3 -> rf2iq -> dasmtx3 for every transmit row of TXdelays, summed (the receive
    apodization weights the RF columns)."""
    X, Y, Z = (np.ascontiguousarray(coords[..., i])[..., None] for i in range(3))
    img = np.zeros(coords.shape[:2], dtype=np.complex128)
    events = param.get("TXapodizations")                  # per-transmit apertures: one row an event
    for i, tx in enumerate(np.atleast_2d(param["TXdelays"])):
        P = pymust.utils.Param(dict(param))
        if events is not None:
            P["TXapodization"] = np.atleast_2d(events)[i].reshape(1, -1)
        RF, _ = pymust.simus3(*(np.array([v]) for v in scatterer), np.array([1.0]), tx.reshape(1, -1), P)
        IQ = pymust.rf2iq(RF * np.asarray(P["RXapodization"]).reshape(1, -1), P)
        M = pymust.dasmtx3(1j * np.array(IQ.shape), X, Y, Z, tx.reshape(1, -1), P)
        img += (M @ IQ.flatten(order="F")).reshape(img.shape + (1,), order="F")[..., 0]
    return img


def _si_mse(k, ref):
    k, ref = np.ravel(k), np.ravel(ref)
    a = np.vdot(k, ref) / np.vdot(k, k)
    return float(np.linalg.norm(a * k - ref) ** 2 / np.linalg.norm(ref) ** 2)


@pytest.mark.parametrize("fmt", ["mat", "npz"])
def test_exported_selection_simulated_by_pymust_matches_the_exact_3d_psf(tmp_path, fmt):
    from arraysel.physics.volume import MatrixPSF, MatrixPSFSetup, diverging_delays3, tilt_grid

    pymust = _pymust()
    p = _holey()                                               # 6 x 7 grid, row 3 blank: 36 elements
    acq = Acquisition.for_probe(p)
    d = diverging_delays3(p, *tilt_grid(2, 1, 10, 10), 5e-3, acq)   # 2 diverging waves
    lam = acq.c / p.fc
    scat = (0.5e-3, -0.3e-3, 15e-3)
    setup = MatrixPSFSetup(p, acq, d, scat, half_x=1.5 * lam, half_y=1.5 * lam, half_z=lam, pixel=lam / 2,
                           planes=("xy",))
    rng = np.random.default_rng(1)
    ap = Aperture.of(p, rng.choice(36, 20, replace=False), weights=rng.uniform(0.5, 1.0, 20))
    path = export_selection(ap, tmp_path, [fmt], acquisition=acq, delays=d)[fmt]
    model = MatrixPSF(setup, dtype=torch.float64)
    ours = model.planes(torch.tensor(ap.weights[None]))["xy"][0].numpy()
    ref = _pymust_image(pymust, _load_param(path), scat, model.coords["xy"].numpy())
    assert ours.shape == (6, 6) and _si_mse(ours, ref) <= 1e-4


def test_per_transmit_apertures_exported_and_simulated_by_pymust_match_the_exact_3d_psf(tmp_path):
    from arraysel.physics.volume import MatrixPSF, MatrixPSFSetup, diverging_delays3, tilt_grid

    pymust = _pymust()
    p = _holey()
    acq = Acquisition.for_probe(p)
    d = diverging_delays3(p, *tilt_grid(2, 1, 10, 10), 5e-3, acq)   # 2 diverging waves, one aperture each
    lam = acq.c / p.fc
    scat = (0.5e-3, -0.3e-3, 15e-3)
    setup = MatrixPSFSetup(p, acq, d, scat, half_x=1.5 * lam, half_y=1.5 * lam, half_z=lam, pixel=lam / 2,
                           planes=("xy",))
    rng = np.random.default_rng(2)
    events = np.zeros((2, 36), dtype=bool)
    events[0, rng.choice(36, 12, replace=False)] = events[1, rng.choice(36, 12, replace=False)] = True
    rx = rng.choice(36, 16, replace=False)
    ap = Aperture.of(p, transmit=events.any(0), receive=rx)
    paths = export_selection(ap, tmp_path, ["mat", "csv"], acquisition=acq, delays=d, transmit_events=events)
    rows = (tmp_path / "transmit_events.csv").read_text().splitlines()
    assert rows[1] == "event,elements" and rows[2] == "0," + " ".join(str(e) for e in np.flatnonzero(events[0]))
    param = _load_param(paths["mat"])
    assert np.array_equal(np.atleast_2d(param["TXapodizations"]) > 0, events)
    model = MatrixPSF(setup, dtype=torch.float64)
    ours = model.planes(torch.tensor(events[None], dtype=torch.float64),
                        receive=torch.tensor(ap.receive[None], dtype=torch.float64))["xy"][0].numpy()
    ref = _pymust_image(pymust, param, scat, model.coords["xy"].numpy())
    err = _si_mse(ours, ref)
    assert err <= 1e-4
    union = model.planes(torch.tensor(ap.transmit[None], dtype=torch.float64),
                         receive=torch.tensor(ap.receive[None], dtype=torch.float64))["xy"][0].numpy()
    assert _si_mse(union, ref) > max(1e-4, 10 * err)           # the events are not their union
    with pytest.raises(ParameterError, match="transmit_events: their union must be the aperture's transmit"):
        export_selection(ap, tmp_path / "bad", ["csv"], transmit_events=events[:1])


def test_separate_apertures_in_the_parameter_set_give_pymusts_rf(tmp_path):
    from arraysel.physics.volume import diverging_delays3, simulate_rf3, tilt_grid

    pymust = _pymust()
    ap = _apertures()["tx-rx"]                               # full transmit, 4 receivers, weights
    acq = Acquisition.for_probe(ap.probe)
    d = diverging_delays3(ap.probe, *tilt_grid(1, 1, 0, 0), 5e-3, acq)
    param = _load_param(export_selection(ap, tmp_path, ["mat"], acquisition=acq, delays=d)["mat"])
    pts = np.array([[0.5e-3, -0.3e-3, 12e-3]])
    RF, _ = pymust.simus3(pts[:, 0], pts[:, 1], pts[:, 2], np.array([1.0]), param["TXdelays"].reshape(1, -1),
                          pymust.utils.Param(dict(param)))
    RF = RF * param["RXapodization"].reshape(1, -1)
    ours, _ = simulate_rf3(pts, [1.0], d[0], ap.probe, acq, torch.tensor(ap.tx_apodization),
                           torch.tensor(ap.rx_apodization))
    ours = ours.numpy()
    n = min(len(ours), len(RF))
    assert np.linalg.norm(ours[:n] - RF[:n]) <= 1e-4 * np.linalg.norm(RF[:n])
    assert np.all(RF[:, ~ap.receive] == 0)


# --------------------------------------------------------------------------- the command
def test_cli_export_from_a_probe_file_and_a_mask_line(tmp_path, capsys):
    ap = _apertures()["shared"]
    probe_csv = export_selection(ap, tmp_path / "probe", ["csv"])["csv"]
    masks = tmp_path / "m.txt"
    masks.write_text("# two selections\n0 1 2\n\n5,6,7,8\n")
    out = tmp_path / "out"
    assert main(["export", "--probe", str(probe_csv), "--masks", str(masks), "--line", "4", "--out", str(out),
                 "--weights", "1,2,3,4"]) == 0
    printed = capsys.readouterr().out
    assert "4 of 36 elements" in printed and printed.count("wrote") == 5
    back = read_aperture(out / "channels.json")
    assert np.flatnonzero(back.active).tolist() == [5, 6, 7, 8] and back.weights[5:9].tolist() == [1, 2, 3, 4]
    # an earlier export is kept unless --force
    assert main(["export", "--probe", str(probe_csv), "--elements", "1", "--out", str(out)]) == 2
    assert "already holds an export" in capsys.readouterr().err
    assert main(["export", "--probe", str(probe_csv), "--transmit", "0,1,2", "--receive", "3", "--out", str(out),
                 "--formats", "csv,mat", "--force"]) == 0
    back = read_aperture(out / "must_param.mat")
    assert np.flatnonzero(back.transmit).tolist() == [0, 1, 2] and np.flatnonzero(back.receive).tolist() == [3]
    for argv, match in ((["--line", "3"], "line 3: holds no selection"), (["--line", "9"], "no line 9"),
                        (["--line", "3", "--elements", "1"], "give one selection")):
        assert main(["export", "--probe", str(probe_csv), "--masks", str(masks), *argv, "--out",
                     str(tmp_path / "o2")]) == 2
        assert match in capsys.readouterr().err


def test_cli_export_from_a_compare_folder_and_a_scene(tmp_path, capsys):
    from arraysel.scenes.schema import load_scene

    scene = load_scene({"base": "matrix-1024", "probe": {"nx": 6, "ny": 7, "blank_rows": [3]},
                        "selection": {"k": 4}})
    folder = tmp_path / "cmp"
    folder.mkdir()
    (folder / "run.json").write_text(json.dumps({"scene": scene.to_dict()}))
    (folder / "table1.csv").write_text("config,Mean,elements\nfull,0.1,\"0 1 2\"\nuniform,0.2,0 2 18 20\n")
    out = tmp_path / "out"
    assert main(["export", "--compare", str(folder), "--config", "uniform", "--out", str(out)]) == 0
    param = _load_param(out / "must_param.npz")
    assert param["TXdelays"].shape == (9, 36) and param["fs"] == scene.acquisition().fs
    assert np.flatnonzero(param["TXapodization"]).tolist() == [0, 2, 18, 20]
    capsys.readouterr()
    assert main(["export", "--compare", str(folder), "--config", "ste", "--out", str(tmp_path / "o")]) == 2
    assert "has no selection for it; its configs: ['full', 'uniform']" in capsys.readouterr().err
    assert main(["export", "--scene", "paper", "--elements", "1", "--out", str(tmp_path / "o")]) == 2
    assert "1-D probe 'P4-2v'" in capsys.readouterr().err
    assert main(["export", "--elements", "1", "--out", str(tmp_path / "o")]) == 2
    assert "give the probe with one of --scene, --probe, --compare" in capsys.readouterr().err
