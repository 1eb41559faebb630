"""Hostile cases, the Python API with bad arguments: ``arraysel.compare``, ``build_objective``,
``load_scene``, ``Budget`` and an objective's ``evaluate``.

Each bad argument is a :class:`~arraysel.errors.ParameterError` (or ``SelectionError``) in one
line naming the parameter, raised before anything is written (the ``out_dir`` given is never
made); never a ``TypeError`` or ``AttributeError`` from deep inside, a seed run twice, a silent
NaN, or options that are dropped.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

import arraysel as asel
from arraysel.errors import ArrayselError
from support import own_plugin_manager, time_limit  # noqa: F401  (autouse fixtures)

_bounded = time_limit(120)

BAD_COMPARE = {
    "selectors None": ({"selectors": None}, "selectors must be a list of selector names, got NoneType"),
    "selectors an int": ({"selectors": 3}, "selectors must be a list of selector names, got int"),
    "selectors empty": ({"selectors": []}, "compare needs at least one selector"),
    "unknown selector": ({"selectors": ["nope"]}, "unknown selector 'nope'; known selectors:"),
    "seeds an int": ({"seeds": 3}, "seeds must be a list of whole numbers >= 0 (e.g. [0, 1, 2]), got 3"),
    "seeds a string": ({"seeds": "0,1"}, "seeds must be a list of whole numbers >= 0"),
    "seeds empty": ({"seeds": []}, "seeds is empty: give at least one seed"),
    "a seed twice": ({"seeds": [0, 1, 0]}, "seeds lists 0 more than once"),
    "a negative seed": ({"seeds": [-1]}, "seed = -1 is out of range"),
    "a fractional seed": ({"seeds": [0.5]}, "seed must be an integer, got 0.5"),
    "a NaN budget": ({"budget_s": math.nan}, "budget seconds must not be NaN"),
    "an infinite budget": ({"budget_s": math.inf}, "budget seconds = inf is not allowed"),
    "a negative budget": ({"budget_s": -1}, "budget seconds = -1 is out of range"),
    "no budget at all": ({"budget_s": None, "budget_evals": None}, "the budget has no limit: give a time budget"),
    "a fractional evaluation budget": ({"budget_evals": 2.5}, "budget evaluations must be an integer"),
    "options a list": ({"options": [1]}, "options must be a dict {selector: {option: value}}, got list"),
    "options of a selector not run": ({"options": {"random": {"n": 2}}},
                                      "options names selector(s) 'random', not in selectors"),
    "an unknown option": ({"selectors": ["random"], "options": {"random": {"nope": 1}}},
                          "selector 'random' has no option nope"),
    "an option out of range": ({"selectors": ["random"], "options": {"random": {"n": -3}}},
                               "option random.n = -3 is out of range"),
    "dtype float16": ({"dtype": "float16"}, "dtype = 'float16' is not allowed; choose one of ['float32', 'float64']"),
    "dtype unknown": ({"dtype": "nope"}, "dtype = 'nope' is not allowed"),
    "device unknown": ({"device": "tpu"}, "device must be 'cpu' or 'cuda', got 'tpu'"),
    "scene an int": ({"scene": 42}, "scene must be a name, a path or a dict, got int"),
    "scene unknown": ({"scene": "nope"}, "unknown scene 'nope'"),
    "a scene value out of range": ({"scene": {"base": "paper", "probe": {"pitch": -1}}},
                                   "probe.pitch = -1 is out of range"),
    "a negative grace period": ({"grace_s": -1}, "grace_s = -1 is out of range"),
    "a NaN grace period": ({"grace_s": math.nan}, "grace_s must not be NaN"),
    "not an objective": ({"objective": object()}, "objective must follow the Objective contract"),
    "resume and force": ({"resume": True, "force": True}, "--resume and --force exclude each other"),
}


@pytest.mark.parametrize("case", sorted(BAD_COMPARE))
def test_compare_refuses_a_bad_argument_naming_it_before_writing_anything(tmp_path, case):
    kwargs, said = BAD_COMPARE[case]
    out = tmp_path / "out"
    args = {"scene": "toy", "selectors": ["uniform"], "budget_s": 5.0, "progress": False, "figures": False,
            "out_dir": out, **kwargs}
    with pytest.raises(ArrayselError) as err:
        asel.compare(**args)
    msg = str(err.value)
    assert said in msg and "\n" not in msg, msg
    assert not out.exists()


def test_selectors_as_one_string_are_read_as_the_command_line_reads_them(tmp_path):
    res = asel.compare("toy", "uniform, random", budget_evals=5, budget_s=None, out_dir=tmp_path / "out",
                       progress=False, figures=False)
    assert list(res.table["config"]) == ["full", "uniform", "random"]


def test_an_out_dir_that_is_a_file_is_refused_and_kept(tmp_path):
    file = tmp_path / "f"
    file.write_text("mine")
    with pytest.raises(ArrayselError, match="is a file, not a folder"):
        asel.compare("toy", ["uniform"], budget_s=5.0, out_dir=file, progress=False, figures=False)
    assert file.read_text() == "mine"


BAD_OTHER = {
    "load_scene(None)": (lambda: asel.load_scene(None), "scene must be a name, a path or a dict, got NoneType"),
    "Budget(seconds=-1)": (lambda: asel.Budget(seconds=-1), "budget seconds = -1 is out of range"),
    "Budget(evaluations=0)": (lambda: asel.Budget(evaluations=0), "budget evaluations = 0 is out of range"),
    "build_objective(device='tpu')": (lambda: asel.build_objective("paper", device="tpu"),
                                      "device must be 'cpu' or 'cuda' (or a torch device), got 'tpu'"),
    "build_objective(dtype='float32')": (lambda: asel.build_objective("paper", dtype="float32"),
                                         "dtype = float32 is not allowed"),
}


@pytest.mark.parametrize("case", sorted(BAD_OTHER))
def test_the_other_entry_points_refuse_a_bad_argument_naming_it(case):
    call, said = BAD_OTHER[case]
    with pytest.raises(ArrayselError) as err:
        call()
    assert said in str(err.value), str(err.value)


@pytest.mark.parametrize("masks, said", [
    (np.full((1, 64), np.nan), "masks contain NaN or Inf"),
    (np.full((1, 64), np.inf), "masks contain NaN or Inf"),
    (np.ones((1, 8)), "masks must have shape (B, 64), got (1, 8)"),
], ids=["NaN", "Inf", "wrong width"])
def test_the_toy_objective_refuses_masks_no_selection_can_be(masks, said):
    """The toy objective returned a NaN Mean for NaN masks."""
    from arraysel.objective.toy import ToyObjective

    with pytest.raises(ArrayselError) as err:
        ToyObjective(64, 32).evaluate(masks)
    assert said in str(err.value)
