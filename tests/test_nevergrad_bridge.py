"""The nevergrad selector on a problem of a matrix probe's size: nevergrad's diagonal CMA (NGOpt's
choice at 1024 dimensions with parallel asks) loses its mean-shift samples after about 1000
evaluations (nevergrad issue 1690); the run starts a fresh optimizer and goes on to its budget."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from arraysel.objective.toy import ToyObjective
from arraysel.run.experiment import Experiment
from arraysel.selectors.contract import Budget
from arraysel.selectors.registry import get_registry

pytest.importorskip("nevergrad")


def test_nevergrad_runs_past_the_diagonal_cma_fault_on_1024_elements(caplog):
    cls = get_registry()["nevergrad"]
    with caplog.at_level(logging.INFO, logger="arraysel"):
        row = Experiment(ToyObjective(1024, 256), cls, options={}, budget=Budget(evaluations=1600), seed=0,
                         k=256).run()
    assert row["error"] == "" and np.isfinite(row["Mean"])
    assert 1600 <= row["evaluations"] <= 1600 + 32
    sel = [int(i) for i in row["elements"].split()]
    assert len(set(sel)) == 256
    assert any("starting a fresh one" in r.getMessage() for r in caplog.records)
