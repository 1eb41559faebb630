"""Where selector runs and batches of masks are computed: in-process, a local
process pool, or a Dask distributed cluster.

The unit of work is a *task*: one ``(scene, selector, seed)`` run of
``arraysel compare`` (:mod:`arraysel.run.compare_task`) or one chunk of masks
(:mod:`arraysel.run.random_search`). A task is a module-level function
``fn(objective, item)``; every worker builds the objective **once** from a
picklable *objective factory* (``objective.worker_factory()``, e.g.
:class:`~arraysel.objective.psf_objective.SceneObjectiveFactory`) and keeps it in
the worker-side cache of :mod:`arraysel.run.workers`.

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

``run_tasks(..., fresh=True, timeout=S)`` (what ``compare`` asks for, since its tasks run
plugins) runs each task in a fresh child process (:class:`~arraysel.run.isolation.OneShot`):
started by this process for :class:`ProcessExecutor` (at most ``workers`` at a time), by the
worker for :class:`DaskExecutor`. Nothing a task does reaches another, and a task still running
``S`` seconds after its objective was built is killed and yields a :class:`TaskFailed` of kind
``"timeout"`` (not retried).
"""
from __future__ import annotations

import collections
import concurrent.futures as cf
import logging
import multiprocessing.connection
import os
import time
import uuid
from typing import Any, Callable, Iterator, Sequence

from arraysel.errors import ParameterError, check_choice, check_number, error_text as _error_text
from arraysel.run.workers import TaskFailed, _process_init, _run_on_worker
from arraysel.run.workers import mp_context as _mp_context
from arraysel.run.template import threads_per_worker

__all__ = ["EXECUTORS", "DASK_INSTALL_HINT", "DEFAULT_RETRIES", "TaskFailed", "Executor", "LocalExecutor",
           "ProcessExecutor", "DaskExecutor", "make_executor", "as_executor"]

#: executor names accepted by :func:`make_executor` and ``arraysel compare --executor``
EXECUTORS = ("local", "process", "dask")
DASK_INSTALL_HINT = "pip install arraysel[dask]"
DEFAULT_RETRIES = 2


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

    def run_tasks(self, factory, fn: Callable, items: Sequence, *, fresh: bool = False,
                  timeout: float | None = None, verify: str | None = None) -> Iterator[tuple[int, Any]]:
        """Yield ``(index, result)`` for each item as it finishes (any order); ``result`` is a
        :class:`TaskFailed` for a task whose worker died (or that raised) more than
        ``retries`` times. ``fresh``: each task in a fresh child process, killed ``timeout``
        seconds after its objective was built (see the module docstring; ``verify`` is the
        child's cache check, :class:`~arraysel.run.isolation.OneShot`)."""
        raise NotImplementedError

    def describe(self) -> dict:
        return {"executor": self.name, "workers": self.workers, "retries": self.retries}

    def worker_warm_ups(self) -> list[dict]:
        """One entry per warm template this executor's workers started (the one-off work of a
        worker, done before its first run's clock starts; ``info`` of
        :class:`~arraysel.run.template.WarmTemplate`)."""
        return []

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
        self.warm_ups: list[dict] = []

    def worker_warm_ups(self) -> list[dict]:
        return list(self.warm_ups)

    def _objective(self, factory):
        if self.objective is not None:
            return self.objective
        key = factory.key() if hasattr(factory, "key") else id(factory)
        if key not in self._built:
            self._built[key] = factory()
        return self._built[key]

    def run_tasks(self, factory, fn, items, *, fresh=False, timeout=None, verify=None):
        if fresh:
            from arraysel.run.isolation import default_threads
            from arraysel.run.template import WarmTemplate, run_with_retries
            template = WarmTemplate(factory, default_threads(), verify)
            try:
                for i, item in enumerate(items):
                    yield i, run_with_retries(template, fn, item, timeout, self.retries)
            finally:
                self.warm_ups.extend(template.warm_ups)
                template.close()
            return
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
            threads = threads_per_worker(self._workers)
        self.threads = int(check_number("threads", threads, lo=0, integer=True))
        self._pool: cf.ProcessPoolExecutor | None = None
        self._pool_token: str | None = None
        self.restarts = 0
        self._templates: list = []
        self._template_key = None
        self.warm_ups: list[dict] = []

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

    def _shutdown(self, kill: bool = False) -> None:
        """Shut the pool down; ``kill``: stop its processes first (an interrupted run must not
        wait for the tasks they are running)."""
        if self._pool is not None:
            if kill:
                for proc in list((getattr(self._pool, "_processes", None) or {}).values()):
                    if proc.is_alive():
                        proc.kill()
            self._pool.shutdown(wait=not kill, cancel_futures=True)
            self._pool = None
            self._pool_token = None

    def _templates_for(self, factory, verify) -> list:
        """This pool's warm templates for ``factory`` (started, warming, on first use; kept for
        the next :meth:`run_tasks`)."""
        from arraysel.run.template import WarmTemplate

        key = (factory.key(), verify)
        if self._template_key != key:
            self._close_templates()
            self._templates = [WarmTemplate(factory, self.threads, verify).start() for _ in range(self._workers)]
            self._template_key = key
        return self._templates

    def _close_templates(self) -> None:
        for t in self._templates:
            self.warm_ups.extend(t.warm_ups)
            t.close()
        self._templates, self._template_key = [], None

    def _run_fresh(self, factory, fn, items, timeout, verify):
        """Each task in a child forked from one of ``workers`` warm templates, at most one per
        template at a time."""
        items = list(items)
        pending = collections.deque(range(len(items)))
        attempts = [0] * len(items)
        templates = self._templates_for(factory, verify)
        running: dict = {}
        try:
            while pending or running:
                for t in templates:
                    if pending and t not in running:
                        i = pending.popleft()
                        attempts[i] += 1
                        running[t.submit(fn, items[i], timeout)] = i
                left = min(t.deadline for t in running) - time.monotonic()
                multiprocessing.connection.wait([w for t in running for w in t.waitables()],
                                                timeout=min(max(0.0, left), 3600.0))
                for t in list(running):
                    res = t.poll()
                    if res is None:
                        continue
                    i = running.pop(t)
                    if isinstance(res, TaskFailed):
                        res.attempts = attempts[i]
                        if res.kind == "died":
                            if attempts[i] <= self.retries:
                                self.restarts += 1
                                pending.appendleft(i)
                                continue
                            res.message = f"worker process died ({attempts[i]} attempt(s)): {res.message}"
                    yield i, res
        finally:
            for t in running:
                t.cancel()

    def describe(self) -> dict:
        return {**super().describe(), "threads": self.threads}

    def worker_warm_ups(self) -> list[dict]:
        """The warm-up of each template this pool started (``info`` of
        :class:`~arraysel.run.template.WarmTemplate`)."""
        return self.warm_ups + [w for t in self._templates for w in t.warm_ups]

    def run_tasks(self, factory, fn, items, *, fresh=False, timeout=None, verify=None):
        if fresh:
            yield from self._run_fresh(factory, fn, items, timeout, verify)
            return
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
        except BaseException:
            for f in inflight:
                f.cancel()
            self._shutdown(kill=True)  # the tasks still running are not waited for
            raise
        finally:
            for f in inflight:
                f.cancel()

    def close(self) -> None:
        self._shutdown()
        self._close_templates()


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
            from arraysel.run.workers import _install_factory
            _install_factory(self.token, self.factory)

        def teardown(self, worker):
            from arraysel.run.template import close_templates
            from arraysel.run.workers import _remove_factory
            _remove_factory(self.token)
            close_templates(self.token)

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
                 retries: int = DEFAULT_RETRIES, connect_timeout: float = 30.0, client=None,
                 threads: int | None = None):
        super().__init__(retries)
        self.threads = None if threads is None else int(check_number("threads", threads, lo=1, integer=True))
        self._warm_ups: dict = {}
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
                    # the scheduler's HTTP server (dashboard, metrics) on a free loopback port: a
                    # fixed one (8787) may be taken by another cluster on the machine
                    n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                    dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR,
                    scheduler_kwargs={"allowed_failures": self.retries})
            self.client = distributed.Client(self.cluster, set_as_default=False)

    @property
    def workers(self) -> int:
        return len(self.client.nthreads())

    def describe(self) -> dict:
        return {**super().describe(), "scheduler": self.client.scheduler.address,
                "threads": "cores / tasks at a time on the host" if self.threads is None else self.threads}

    def worker_warm_ups(self) -> list[dict]:
        return list(self._warm_ups.values())

    def _threads_by_host(self) -> dict | int:
        """Threads of each run: the ``threads`` given, else ``{host: tasks that run at a time on
        it}`` (the sum of its workers' threads), from which a worker takes cores / that."""
        if self.threads is not None:
            return int(self.threads)
        per_host: dict[str, int] = collections.Counter()
        for addr, info in self.client.scheduler_info(n_workers=-1)["workers"].items():
            per_host[_host_of(addr)] += int(info.get("nthreads") or 1)
        return dict(per_host)

    def _install(self, factory) -> str:
        token = factory.key()
        if token not in self._plugins:
            self.client.register_plugin(__getattr__("_FactoryPlugin")(token, factory),
                                        name=f"arraysel-objective-{token}")
            self._plugins.add(token)
        return token

    def run_tasks(self, factory, fn, items, *, fresh=False, timeout=None, verify=None):
        distributed = _import_distributed()
        token = self._install(factory)
        run = uuid.uuid4().hex[:8]
        if fresh:  # the worker runs each task in a child of its own, killed at the deadline
            threads = self._threads_by_host()
            futures = [self.client.submit(_run_fresh_on_worker, token, fn, item, timeout, self.retries, threads,
                                          key=f"arraysel-{run}-{i}", retries=self.retries, pure=False)
                       for i, item in enumerate(items)]
        else:
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
                if fresh and isinstance(result, dict) and "warm_ups" in result:
                    for w in result["warm_ups"]:
                        self._warm_ups[(w.get("host"), w.get("pid"))] = w
                    result = result["result"]
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


def _host_of(address: str) -> str:
    """``tcp://10.0.0.5:40123`` -> ``10.0.0.5``."""
    return address.split("://", 1)[-1].rsplit(":", 1)[0]


def _run_fresh_on_worker(token: str, fn, item, timeout, retries: int, threads):
    """On a Dask worker: ``fn(objective, item)`` in a child forked from this worker's warm template
    (built from the factory the worker plugin installed, warmed on the worker's first task, before
    that run's clock starts). ``threads``: the run's threads, or ``{host: tasks at a time}`` to
    share this host's cores. Returns ``{"result": ..., "warm_ups": [...]}``."""
    from arraysel.errors import ArrayselError
    from arraysel.run.template import borrowed_template, cpu_cores
    from arraysel.run.workers import _FACTORIES

    factory = _FACTORIES.get(token)
    if factory is None:
        raise ArrayselError(f"worker process {os.getpid()} has no objective factory {token} "
                            f"(the executor did not install it)")
    if isinstance(threads, dict):
        from distributed import get_worker
        threads = max(1, cpu_cores() // max(1, int(threads.get(_host_of(get_worker().address), 1))))
    from arraysel.run.template import run_with_retries
    with borrowed_template(token, factory, threads) as template:
        result = run_with_retries(template, fn, item, timeout, retries)
        return {"result": result, "warm_ups": list(template.warm_ups)}


def make_executor(kind: str = "local", *, workers: int | None = None, scheduler: str | None = None,
                  retries: int = DEFAULT_RETRIES, threads: int | None = None) -> Executor:
    """The executor of ``arraysel compare --executor KIND [--workers N] [--scheduler ADDR]
    [--threads T]`` (``threads``: each run's threads; default cores / runs at a time)."""
    check_choice("--executor", kind, EXECUTORS)
    if threads is not None:
        check_number("--threads", threads, lo=1, hi=1024, integer=True)
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
        return ProcessExecutor(workers=workers, retries=retries, threads=threads)
    return DaskExecutor(scheduler=scheduler, workers=workers, retries=retries, threads=threads)


def as_executor(executor) -> tuple[Executor, bool]:
    if executor is None:
        return LocalExecutor(), True
    if isinstance(executor, str):
        return make_executor(executor), True
    if not isinstance(executor, Executor):
        raise ParameterError(f"executor must be an arraysel.run.executors.Executor, a name in {EXECUTORS} "
                             f"or None, got {type(executor).__name__}")
    return executor, False
