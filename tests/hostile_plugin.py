"""Selectors that misbehave on purpose, loaded with ``--plugin`` by tests/test_hostile_plugins.py
and tests/test_hostile_runs.py (not a test module itself).

``ARRAYSEL_HOSTILE_PIDS``: a file to which ``ignores_budget`` appends the pid of the process it
runs in (so a test can check that the process is gone afterwards).
"""
import os
import threading
import time

import numpy as np

from arraysel.selectors.contract import Selector, indices_to_mask
from arraysel.selectors.hookspecs import hookimpl

METRICS = ("L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i", "L_SLR", "Mean")


def _note_pid():
    path = os.environ.get("ARRAYSEL_HOSTILE_PIDS")
    if path:
        with open(path, "a") as fh:
            fh.write(f"{os.getpid()}\n")


class _Base(Selector):
    options = {}
    deterministic = True

    def batch_size(self, n_elements, k):
        return 1


class EditsObjective(_Base):
    name = "edits_objective"
    description = "edits the objective it receives, then returns every second element"

    def select(self, objective, k, seed):
        if hasattr(objective, "metric_kw"):  # the physics objective
            objective.metric_kw["r_main"] *= 1.3
        else:  # the toy objective: its target
            objective._t.mul_(0.5)
        return list(range(0, 2 * k, 2))


class WrapsEvaluate(_Base):
    name = "wraps_evaluate"
    description = "replaces evaluate on the objective's class and on the budgeted view's class"

    def select(self, objective, k, seed):
        def fake(self, masks, **kwargs):
            n = len(np.atleast_2d(np.asarray(masks)))
            return {m: np.zeros(n) for m in METRICS}

        inner = object.__getattribute__(objective, "_inner")
        type(objective).evaluate = fake
        type(inner).evaluate = fake
        return list(range(0, 2 * k, 2))


class LeavesThreads(_Base):
    name = "leaves_threads"
    description = "leaves threads calling the objective for 5 s after it returns"

    def select(self, objective, k, seed):
        mask = indices_to_mask(list(range(k)), objective.n_elements)[None]

        def spin():
            end = time.monotonic() + 5.0
            while time.monotonic() < end:
                try:
                    objective.evaluate(mask)
                except Exception:
                    pass
                time.sleep(0.002)

        for _ in range(2):
            threading.Thread(target=spin, daemon=True).start()
        time.sleep(0.05)
        return list(range(k))


class SoftWeights(_Base):
    name = "soft_weights"
    description = "scores soft weights with evaluate"

    def select(self, objective, k, seed):
        n = objective.n_elements
        objective.evaluate(np.full((1, n), k / n))
        return list(range(k))


class IgnoresBudget(_Base):
    name = "ignores_budget"
    description = "never returns"

    def select(self, objective, k, seed):
        _note_pid()
        while True:
            time.sleep(0.05)


@hookimpl
def arraysel_register_selectors(register):
    for cls in (EditsObjective, WrapsEvaluate, LeavesThreads, SoftWeights, IgnoresBudget):
        register(cls)
