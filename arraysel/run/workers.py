"""The worker side of every executor: each worker process builds the objective **once** from a
picklable factory and keeps it in a cache keyed by the factory's token, so the scene travels to a
worker once (in a process pool's initializer, a Dask worker plugin or an isolated child), not
with every task. Also what a task failure looks like (:class:`TaskFailed`) and the process start
method (:func:`mp_context`).

:func:`objective_factory_for` asks an objective for its recipe through the ``worker_factory()``
capability of :mod:`arraysel.objective.contract`; it never looks at the objective's class.
"""
from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import multiprocessing.connection
import multiprocessing.util
import os
import threading
import time
from typing import Any, Callable

from arraysel.errors import ArrayselError, ParameterError
from arraysel.objective.contract import worker_factory_of

__all__ = ["TaskFailed", "objective_factory_for", "mp_context"]


def objective_factory_for(objective):
    """A picklable factory that rebuilds ``objective`` on a worker: ``objective.worker_factory()``.

    Raises :class:`ParameterError` for an objective without that capability (or whose
    ``worker_factory()`` returns ``None``): pass ``objective_factory=`` then.
    """
    factory = worker_factory_of(objective)
    if factory is None:
        raise ParameterError(
            f"cannot send a {type(objective).__name__} to other processes; give an objective_factory "
            f"(a picklable callable that builds the objective, e.g. "
            f"arraysel.objective.psf_objective.SceneObjectiveFactory)")
    return factory


@dataclasses.dataclass
class TaskFailed:
    """Yielded by :meth:`Executor.run_tasks` for a task that failed ``attempts`` times."""

    message: str
    attempts: int = 1
    exception: BaseException | None = None
    #: "failed" (the task raised), "died" (its process ended without a result) or "timeout"
    #: (its process was stopped at its deadline)
    kind: str = "failed"

    def __str__(self) -> str:
        return self.message


# ---------------------------------------------------------------------------
# the cache of objectives, one per factory and worker process
# ---------------------------------------------------------------------------

_FACTORIES: dict[str, Any] = {}
_OBJECTIVES: dict[str, Any] = {}
_LOCKS: dict[str, threading.Lock] = {}
_CACHE_LOCK = threading.Lock()


def _install_factory(token: str, factory) -> None:
    with _CACHE_LOCK:
        _FACTORIES[token] = factory
        _LOCKS.setdefault(token, threading.Lock())


def _remove_factory(token: str) -> None:
    with _CACHE_LOCK:
        _FACTORIES.pop(token, None)
        _OBJECTIVES.pop(token, None)
        _LOCKS.pop(token, None)


def _worker_objective(token: str):
    """This process's objective for ``token`` (built on first use) and its lock."""
    with _CACHE_LOCK:
        factory = _FACTORIES.get(token)
        lock = _LOCKS.setdefault(token, threading.Lock())
    if factory is None:
        raise ArrayselError(f"worker process {os.getpid()} has no objective factory {token} "
                            f"(the executor did not install it)")
    with lock:
        obj = _OBJECTIVES.get(token)
        if obj is None:
            obj = factory()
            _OBJECTIVES[token] = obj
    return obj, lock


def _run_on_worker(token: str, fn: Callable, item):
    """Run ``fn(objective, item)`` with this worker's objective; one task per objective at a time
    (the objective's counters measure each run's budget)."""
    obj, lock = _worker_objective(token)
    with lock:
        return fn(obj, item)


def _process_init(token: str | None, factory, threads: int) -> None:
    from arraysel.io.allocator import tune_malloc

    tune_malloc()
    if threads:
        try:
            import torch
            torch.set_num_threads(threads)
        except Exception:  # torch missing or already initialised: keep its default
            pass
    if token is not None:
        _install_factory(token, factory)


# ---------------------------------------------------------------------------

def mp_context():
    """``forkserver`` with torch and arraysel preloaded (a new worker is a cheap fork of a clean,
    single-threaded server, so restarting a pool after a worker died is fast); ``spawn`` where
    there is no forkserver. Never plain ``fork``: forking a process whose torch thread pools are
    running can deadlock."""
    # OpenMP threads that sleep at a barrier instead of spinning: the runs share the machine with
    # each other, the calling process and whatever else runs there, and spinning threads then
    # take the cores the others need (paper scene, 2 threads a run on a machine with a load of
    # 4 on 2 cores: 1.8x to 4.5x the evaluations of the default policy). Read by OpenMP when the
    # forkserver (or a spawned child) loads torch; a policy set by the user is kept.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["torch", "arraysel.run.workers", "arraysel.run.compare_task"])
        return ctx
    return multiprocessing.get_context("spawn")


# ---------------------------------------------------------------------------
# the life of a child process (isolated runs, warm templates)
# ---------------------------------------------------------------------------

#: seconds a child may take to build its objective before it is stopped (a first build of a
#: large scene's PSF basis, or a wait on another process building it, takes minutes)
BUILD_LIMIT_S = 1800.0
#: seconds a child goes on past its deadline before it ends itself (its supervisor kills it first)
_SELF_STOP_MARGIN_S = 10.0


def _watch(alive, limit: list) -> None:
    """Child-side watchdog thread: end the process when its supervisor is gone (``alive``, the
    read end of a pipe whose only write end the supervisor holds, reads end-of-file: this holds
    for a killed supervisor not yet reaped, whose pid still exists), or when ``limit[0]`` (a
    ``time.monotonic`` deadline, ``None``: none) has passed."""
    while True:
        if alive.poll(0.5):  # the supervisor never writes: readable means it is gone
            os._exit(70)
        if limit[0] is not None and time.monotonic() > limit[0]:
            os._exit(124)


def wait_for_result(task, abort: Callable[[], None]):
    """Block until ``task.poll()`` has a result and return it, sleeping on ``task.waitables()`` until
    ``task.deadline`` (a monotonic time) between polls; on any exception (KeyboardInterrupt, SIGTERM
    included) call ``abort()`` first, so that no child process is left running, then re-raise."""
    try:
        while True:
            res = task.poll()
            if res is not None:
                return res
            left = max(0.0, task.deadline - time.monotonic())
            multiprocessing.connection.wait(task.waitables(), timeout=min(left, 3600.0))
    except BaseException:
        abort()
        raise


def _end(code: int = 0) -> None:
    """End the child now, without waiting for threads the task left running; release what
    multiprocessing registered for cleanup (semaphores: else the resource tracker warns)."""
    with contextlib.suppress(Exception):
        multiprocessing.util._run_finalizers(0)  # noqa: SLF001 - what a normal exit runs
    os._exit(code)


@contextlib.contextmanager
def _children_allowed():
    """Let a daemonic process (a Dask worker under its nanny) start the child: multiprocessing
    refuses children of daemonic processes so that none is orphaned at exit; the child's
    watchdog ends it when its supervisor is gone, which is what that rule protects."""
    config = multiprocessing.current_process()._config  # noqa: SLF001 - no public switch exists
    daemon = config.get("daemon")
    if daemon:
        config["daemon"] = False
    try:
        yield
    finally:
        if daemon:
            config["daemon"] = daemon
