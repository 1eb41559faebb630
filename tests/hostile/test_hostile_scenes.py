"""Hostile cases, custom scenes with extreme or stiff values: zero, negative or NaN lengths, an
f-number of 0 or one so large no element receives, one element, k = 0 and k = Ne, a scatterer on
the array, behind it or off the grid, huge and tiny reflectivities.

A value the physics cannot use is refused in one line naming the key (``arraysel evaluate``,
exit code 2, before any basis is built); a value it can use gives the right number: what the
same scene gives at the limit it tends to (an f-number of 0 and 1e-6; reflectivity 1e-30, 1
and 1e6, the metrics being normalised), and for k = Ne the full array's own row.
"""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from arraysel.cli.main import main
from support import own_plugin_manager, time_limit  # noqa: F401  (autouse fixtures)

_bounded = time_limit(300)
#: an 8-element paper scene on a 32 x 32 grid (tests/scene_texts.py's TINY_SCENE)
TINY = {"name": "tiny", "base": "paper", "probe": {"n_elements": 8}, "transmit": {"n_tx": 1},
        "grid": {"n_x": 32, "n_z": 32, "window": 16}, "selection": {"k": 4},
        "metrics": {"r_main": 0.25, "r_guard": 0.5}, "simulator": {"fast_margin": 2, "fast_block": 4}}
NAN, INF = math.nan, math.inf


def _scene(**sections) -> dict:
    out = copy.deepcopy(TINY)
    for section, keys in sections.items():
        out.setdefault(section, {}).update(keys)
    return out


def _toml_value(v) -> str:
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    if isinstance(v, float) and math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return repr(v)


def _toml(scene: dict) -> str:
    lines = [f"{k} = {_toml_value(v)}" for k, v in scene.items() if not isinstance(v, dict)]
    for section, keys in scene.items():
        if isinstance(keys, dict):
            lines += [f"[{section}]", *(f"{k} = {_toml_value(v)}" for k, v in keys.items())]
    return "\n".join(lines) + "\n"


REFUSED = {
    "zero pitch": ({"probe": {"pitch": 0.0}}, "probe.pitch = 0.0 is out of range; allowed: (0, 1]"),
    "negative pitch": ({"probe": {"pitch": -0.0003}}, "probe.pitch = -0.0003 is out of range"),
    "NaN pitch": ({"probe": {"pitch": NAN}}, "probe.pitch must not be NaN"),
    "element wider than the pitch": ({"probe": {"width": 0.001}}, "probe.width = 0.001 is out of range; "
                                                                  "allowed: (0, pitch]"),
    "NaN centre frequency": ({"probe": {"fc": NAN}}, "probe.fc must not be NaN"),
    "infinite sound speed": ({"acquisition": {"c": INF}}, "acquisition.c = inf is out of range"),
    "negative f-number": ({"receive": {"fnumber": -1.0}}, "receive.fnumber = -1.0 is out of range"),
    "NaN f-number": ({"receive": {"fnumber": NAN}}, "receive.fnumber must not be NaN"),
    "f-number no element receives at": ({"receive": {"fnumber": 100.0}},
                                        "receive.fnumber = 100 leaves no element in the receive aperture"),
    "k = 0": ({"selection": {"k": 0}}, "selection.k = 0 is out of range; allowed: [1, 4096]"),
    "k > Ne": ({"selection": {"k": 9}}, "selection.k = 9 is out of range; allowed: [1, 8] (the probe has 8"),
    "no element": ({"probe": {"n_elements": 0}}, "probe.n_elements = 0 is out of range"),
    "scatterer on the array": ({"medium": {"scatterer_z": 0.0}}, "medium.scatterer_z = 0.0 is out of range; "
                                                                 "allowed: (0, 2]"),
    "scatterer behind the probe": ({"medium": {"scatterer_z": -0.005}}, "medium.scatterer_z = -0.005 is out of range"),
    "scatterer beside the grid": ({"medium": {"scatterer_x": 0.0006}},
                                  "medium.scatterer_x: the scatterer at x = 0.0006 m, z = 0.00044 m lies outside "
                                  "the grid (x from -0.00044 to 0.0004125 m"),
    "scatterer below the grid": ({"medium": {"scatterer_z": "2 mm"}}, "medium.scatterer_z: the scatterer at x = 0 m, "
                                                                       "z = 0.002 m lies outside the grid"),
    "NaN scatterer": ({"medium": {"scatterer_z": NAN}}, "medium.scatterer_z must not be NaN"),
    "NaN length with a unit": ({"medium": {"scatterer_x": "nan mm"}}, "medium.scatterer_x"),
    "NaN weight": ({"weights": {"L_PSF": NAN}}, "weights.L_PSF must not be NaN"),
    "NaN metric radius": ({"metrics": {"r_main": NAN}}, "metrics.r_main must not be NaN"),
    "zero reflectivity": ({"medium": {"reflectivity": 0.0}}, "medium.reflectivity = 0.0 is out of range"),
    "NaN reflectivity": ({"medium": {"reflectivity": NAN}}, "medium.reflectivity must not be NaN"),
    "NaN tilt": ({"transmit": {"max_tilt_deg": NAN}}, "transmit.max_tilt_deg must not be NaN"),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_a_scene_value_the_physics_cannot_use_is_refused_in_one_line_naming_the_key(tmp_path, capsys, case):
    sections, said = REFUSED[case]
    scene = tmp_path / "s.toml"
    scene.write_text(_toml(_scene(**sections)))
    masks = tmp_path / "m.txt"
    masks.write_text("0 2 4 6\n")
    code = main(["evaluate", "--scene", str(scene), "--masks", str(masks), "--out", str(tmp_path / "o.csv"),
                 "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("arraysel evaluate: error: ") and said in err[0], err[0]
    assert not (tmp_path / "o.csv").exists()


# ------------------------------------------------------------------ the right number
def _objective(scene: dict):
    from arraysel.objective.build import build_objective
    from arraysel.scenes.schema import load_scene

    return build_objective(load_scene(scene))


def _scores(obj, selections) -> dict:
    n = int(obj.n_elements)
    masks = np.zeros((len(selections), n), dtype=bool)
    for row, sel in zip(masks, selections):
        row[list(sel)] = True
    out = obj.evaluate(masks)
    return {m: np.asarray(out[m], dtype=np.float64) for m in ("Mean", "L_PSF", "L_contrast", "L_SLR")}


SELECTIONS = [(0, 1, 2, 3), (0, 2, 4, 6), (1, 3, 5, 7)]


@pytest.mark.parametrize("sections", [{"medium": {"reflectivity": 1e-30}}, {"medium": {"reflectivity": 1e6}},
                                      {"receive": {"fnumber": 1e-6}}],
                         ids=["reflectivity 1e-30", "reflectivity 1e6", "f-number 1e-6"])
def test_stiff_values_give_the_number_of_the_limit_they_tend_to(sections):
    """The metrics are normalised (a reflectivity scales the image only), and an f-number that
    tends to 0 opens the aperture to every element (f-number 0)."""
    want = _scores(_objective(TINY), SELECTIONS)
    got = _scores(_objective(_scene(**sections)), SELECTIONS)
    for m in want:
        assert np.all(np.isfinite(got[m]))
        np.testing.assert_allclose(got[m], want[m], rtol=1e-5, err_msg=m)


@pytest.mark.parametrize("sections", [{"selection": {"k": 8}}, {"probe": {"n_elements": 1}, "selection": {"k": 1}}],
                         ids=["k = Ne", "one element"])
def test_when_every_element_must_be_kept_every_selector_returns_the_full_array(tmp_path, capsys, sections):
    scene = tmp_path / "s.toml"
    scene.write_text(_toml(_scene(**sections)))
    out = tmp_path / "cmp"
    code = main(["compare", "--scene", str(scene), "--selectors", "random,uniform,greedy,swap", "--seeds", "0",
                 "--budget-s", "20", "--budget-evals", "20", "--out", str(out), "--no-progress", "--no-figures",
                 "--in-process"])
    assert code == 0, capsys.readouterr().err
    import pandas as pd

    runs = pd.read_csv(out / "runs.csv", keep_default_na=False).set_index("config")
    full = runs.loc["full"]
    assert float(full["L_PSF"]) < 1e-9 and math.isfinite(float(full["Mean"]))
    for config in ("random", "uniform", "greedy", "swap"):
        row = runs.loc[config]
        assert row["error"] == "" and row["elements"] == full["elements"], config
        assert float(row["Mean"]) == float(full["Mean"]), config
