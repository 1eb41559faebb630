"""Where selector runs and batches of masks are computed: in-process, a local
process pool, or a Dask distributed cluster.

The unit of work is a *task*: one ``(scene, selector, seed)`` run of
``arraysel compare`` or one chunk of masks. A task is a module-level function
``fn(objective, item)``; every worker builds the objective **once** from a
picklable *objective factory* (:class:`SceneObjectiveFactory`,
:class:`ToyObjectiveFactory`) and keeps it in a worker-side cache keyed by the
factory, so the scene travels to each worker once (in the process pool's
initializer, or in a Dask worker plugin), not with every task.

Executors
---------
* :class:`LocalExecutor` -- in the calling process, one task after another.
* :class:`ProcessExecutor` -- ``concurrent.futures`` process pool (``spawn``)
  of ``workers`` processes.
* :class:`DaskExecutor` -- a ``dask.distributed`` client connected to a
  scheduler (``tcp://host:8786``) or to a :class:`~distributed.LocalCluster`
  started on loopback with ``workers`` single-threaded worker processes.
  Dask is optional (``pip install arraysel[dask]``) and imported lazily.

:meth:`Executor.run_tasks` yields ``(index, result)`` pairs as tasks finish.
A worker that dies loses only the task it was running: the task is run again
(at most ``retries`` more times); a task that still fails yields a
:class:`TaskFailed` instead of a result, and the other tasks go on.

Random search
-------------
:func:`distributed_random_search` scores ``n_masks`` uniformly random
k-subsets. The masks are cut into chunks of ``chunk`` masks; chunk ``i`` draws
its masks from ``numpy.random.SeedSequence(seed).spawn(n_chunks)[i]``, so the
masks, and the best one (ties broken by chunk order, then by position in the
chunk), do not depend on the executor or on the number of workers.

Example
-------
>>> from arraysel.run.executors import ToyObjectiveFactory, ProcessExecutor, distributed_random_search
>>> with ProcessExecutor(workers=2) as ex:                              # doctest: +SKIP
...     res = distributed_random_search(ToyObjectiveFactory(64, 32), 100_000, None, 0, ex, 4096)
>>> res.elements, res.mean                                             # doctest: +SKIP
"""
from __future__ import annotations

import collections
import concurrent.futures as cf
import dataclasses
import hashlib
import json
import logging
import math
import os
import pickle
import threading
import time
import uuid
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from arraysel.errors import ArrayselError, ParameterError, check_choice, check_number

__all__ = [
    "EXECUTORS", "DASK_INSTALL_HINT", "TaskFailed", "Executor", "LocalExecutor", "ProcessExecutor",
    "DaskExecutor", "make_executor", "SceneObjectiveFactory", "ToyObjectiveFactory",
    "objective_factory_for", "RandomSearchResult", "distributed_random_search", "distributed_evaluate",
    "random_subsets",
]

#: executor names accepted by :func:`make_executor` and ``arraysel compare --executor``
EXECUTORS = ("local", "process", "dask")
DASK_INSTALL_HINT = "pip install arraysel[dask]"
DEFAULT_RETRIES = 2


# ---------------------------------------------------------------------------
# objective factories (picklable recipes to build an objective on a worker)
# ---------------------------------------------------------------------------

def _dtype_name(dtype) -> str:
    text = str(dtype)
    return text[len("torch."):] if text.startswith("torch.") else text


class _Factory:
    """Common part of the factories: a stable :meth:`key` for worker caches."""

    def key(self) -> str:
        fields = dataclasses.asdict(self)  # type: ignore[arg-type]
        text = json.dumps({"type": type(self).__name__, **fields}, sort_keys=True, default=str)
        return hashlib.sha1(text.encode()).hexdigest()[:16]


@dataclasses.dataclass(frozen=True)
class SceneObjectiveFactory(_Factory):
    """Builds the physics objective of a scene with :func:`arraysel.objective.psf_objective.build_objective`.

    Parameters
    ----------
    scene : the scene as a dictionary (``Scene.to_dict()``)
    device : ``"cpu"`` or ``"cuda"`` (on the worker)
    dtype : ``"float32"`` or ``"float64"``
    chunk : masks per batch inside ``Objective.evaluate``
    """

    scene: dict
    device: str = "cpu"
    dtype: str = "float32"
    chunk: int = 256

    def __hash__(self):  # the dict field is not hashable; the key is
        return hash(self.key())

    def __call__(self):
        import torch

        from arraysel.objective.psf_objective import build_objective
        from arraysel.scenes.schema import load_scene
        return build_objective(load_scene(dict(self.scene)), device=self.device,
                               dtype=getattr(torch, self.dtype), chunk=self.chunk)


@dataclasses.dataclass(frozen=True)
class ToyObjectiveFactory(_Factory):
    """Builds an :class:`arraysel.objective.toy.ToyObjective` (tests, demos, benchmarks)."""

    n_elements: int = 64
    k: int = 32
    device: str = "cpu"
    dtype: str = "float32"
    seed: int = 0
    chunk: int = 4096
    fail_after: int | None = None
    nan_element: int | None = None
    always_nan: bool = False
    delay: float = 0.0

    def __call__(self):
        import torch

        from arraysel.objective.toy import ToyObjective
        return ToyObjective(self.n_elements, self.k, device=self.device, dtype=getattr(torch, self.dtype),
                            seed=self.seed, chunk=self.chunk, fail_after=self.fail_after,
                            nan_element=self.nan_element, always_nan=self.always_nan, delay=self.delay)


def objective_factory_for(objective) -> _Factory:
    """A factory that rebuilds ``objective`` on a worker.

    Knows :class:`~arraysel.objective.toy.ToyObjective` and objectives with a
    ``scene`` that has ``to_dict()`` (the physics objective). Raises
    :class:`ParameterError` for anything else: pass ``objective_factory=``.
    """
    from arraysel.objective.toy import ToyObjective

    if isinstance(objective, ToyObjective):
        return ToyObjectiveFactory(objective.n_elements, objective.k, device=str(objective.device),
                                   dtype=_dtype_name(objective.dtype), seed=int(objective.scene.seed),
                                   chunk=objective.chunk, fail_after=objective.fail_after,
                                   nan_element=objective.nan_element, always_nan=objective.always_nan,
                                   delay=objective.delay)
    scene = getattr(objective, "scene", None)
    if scene is not None and hasattr(scene, "to_dict") and type(objective).__name__ == "Objective":
        return SceneObjectiveFactory(scene.to_dict(), device=str(getattr(objective, "device", "cpu")),
                                     dtype=_dtype_name(getattr(objective, "dtype", "float32")),
                                     chunk=int(getattr(objective, "chunk", 256)))
    raise ParameterError(
        f"cannot send a {type(objective).__name__} to other processes; give an objective_factory "
        f"(a picklable callable that builds the objective, e.g. arraysel.run.executors.SceneObjectiveFactory)")


# ---------------------------------------------------------------------------
# worker side: the cache of objectives, one per factory and worker process
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


def _process_init(token: str, factory, threads: int) -> None:
    from arraysel.run.allocator import tune_malloc

    tune_malloc()
    if threads:
        try:
            import torch
            torch.set_num_threads(threads)
        except Exception:  # torch missing or already initialised: keep its default
            pass
    _install_factory(token, factory)


# ---------------------------------------------------------------------------
# executors
# ---------------------------------------------------------------------------

@dataclasses.dataclass
class TaskFailed:
    """Yielded by :meth:`Executor.run_tasks` for a task that failed ``attempts`` times."""

    message: str
    attempts: int = 1
    exception: BaseException | None = None

    def __str__(self) -> str:
        return self.message


def _error_text(exc: BaseException) -> str:
    text = str(exc).strip().replace("\n", " ")
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class Executor:
    """Base class: runs ``fn(objective, item)`` for many items; see the module docstring."""

    name = "executor"
    #: True when the tasks run in the calling process (the caller's objective can be used)
    in_process = False

    def __init__(self, retries: int = DEFAULT_RETRIES):
        self.retries = int(check_number("retries", retries, lo=0, hi=100, integer=True))

    @property
    def workers(self) -> int:
        return 1

    def run_tasks(self, factory, fn: Callable, items: Sequence) -> Iterator[tuple[int, Any]]:
        """Yield ``(index, result)`` for each item as it finishes (any order); ``result`` is a
        :class:`TaskFailed` for a task whose worker died (or that raised) more than
        ``retries`` times."""
        raise NotImplementedError

    def describe(self) -> dict:
        return {"executor": self.name, "workers": self.workers, "retries": self.retries}

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class LocalExecutor(Executor):
    """Runs every task in the calling process, one after another.

    ``objective``: use this objective instead of building one from the factory.
    """

    name = "local"
    in_process = True

    def __init__(self, objective=None, retries: int = 0):
        super().__init__(retries)
        self.objective = objective
        self._built: dict[str, Any] = {}

    def _objective(self, factory):
        if self.objective is not None:
            return self.objective
        key = factory.key() if hasattr(factory, "key") else id(factory)
        if key not in self._built:
            self._built[key] = factory()
        return self._built[key]

    def run_tasks(self, factory, fn, items):
        obj = self._objective(factory)
        for i, item in enumerate(items):
            attempts = 0
            while True:
                attempts += 1
                try:
                    result = fn(obj, item)
                except (KeyboardInterrupt, SystemExit):
                    raise
                except Exception as exc:
                    if attempts <= self.retries:
                        continue
                    result = TaskFailed(_error_text(exc), attempts, exc)
                break
            yield i, result


def _mp_context():
    """``forkserver`` with torch and arraysel preloaded (a new worker is a cheap fork of a clean,
    single-threaded server, so restarting a pool after a worker died is fast); ``spawn`` where
    there is no forkserver. Never plain ``fork``: forking a process whose torch thread pools are
    running can deadlock."""
    import multiprocessing
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["torch", "arraysel.run.executors", "arraysel.run.experiment"])
        return ctx
    return multiprocessing.get_context("spawn")


class ProcessExecutor(Executor):
    """A pool of ``workers`` local processes (``forkserver`` start method, else ``spawn``).

    Each process builds the objective once (the factory is sent in the pool's
    initializer) and uses ``threads`` torch threads (default: cores / workers).
    When a process dies, ``concurrent.futures`` breaks the whole pool; the
    pool is restarted and the tasks that were running are run again *one at a
    time*, so only the task that kills its worker is charged an attempt.
    """

    name = "process"

    def __init__(self, workers: int | None = None, retries: int = DEFAULT_RETRIES, threads: int | None = None):
        super().__init__(retries)
        n = (os.cpu_count() or 1) if workers is None else workers
        self._workers = int(check_number("workers", n, lo=1, hi=1024, integer=True))
        if threads is None:
            threads = max(1, (os.cpu_count() or 1) // self._workers)
        self.threads = int(check_number("threads", threads, lo=0, integer=True))
        self._pool: cf.ProcessPoolExecutor | None = None
        self._pool_token: str | None = None
        self.restarts = 0

    @property
    def workers(self) -> int:
        return self._workers

    def _get_pool(self, token: str, factory, size: int) -> cf.ProcessPoolExecutor:
        if self._pool is not None and self._pool_token != token:
            self._shutdown()
        if self._pool is None:
            self._pool = cf.ProcessPoolExecutor(
                max_workers=size, mp_context=_mp_context(),
                initializer=_process_init, initargs=(token, factory, self.threads))
            self._pool_token = token
        return self._pool

    def _shutdown(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
            self._pool_token = None

    def run_tasks(self, factory, fn, items):
        items = list(items)
        token = factory.key()
        pending = collections.deque(range(len(items)))
        suspects: collections.deque[int] = collections.deque()
        attempts = [0] * len(items)
        inflight: dict[cf.Future, int] = {}
        size = min(self._workers, max(1, len(items)))

        def failed(i, exc, why):
            attempts[i] += 1
            if attempts[i] > self.retries:
                return TaskFailed(f"{why} ({attempts[i]} attempt(s)): {_error_text(exc)}", attempts[i], exc)
            return None

        try:
            while pending or suspects or inflight:
                pool = self._get_pool(token, factory, size)
                isolated = bool(suspects)
                if isolated:
                    if not inflight:
                        i = suspects.popleft()
                        inflight[pool.submit(_run_on_worker, token, fn, items[i])] = i
                else:
                    while pending and len(inflight) < size:
                        i = pending.popleft()
                        inflight[pool.submit(_run_on_worker, token, fn, items[i])] = i
                done, _ = cf.wait(list(inflight), return_when=cf.FIRST_COMPLETED)
                broken = any(isinstance(f.exception(), cf.process.BrokenProcessPool) for f in done)
                if broken:  # every unfinished task of the pool is lost; sort them out
                    done = set(inflight)
                    cf.wait(list(inflight))
                victims = []
                for f in sorted(done, key=lambda f: inflight[f]):
                    i = inflight.pop(f)
                    exc = f.exception()
                    if exc is None:
                        yield i, f.result()
                    elif isinstance(exc, cf.process.BrokenProcessPool):
                        victims.append((i, exc))
                    else:
                        res = failed(i, exc, "task failed")
                        if res is None:
                            pending.appendleft(i)
                        else:
                            yield i, res
                if broken:
                    self._shutdown()
                    self.restarts += 1
                    if isolated and len(victims) == 1:  # it ran alone: it is the one that kills its worker
                        i, exc = victims[0]
                        res = failed(i, exc, "worker process died")
                        if res is None:
                            suspects.appendleft(i)
                        else:
                            yield i, res
                    else:
                        suspects.extend(i for i, _ in victims)
        finally:
            for f in inflight:
                f.cancel()

    def close(self) -> None:
        self._shutdown()


# -- Dask -------------------------------------------------------------------

def _import_distributed():
    try:
        import distributed
    except ImportError as exc:
        raise ParameterError(f"--executor dask needs dask.distributed, which is not installed "
                             f"({exc}); install it with: {DASK_INSTALL_HINT}") from None
    return distributed


def _make_factory_plugin_class():
    from distributed.diagnostics.plugin import WorkerPlugin

    class FactoryPlugin(WorkerPlugin):
        """Installs an objective factory on every worker (present and future) once."""

        idempotent = False

        def __init__(self, token, factory):
            self.token = token
            self.factory = factory
            self.name = f"arraysel-objective-{token}"

        def setup(self, worker):
            from arraysel.run.executors import _install_factory
            _install_factory(self.token, self.factory)

        def teardown(self, worker):
            from arraysel.run.executors import _remove_factory
            _remove_factory(self.token)

    FactoryPlugin.__module__ = __name__
    FactoryPlugin.__qualname__ = "_FactoryPlugin"
    FactoryPlugin.__name__ = "_FactoryPlugin"
    return FactoryPlugin


def __getattr__(name):  # the plugin class exists only once distributed is imported (lazy)
    if name == "_FactoryPlugin":
        cls = _make_factory_plugin_class()
        globals()[name] = cls
        return cls
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class DaskExecutor(Executor):
    """Tasks on a Dask distributed cluster.

    Parameters
    ----------
    scheduler : address of a running scheduler (``tcp://host:8786``); or
    workers : start a LocalCluster on 127.0.0.1 with this many single-threaded
        worker processes (no dashboard)
    retries : extra attempts of a task after it raised; on the LocalCluster
        also the number of worker deaths a task may cause before it is given
        up (``allowed_failures``; on your own scheduler that is its
        ``distributed.scheduler.allowed-failures`` setting)
    connect_timeout : seconds to wait for the scheduler
    client : an existing ``distributed.Client`` to use (not closed by :meth:`close`)
    """

    name = "dask"

    def __init__(self, scheduler: str | None = None, workers: int | None = None,
                 retries: int = DEFAULT_RETRIES, connect_timeout: float = 30.0, client=None):
        super().__init__(retries)
        distributed = _import_distributed()
        self._own_client = client is None
        self.cluster = None
        self._plugins: set[str] = set()
        if client is not None:
            self.client = client
        elif scheduler:
            if "://" not in scheduler:
                raise ParameterError(f"--scheduler must be an address like tcp://host:8786, got {scheduler!r}")
            try:
                self.client = distributed.Client(scheduler, timeout=f"{connect_timeout}s",
                                                 set_as_default=False)
            except (OSError, TimeoutError) as exc:
                raise ParameterError(f"cannot reach the Dask scheduler at {scheduler} within "
                                     f"{connect_timeout:g} s: {_error_text(exc)}") from None
        else:
            n = (os.cpu_count() or 1) if workers is None else workers
            n = int(check_number("workers", n, lo=1, hi=1024, integer=True))
            import dask
            # worker-saturation 1.0: a worker holds only the task it runs, so when it dies the
            # scheduler blames (and counts a failure against) that task alone
            with dask.config.set({"distributed.scheduler.worker-saturation": 1.0}):
                self.cluster = distributed.LocalCluster(
                    n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                    dashboard_address=None, silence_logs=logging.ERROR,
                    scheduler_kwargs={"allowed_failures": self.retries})
            self.client = distributed.Client(self.cluster, set_as_default=False)

    @property
    def workers(self) -> int:
        return len(self.client.nthreads())

    def describe(self) -> dict:
        return {**super().describe(), "scheduler": self.client.scheduler.address}

    def _install(self, factory) -> str:
        token = factory.key()
        if token not in self._plugins:
            self.client.register_plugin(__getattr__("_FactoryPlugin")(token, factory),
                                        name=f"arraysel-objective-{token}")
            self._plugins.add(token)
        return token

    def run_tasks(self, factory, fn, items):
        distributed = _import_distributed()
        token = self._install(factory)
        run = uuid.uuid4().hex[:8]
        futures = [self.client.submit(_run_on_worker, token, fn, item, key=f"arraysel-{run}-{i}",
                                      retries=self.retries, pure=False)
                   for i, item in enumerate(items)]
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for f in distributed.as_completed(futures, loop=self.client.loop):
                i = index[f.key]
                try:
                    result = f.result()
                except distributed.KilledWorker as exc:
                    result = TaskFailed(f"worker process died more than {self.retries} time(s) running "
                                        f"this task ({_error_text(exc)})", self.retries + 1, exc)
                except Exception as exc:  # the task raised on its last attempt, or was lost
                    result = TaskFailed(f"task failed ({self.retries + 1} attempt(s)): {_error_text(exc)}",
                                        self.retries + 1, exc)
                f.release()
                yield i, result
        finally:
            for f in futures:
                if not f.done():
                    f.cancel()

    def close(self) -> None:
        for token in list(self._plugins):
            try:
                self.client.unregister_worker_plugin(f"arraysel-objective-{token}")
            except Exception:  # the cluster may be gone already
                pass
        self._plugins.clear()
        if self._own_client:
            self.client.close()
            if self.cluster is not None:
                self.cluster.close()


def make_executor(kind: str = "local", *, workers: int | None = None, scheduler: str | None = None,
                  retries: int = DEFAULT_RETRIES) -> Executor:
    """The executor of ``arraysel compare --executor KIND [--workers N] [--scheduler ADDR]``."""
    check_choice("--executor", kind, EXECUTORS)
    if scheduler and kind != "dask":
        raise ParameterError("--scheduler is only used with --executor dask")
    if workers is not None:
        check_number("--workers", workers, lo=1, hi=1024, integer=True)
        if kind == "local":
            raise ParameterError("--workers needs --executor process or --executor dask")
        if kind == "dask" and scheduler:
            raise ParameterError("give --scheduler (the cluster's workers are used) or --workers "
                                 "(a local cluster is started), not both")
    if kind == "local":
        return LocalExecutor(retries=0)
    if kind == "process":
        return ProcessExecutor(workers=workers, retries=retries)
    return DaskExecutor(scheduler=scheduler, workers=workers, retries=retries)


# ---------------------------------------------------------------------------
# batched mask evaluation and random search
# ---------------------------------------------------------------------------

def random_subsets(rng: np.random.Generator, batch: int, n: int, k: int) -> np.ndarray:
    """``(batch, k)`` sorted element indices of uniformly random k-subsets of ``range(n)``."""
    if k >= n:
        return np.tile(np.arange(n), (batch, 1))
    keys = rng.random((batch, n))
    return np.sort(np.argpartition(keys, k - 1, axis=1)[:, :k], axis=1)


def _finite(values) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)
    return np.where(np.isfinite(v), v, np.inf)


def _random_chunk(objective, item) -> dict:
    """Score one chunk of random masks; return its best (first minimum)."""
    index, seedseq, size, k = item
    n = int(objective.n_elements)
    k = int(objective.k if k is None else k)
    rng = np.random.default_rng(seedseq)
    subsets = random_subsets(rng, size, n, k)
    masks = np.zeros((size, n), dtype=bool)
    np.put_along_axis(masks, subsets, True, axis=1)
    t0 = time.perf_counter()
    means = _finite(objective.evaluate(masks)["Mean"])
    seconds = time.perf_counter() - t0
    best = int(np.argmin(means))
    return {"chunk": index, "mean": float(means[best]), "position": best,
            "elements": [int(i) for i in subsets[best]], "masks": size, "seconds": seconds,
            "pid": os.getpid()}


@dataclasses.dataclass
class RandomSearchResult:
    """Best of ``n_masks`` random k-subsets (see :func:`distributed_random_search`)."""

    elements: list[int]
    mean: float
    chunk_index: int
    n_masks: int
    n_chunks: int
    chunk: int
    seed: int
    seconds: float
    workers: int
    executor: str
    worker_pids: int

    @property
    def masks_per_second(self) -> float:
        return self.n_masks / self.seconds if self.seconds > 0 else math.inf

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "masks_per_second": self.masks_per_second}


def _as_executor(executor) -> tuple[Executor, bool]:
    if executor is None:
        return LocalExecutor(), True
    if isinstance(executor, str):
        return make_executor(executor), True
    if not isinstance(executor, Executor):
        raise ParameterError(f"executor must be an arraysel.run.executors.Executor, a name in {EXECUTORS} "
                             f"or None, got {type(executor).__name__}")
    return executor, False


def distributed_random_search(objective_factory, n_masks: int, k: int | None = None, seed: int = 0,
                              executor: Executor | str | None = None, chunk: int = 1024) -> RandomSearchResult:
    """Best of ``n_masks`` uniformly random k-subsets, scored on ``executor``'s workers.

    Parameters
    ----------
    objective_factory : picklable callable building the objective on a worker
        (:class:`SceneObjectiveFactory`, :class:`ToyObjectiveFactory`)
    n_masks : masks to score
    k : elements per mask (``None``: the objective's ``k``)
    seed : the search's seed; chunk ``i`` uses ``SeedSequence(seed).spawn(n_chunks)[i]``
    executor : an :class:`Executor` (``None``: in-process)
    chunk : masks per task; the chunks, hence the result, do not depend on the
        number of workers

    Raises :class:`ArrayselError` when a chunk fails after its retries.
    """
    n_masks = int(check_number("n_masks", n_masks, lo=1, integer=True))
    chunk = int(check_number("chunk", chunk, lo=1, integer=True))
    seed = int(check_number("seed", seed, lo=0, integer=True))
    if k is not None:
        k = int(check_number("k", k, lo=1, integer=True))
    ex, own = _as_executor(executor)
    n_chunks = -(-n_masks // chunk)
    streams = np.random.SeedSequence(seed).spawn(n_chunks)
    items = [(i, streams[i], min(chunk, n_masks - i * chunk), k) for i in range(n_chunks)]
    best: tuple[float, int] | None = None
    best_res: dict | None = None
    pids = set()
    t0 = time.perf_counter()
    try:
        for i, res in ex.run_tasks(objective_factory, _random_chunk, items):
            if isinstance(res, TaskFailed):
                raise ArrayselError(f"random search chunk {i} of {n_chunks} failed: {res.message}")
            pids.add(res["pid"])
            key = (res["mean"], res["chunk"])
            if best is None or key < best:
                best, best_res = key, res
    finally:
        seconds = time.perf_counter() - t0
        if own:
            ex.close()
    assert best_res is not None
    mean = best_res["mean"]
    return RandomSearchResult(
        elements=best_res["elements"], mean=mean if math.isfinite(mean) else math.nan,
        chunk_index=best_res["chunk"], n_masks=n_masks, n_chunks=n_chunks, chunk=chunk, seed=seed,
        seconds=seconds, workers=ex.workers, executor=ex.name, worker_pids=len(pids))


def _evaluate_chunk(objective, item) -> dict:
    index, masks = item
    return {"chunk": index, "metrics": objective.evaluate(masks)}


def distributed_evaluate(objective_factory, masks, executor: Executor | str | None = None,
                         chunk: int = 1024) -> dict[str, np.ndarray]:
    """``objective.evaluate(masks)`` computed in chunks of ``chunk`` masks on ``executor``'s
    workers; the metrics come back in the order of ``masks``."""
    masks = np.asarray(masks)
    if masks.ndim != 2 or masks.shape[0] == 0:
        raise ParameterError(f"masks must have shape (B, Ne) with B >= 1, got {masks.shape}")
    chunk = int(check_number("chunk", chunk, lo=1, integer=True))
    ex, own = _as_executor(executor)
    items = [(i, masks[s:s + chunk]) for i, s in enumerate(range(0, masks.shape[0], chunk))]
    parts: dict[int, dict] = {}
    try:
        for i, res in ex.run_tasks(objective_factory, _evaluate_chunk, items):
            if isinstance(res, TaskFailed):
                raise ArrayselError(f"evaluation chunk {i} of {len(items)} failed: {res.message}")
            parts[i] = res["metrics"]
    finally:
        if own:
            ex.close()
    names = list(parts[0])
    return {m: np.concatenate([np.asarray(parts[i][m]) for i in range(len(items))]) for m in names}


# ---------------------------------------------------------------------------
# compare: one (selector, seed) run per task
# ---------------------------------------------------------------------------

def _plugin_specs(cls) -> tuple[str, ...]:
    """``--plugin`` files a worker must load before it can unpickle ``cls``."""
    import sys
    mod = sys.modules.get(cls.__module__)
    if cls.__module__.startswith("arraysel_plugin_file_") and getattr(mod, "__file__", None):
        return (mod.__file__,)
    return ()


def compare_item(config: str, cls, options: dict, budget, seed: int) -> dict:
    """The picklable description of one compare run (see :func:`compare_task`)."""
    try:
        blob = pickle.dumps(cls)
    except Exception as exc:
        raise ParameterError(
            f"selector class {cls.__qualname__} cannot be sent to worker processes ({_error_text(exc)}); "
            f"define it at module level of an importable module, or load it with --plugin") from None
    return {"config": config, "selector": blob, "plugins": _plugin_specs(cls), "options": dict(options),
            "budget": budget.fresh(), "seed": int(seed)}


@dataclasses.dataclass
class _Raise:
    """Returned by a worker instead of raising an error that must stop the comparison
    (not retried: it is not the worker's fault)."""

    exception: BaseException


def compare_task(objective, item) -> dict | _Raise:
    """Run one ``(selector, seed)`` experiment on a worker: ``{"row": ..., "trace": [...]}``."""
    from arraysel.selectors.registry import load_plugin
    from arraysel.run.experiment import Experiment
    from arraysel.selectors.contract import BudgetExceededError

    for spec in item["plugins"]:
        load_plugin(spec)
    cls = pickle.loads(item["selector"])
    exp = Experiment(objective, cls, options=item["options"], budget=item["budget"], seed=item["seed"],
                     config=item["config"])
    try:
        row = exp.run()
    except BudgetExceededError as exc:
        return _Raise(exc)
    return {"row": row, "trace": [dict(t) for t in exp.trace], "pid": os.getpid()}


# ---------------------------------------------------------------------------
# isolation: one run at a time in a child process that can be killed
# ---------------------------------------------------------------------------

#: seconds a run may go past its time budget before its process is stopped
DEFAULT_GRACE_S = 30.0


def _isolated_main(conn, token: str, factory, threads: int) -> None:
    """Child side of :class:`IsolatedWorker`: build the objective once, then run what arrives."""
    _process_init(token, factory, threads)
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        fn, item = msg
        try:
            result = ("ok", _run_on_worker(token, fn, item))
        except Exception as exc:  # the task's own failure (objective build, unpickling the selector)
            result = ("failed", _error_text(exc))
        try:
            conn.send(result)
        except Exception as exc:  # a result that does not pickle
            conn.send(("failed", f"its result could not be sent back: {_error_text(exc)}"))


class IsolatedWorker:
    """Runs ``fn(objective, item)`` tasks one at a time in a child process (``forkserver``, else
    ``spawn``; never ``fork``), so that a task that hangs, exits the process (``sys.exit``,
    ``os._exit``) or crashes it costs only its own result.

    :meth:`run` returns the task's result, or a :class:`TaskFailed` saying what happened: the
    process was stopped after ``timeout`` seconds, or it ended (exit code) without a result. The
    child is started on first use and again after it was lost; it builds the objective from
    ``factory`` once per start.
    """

    def __init__(self, factory, threads: int | None = None):
        self.factory = factory
        self.threads = threads
        self.token = f"{factory.key()}-{uuid.uuid4().hex[:8]}"
        self.proc = None
        self.conn = None
        self.starts = 0

    def _start(self) -> None:
        ctx = _mp_context()
        parent, child = ctx.Pipe(duplex=True)
        threads = self.threads
        if threads is None:
            try:
                import torch
                threads = torch.get_num_threads()
            except Exception:  # pragma: no cover - torch is a dependency
                threads = 0
        self.proc = ctx.Process(target=_isolated_main, args=(child, self.token, self.factory, threads),
                                daemon=True, name="arraysel-isolated-run")
        self.proc.start()
        child.close()
        self.conn = parent
        self.starts += 1

    def _stop(self) -> int | None:
        """Kill the child (if alive); its exit code."""
        proc, self.proc = self.proc, None
        if self.conn is not None:
            self.conn.close()
            self.conn = None
        if proc is None:
            return None
        if proc.is_alive():
            proc.kill()
        proc.join(10)
        return proc.exitcode

    def run(self, fn: Callable, item, timeout: float | None = None):
        if self.proc is None or not self.proc.is_alive():
            self._stop()
            self._start()
        t0 = time.monotonic()
        try:
            self.conn.send((fn, item))
            ready = self.conn.poll(timeout)
        except BaseException:  # KeyboardInterrupt while waiting: do not leave the child running
            self._stop()
            raise
        if not ready:
            self._stop()
            return TaskFailed(f"stopped after {time.monotonic() - t0:.1f} s (its limit was {timeout:.1f} s): "
                              f"the run did not return in time")
        try:
            status, payload = self.conn.recv()
        except (EOFError, OSError):
            code = self._stop()
            return TaskFailed(f"the run ended its process (exit code {code}) without a result")
        if status == "ok":
            return payload
        return TaskFailed(payload)

    def close(self) -> None:
        if self.proc is not None and self.proc.is_alive() and self.conn is not None:
            try:
                self.conn.send(None)
                self.proc.join(5)
            except (OSError, ValueError):
                pass
        self._stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
