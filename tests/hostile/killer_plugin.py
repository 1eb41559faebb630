"""Selectors whose process is killed in the middle of a run, loaded with ``--plugin`` by
tests/hostile/test_hostile_executors.py (not a test module itself).

``ARRAYSEL_HOSTILE_MARKER``: a file. ``dies_once`` scores a batch, then, the first time (no
marker yet), writes its pid and its ancestors' pids into the marker and kills what
``ARRAYSEL_HOSTILE_KILL`` names: ``self`` (its own process, with SIGKILL), ``worker`` (the
process it was forked from, then itself) or ``wait`` (nothing: it sleeps until the test kills
its worker); once the marker exists it returns the best of its batch (deterministic).
``dies_always`` kills its own process every time. Neither kills the test process itself.
"""
import os
import signal
import time
from pathlib import Path

import numpy as np

from arraysel.selectors.contract import Selector, numpy_rng
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.starts import random_subsets

_GUARD = "ARRAYSEL_HOSTILE_TEST_PID"


def _ancestors() -> list:
    out, pid = [], os.getppid()
    while pid > 1 and len(out) < 20:
        out.append(pid)
        try:
            pid = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
        except OSError:
            break
    return out


def _kill(pid: int) -> None:
    if str(pid) == os.environ.get(_GUARD):
        raise RuntimeError("refusing to kill the test process")
    os.kill(pid, signal.SIGKILL)


def _best_of_batch(objective, k, seed):
    n = int(objective.n_elements)
    subsets = random_subsets(numpy_rng(seed), 12, n, k)
    masks = np.zeros((12, n), dtype=bool)
    np.put_along_axis(masks, subsets, True, axis=1)
    means = objective.evaluate(masks)["Mean"]
    return subsets[int(np.argmin(means))].tolist()


class DiesOnce(Selector):
    name = "dies_once"
    description = "its process is killed once in the middle of the run; then the best of 12 random masks"
    deterministic = True

    def batch_size(self, n_elements, k):
        return 12

    def select(self, objective, k, seed):
        best = _best_of_batch(objective, k, seed)
        marker = Path(os.environ["ARRAYSEL_HOSTILE_MARKER"])
        if not marker.exists():
            marker.write_text(" ".join(map(str, [os.getpid(), *_ancestors()])) + "\n")
            how = os.environ.get("ARRAYSEL_HOSTILE_KILL", "self")
            if how == "worker":
                _kill(os.getppid())
            if how == "wait":
                time.sleep(300)
            _kill(os.getpid())
        return best


class DiesAlways(Selector):
    name = "dies_always"
    description = "kills its own process every time"
    deterministic = True

    def select(self, objective, k, seed):
        _kill(os.getpid())


@hookimpl
def arraysel_register_selectors(register):
    register(DiesOnce)
    register(DiesAlways)
