"""Selectors a factory makes (their classes do not pickle by name), loaded with ``--plugin`` by the
tests of tests/hostile/ (not a test module itself).

* ``sleepy`` never returns (sleeps in short steps);
* ``patches_means`` halves ``numpy.mean`` and ``torch.mean`` in the process it runs in, then returns
  every second element (scored once, honestly);
* ``unscored`` returns every second element without ever calling the objective;
* ``one_eval`` scores exactly one selection (every second element) and returns it.

``ARRAYSEL_HOSTILE_PIDS``: a file to which each appends the pid of the process it runs in.
"""
import os
import time

import numpy as np

from arraysel.selectors.contract import Selector, indices_to_mask
from arraysel.selectors.hookspecs import hookimpl


def _note_pid():
    path = os.environ.get("ARRAYSEL_HOSTILE_PIDS")
    if path:
        with open(path, "a") as fh:
            fh.write(f"{os.getpid()}\n")


def _every_second(objective, k):
    return list(range(0, 2 * k, 2))


def _sleep(self, objective, k, seed):
    _note_pid()
    while True:
        time.sleep(0.05)


def _patch_means(self, objective, k, seed):
    import torch

    _note_pid()
    picked = _every_second(objective, k)
    objective.evaluate(indices_to_mask(picked, objective.n_elements)[None])
    np_mean, torch_mean = np.mean, torch.mean
    np.mean = lambda *a, **kw: 0.5 * np_mean(*a, **kw)
    torch.mean = lambda *a, **kw: 0.5 * torch_mean(*a, **kw)
    return picked


def _unscored(self, objective, k, seed):
    _note_pid()
    return _every_second(objective, k)


def _one_eval(self, objective, k, seed):
    picked = _every_second(objective, k)
    objective.evaluate(indices_to_mask(picked, objective.n_elements)[None])
    return picked


def make_selector(name, description, select):
    """A selector class made here (its qualified name holds ``<locals>``: it does not pickle)."""
    class Made(Selector):
        options = {}
        deterministic = True

        def batch_size(self, n_elements, k):
            return 1

    Made.name = name
    Made.description = description
    Made.select = select
    return Made


MADE = [make_selector("sleepy", "never returns", _sleep),
        make_selector("patches_means", "halves numpy.mean and torch.mean, returns every second element",
                      _patch_means),
        make_selector("unscored", "returns every second element without scoring it", _unscored),
        make_selector("one_eval", "scores one selection and returns it", _one_eval)]


@hookimpl
def arraysel_register_selectors(register):
    for cls in MADE:
        register(cls)
