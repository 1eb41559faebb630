"""Warm templates: each worker slot's one-off work done once, before any run's clock starts.

A :class:`WarmTemplate` is a process (``forkserver``, else ``spawn``) that builds the objective
from its picklable factory (the PSF basis mapped from the cache and checked), warms it
(:func:`warm_objective`: batches of 1, :data:`~arraysel.physics.compiled.MIN_BATCH` and 64 masks
and one gradient step, so numba's compiled code is loaded and the delay-and-sum plans are built)
and then waits. Each run is a child **forked** from the warm template: it starts with all of
that done, sets its thread counts (:func:`set_threads`), runs ``fn(objective, item)`` once, sends
the result and ends. So a run is isolated exactly as a :class:`~arraysel.run.isolation.OneShot`
child is (a plugin that edits the objective, patches a module, hangs, exits or crashes its
process changes nothing for the runs that follow), but it starts in milliseconds instead of
rebuilding everything, and none of the worker's one-off work is charged to it.

The template never runs a task's code and never unpickles what a task sends: the task and its
arguments reach the child as bytes, and the child's messages go back to the supervisor as bytes
(the supervisor, which re-scores every result, unpickles them). The template kills its child on
the supervisor's word (the run's deadline) and reaps it; the child watches the template (a pipe
whose write end only the template holds) and the template watches its supervisor, so none of
them outlives the one above it.

Forking is safe because the template never starts a thread pool that a fork would break: torch
runs its warm-up on one thread (GNU OpenMP, torch's pool, cannot be used across a fork once it
has started threads), and numba uses its ``workqueue`` threading layer in templates (its OpenMP
layer refuses to fork). The child then sets the worker's thread count for torch, numba and the
BLAS libraries.
"""
from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.connection
import multiprocessing.util
import os
import pickle
import signal
import socket
import threading
import time
from typing import Callable

from arraysel.errors import error_text as _error_text
from arraysel.run.workers import (BUILD_LIMIT_S, _SELF_STOP_MARGIN_S, TaskFailed, _children_allowed, _end, _process_init,
                                  _watch, mp_context as _mp_context, wait_for_result)

__all__ = ["WarmTemplate", "warm_objective", "set_threads", "cpu_cores", "threads_per_worker", "run_with_retries",
           "borrowed_template", "close_templates"]

#: seconds the supervisor waits for the template to confirm that a killed child is gone
_KILL_WAIT_S = 10.0


def cpu_cores() -> int:
    """CPU cores this process may use (its affinity mask where the system has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def threads_per_worker(workers: int, cores: int | None = None) -> int:
    """Threads of each of ``workers`` worker processes sharing ``cores`` cores (default: this
    machine's): ``cores // workers``, at least 1."""
    cores = cpu_cores() if cores is None else int(cores)
    return max(1, cores // max(1, int(workers)))


def set_threads(threads: int):
    """Use ``threads`` threads in this process for torch (intra-op), numba's parallel loops and the
    BLAS libraries numpy and scipy load (``threadpoolctl``); ``0``: leave them as they are.
    Returns threadpoolctl's limiter (its ``restore_original_limits()`` undoes the BLAS limit), or
    None (nothing set, or threadpoolctl unable to)."""
    threads = int(threads or 0)
    if threads <= 0:
        return None
    import torch
    torch.set_num_threads(threads)
    numba = _loaded("numba")
    if numba is not None:
        with contextlib.suppress(Exception):  # more than the pool was launched with: keep its size
            numba.set_num_threads(min(threads, int(numba.config.NUMBA_NUM_THREADS)))
    with contextlib.suppress(Exception):  # threadpoolctl missing or a library it cannot drive
        from threadpoolctl import threadpool_limits
        return threadpool_limits(threads, user_api="blas")
    return None


@contextlib.contextmanager
def thread_counts(threads: int | None):
    """:func:`set_threads` ``(threads)`` for the ``with`` block, in this process; the torch and
    numba counts and the BLAS limits it found are restored after it (``None`` or ``0``: nothing
    is changed). A run in this process uses it, so that ``--threads`` holds there as it does in
    a worker."""
    threads = int(threads or 0)
    if threads <= 0:
        yield
        return
    import torch
    numba = _loaded("numba")
    before_torch = torch.get_num_threads()
    before_numba = None
    if numba is not None:
        with contextlib.suppress(Exception):
            before_numba = numba.get_num_threads()
    limits = set_threads(threads)
    try:
        yield
    finally:  # the BLAS limits first: restoring them may touch the library torch's threads read
        if limits is not None:
            with contextlib.suppress(Exception):
                limits.restore_original_limits()
        torch.set_num_threads(before_torch)
        numba = _loaded("numba")  # (a run may have imported it)
        if numba is not None:
            with contextlib.suppress(Exception):
                numba.set_num_threads(before_numba if before_numba is not None else
                                      int(numba.config.NUMBA_NUM_THREADS))


def _loaded(name: str):
    import sys
    return sys.modules.get(name)


def _numba_for_fork(threads: int) -> None:
    """Before numba starts its threads in a template: the fork-safe ``workqueue`` layer, with a
    pool of ``threads`` (the most the children will ask for)."""
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency
        return
    numba.config.THREADING_LAYER = "workqueue"
    numba.config.NUMBA_NUM_THREADS = max(1, int(threads or 1))
    # start the pool here: numba makes a multiprocessing lock (a named semaphore) in the process
    # that starts it; made here, the children inherit it, and it is released when the template
    # ends (a child killed at its deadline cannot leave one behind for the resource tracker)
    numba.get_num_threads()


def warm_objective(objective, seed: int = 0) -> dict:
    """Do an objective's one-off work now (what its first calls would otherwise pay for):
    ``evaluate`` batches of 1, :data:`~arraysel.physics.compiled.MIN_BATCH` and 64 random
    selections of ``k`` elements, and one gradient step of its loss model where the objective
    has one (:func:`~arraysel.objective.contract.loss_model_of`). Returns ``{"warm_s": seconds,
    "warm_steps": [...], "warm_error": text or ""}``; a step that fails is reported, not raised
    (the runs then meet the same error in their rows)."""
    import numpy as np

    from arraysel.objective.contract import loss_model_of
    from arraysel.physics.compiled import MIN_BATCH

    t0 = time.perf_counter()
    n, k = int(objective.n_elements), int(objective.k)
    rng = np.random.default_rng(seed)
    steps, errors = [], []
    for batch in dict.fromkeys((1, MIN_BATCH, 64)):
        masks = np.zeros((batch, n), dtype=bool)
        for row in masks:
            row[rng.choice(n, size=k, replace=False)] = True
        try:
            objective.evaluate(masks)
            steps.append(f"evaluate({batch})")
        except Exception as exc:
            errors.append(f"evaluate({batch}): {_error_text(exc)}")
    model = loss_model_of(objective)
    if model is not None:
        try:
            model.gradient(np.full(n, k / n))
            steps.append("mask_loss+backward")
        except Exception as exc:
            errors.append(f"mask_loss: {_error_text(exc)}")
    return {"warm_s": time.perf_counter() - t0, "warm_steps": steps, "warm_error": "; ".join(errors)}


# ---------------------------------------------------------------------------
# the template process and its children
# ---------------------------------------------------------------------------

def _template_main(ctrl, factory, threads: int, alive, verify, env, warm: bool) -> None:
    """The template: build and warm the objective, say ``warm``, then fork one child per run."""
    os.environ.clear()
    os.environ.update(env)
    threading.Thread(target=_watch, args=(alive, [None]), daemon=True, name="arraysel-watchdog").start()
    _process_init(None, None, 1)  # one torch thread: no OpenMP pool exists when a child is forked
    _numba_for_fork(threads)
    if verify:
        os.environ["ARRAYSEL_CACHE_VERIFY"] = verify
    t0 = time.perf_counter()
    try:
        objective = factory()
        build_s = time.perf_counter() - t0
        info = warm_objective(objective) if warm else {"warm_s": 0.0, "warm_steps": [], "warm_error": ""}
    except Exception as exc:
        ctrl.send(("broken", f"the objective could not be built: {_error_text(exc)}"))
        _end()
    info.update(pid=os.getpid(), host=socket.gethostname(), threads=int(threads), build_s=build_s,
                ready_s=time.perf_counter() - t0)
    ctrl.send(("warm", info))
    while True:
        try:
            msg = ctrl.recv()
        except (EOFError, OSError):  # the supervisor is gone
            _end()
        if msg[0] != "run":
            _end()
        _fork_run(ctrl, alive, objective, msg[1], threads, msg[2])


def _fork_run(ctrl, alive, objective, payload: bytes, threads: int, timeout) -> None:
    """Fork a child that runs the pickled ``(fn, item)`` in ``payload``; relay its messages to the
    supervisor as bytes; kill it when the supervisor says so; reap it; say how it ended."""
    ctx = multiprocessing.get_context("fork")
    res_r, res_w = ctx.Pipe(duplex=False)
    up_r, up_w = ctx.Pipe(duplex=False)  # the child's view of this template
    pid = os.fork()
    if pid == 0:  # the child: nothing of the template's channels stays open in it
        code = 0
        try:
            for end in (ctrl, alive, res_r, up_w):
                end.close()
            _child_main(res_w, up_r, objective, payload, threads, timeout)
        except SystemExit as exc:  # the run called sys.exit(): its code, as a process would end
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except BaseException:  # noqa: BLE001 - a child never returns into the template's loop
            code = 1
        _end(code)
    res_w.close()
    up_r.close()
    final = None
    try:
        while final is None:
            ready = multiprocessing.connection.wait([res_r, ctrl])
            if ctrl in ready:
                try:
                    word = ctrl.recv()
                except (EOFError, OSError):  # the supervisor is gone: so is the run
                    _kill(pid)
                    _end()
                if word[0] == "kill":
                    _kill(pid)
                elif word[0] == "stop":  # the supervisor ends the template, and so the run
                    _kill(pid)
                    _reap(pid)
                    _end()
            if res_r in ready:
                try:
                    data = res_r.recv_bytes()
                except (EOFError, OSError):  # the child ended (or was killed) without a result
                    final = ("died", _reap(pid))
                    pid = None
                    continue
                if data[:1] == b"F":  # its last message: the result
                    _kill(pid)
                    _reap(pid)
                    pid = None
                    final = ("result", data[1:])
                else:
                    ctrl.send(("msg", data[1:]))
    finally:
        if pid is not None:
            _kill(pid)
            _reap(pid)
        res_r.close()
        up_w.close()
    ctrl.send(final)


def _kill(pid: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)


def _reap(pid: int) -> int:
    """Wait for the child ``pid``; its exit code (negative: the signal that ended it)."""
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


def _child_main(res, up, objective, payload: bytes, threads: int, timeout) -> None:
    """A run: say ``ready``, run the task, send its result (``F`` + pickle) and end."""
    limit = [None if timeout is None else time.monotonic() + timeout + _SELF_STOP_MARGIN_S]
    threading.Thread(target=_watch, args=(up, limit), daemon=True, name="arraysel-watchdog").start()
    set_threads(threads)
    res.send_bytes(b"M" + pickle.dumps(("ready", None)))
    try:
        fn, item = pickle.loads(payload)
        result = ("ok", fn(objective, item))
    except Exception as exc:  # the task's own failure (unpickling the selector, a plugin's error)
        result = ("failed", _error_text(exc))
    try:
        data = pickle.dumps(result)
    except Exception as exc:  # a result that does not pickle
        data = pickle.dumps(("failed", f"its result could not be sent back: {_error_text(exc)}"))
    # release what the run registered for cleanup (a multiprocessing lock is a named semaphore)
    # before the result goes: the template kills the child as soon as it has it
    with contextlib.suppress(Exception):
        multiprocessing.util._run_finalizers(0)  # noqa: SLF001 - what a normal exit runs
    res.send_bytes(b"F" + data)
    res.close()
    _end()


class WarmTemplate:
    """A warm template process (see the module docstring) and the run it is doing.

    :meth:`start` starts it (it builds and warms the objective); :meth:`submit` hands it a run
    ``fn(objective, item)``, which a forked child does; :meth:`poll` returns ``None`` while the
    run goes on, then its result or a :class:`~arraysel.run.workers.TaskFailed` (``"timeout"``:
    stopped ``timeout`` seconds after it started; ``"died"``: its process, or the template,
    ended without a result; ``"failed"``: the task raised or the objective could not be built).
    :meth:`wait` blocks until then. ``info`` holds the warm-up's figures once the template is
    warm (``pid``, ``host``, ``threads``, ``build_s``, ``warm_s``, ``ready_s``, ``warm_steps``,
    ``warm_error``). A template whose process ended (``alive`` false) is replaced by a new one.
    """

    def __init__(self, factory, threads: int = 1, verify: str | None = None, warm: bool = True):
        self.factory = factory
        self.threads = max(1, int(threads or 1))
        self.verify = verify
        self.warm = warm
        self.proc = self.conn = self.alive_w = None
        self.info: dict | None = None
        #: the ``info`` of each warm-up (a template that ended is started, and warmed, again)
        self.warm_ups: list[dict] = []
        self.broken: str | None = None
        self._reset_run()

    def _reset_run(self):
        self.busy = False
        self.started_at: float | None = None
        self.ready_at: float | None = None
        self.timeout: float | None = None
        self.result = None
        self.killing: float | None = None

    # -- the process -----------------------------------------------------------------------
    def start(self) -> "WarmTemplate":
        ctx = _mp_context()
        parent, child = ctx.Pipe(duplex=True)
        alive_r, alive_w = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=_template_main, name="arraysel-template", daemon=True,
                                args=(child, self.factory, self.threads, alive_r, self.verify,
                                      dict(os.environ), self.warm))
        with _children_allowed():
            self.proc.start()
        child.close()
        alive_r.close()
        self.conn, self.alive_w = parent, alive_w
        self.info, self.broken = None, None
        self._started = time.monotonic()
        return self

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.broken is None

    def close(self) -> None:
        """End the template (and any run it is doing) and release its pipes."""
        proc = self.proc
        if proc is not None:
            with contextlib.suppress(Exception):
                self.conn.send(("stop",))
            proc.join(5)  # it ends itself, releasing what it registered for cleanup
            if proc.is_alive():
                proc.kill()
            proc.join(10)
            with contextlib.suppress(Exception):
                proc.close()
            self.proc = None
        for end in (self.conn, self.alive_w):
            if end is not None:
                end.close()
        self.conn = self.alive_w = None

    # -- one run ---------------------------------------------------------------------------
    def submit(self, fn: Callable, item, timeout: float | None = None) -> "WarmTemplate":
        """Hand the template the run ``fn(objective, item)`` (it starts once the template is warm)."""
        if self.busy:
            raise RuntimeError("the template is already doing a run")
        payload = pickle.dumps((fn, item))
        if self.proc is not None and not self.proc.is_alive():  # it ended since its last run
            self.close()
        if self.proc is None:
            self.start()
        self._reset_run()
        self.busy = True
        self.timeout = timeout
        self.started_at = time.monotonic()
        try:
            self.conn.send(("run", payload, timeout))
        except OSError:  # it ended just now: a new one
            self.close()
            self.start()
            self.conn.send(("run", payload, timeout))
        return self

    @property
    def deadline(self) -> float:
        """``time.monotonic()`` at which the run is stopped (``inf``: never)."""
        if self.killing is not None:
            return self.killing + _KILL_WAIT_S
        if self.ready_at is None:
            return max(self.started_at, self._started) + BUILD_LIMIT_S
        return self.ready_at + self.timeout if self.timeout is not None else float("inf")

    def waitables(self) -> list:
        return [] if self.result is not None or self.proc is None else [self.conn, self.proc.sentinel]

    def _read_one(self):
        """Read one message of the template; the run's result when it is final, else ``None``."""
        kind, payload = self.conn.recv()
        if kind == "warm":
            self.info = payload
            self.warm_ups.append(payload)
        elif kind == "broken":
            self.broken = payload
            return TaskFailed(payload, kind="failed")
        elif kind == "msg":
            status, _ = pickle.loads(payload)
            if status == "ready":
                self.ready_at = time.monotonic()
        elif kind == "died":
            if self.killing is not None:
                return "killed"
            return TaskFailed(f"the run ended its process (exit code {payload}) without a result", kind="died")
        elif kind == "result":
            if self.killing is not None:
                return "killed"
            status, value = pickle.loads(payload)
            return value if status == "ok" else TaskFailed(value, kind="failed")
        return None

    def _finish(self, result):
        self.result = result
        self.busy = False
        return result

    def poll(self):
        """The run's result once there is one, else ``None``."""
        if self.result is not None or not self.busy:
            return self.result
        try:
            while self.conn.poll():
                res = self._read_one()
                if res == "killed":
                    return self._finish(self._stopped_message())
                if res is not None:
                    if self.broken is not None:
                        self.close()
                    return self._finish(res)
        except (EOFError, OSError):  # the template ended: a child killed it, or it was killed
            code = self.proc.exitcode if self.proc is not None else None
            self.close()
            if self.killing is not None:
                return self._finish(self._stopped_message())
            return self._finish(TaskFailed(f"the run ended its worker's template process (exit code {code}) "
                                           f"without a result", kind="died"))
        now = time.monotonic()
        if now >= self.deadline:
            if self.killing is None and self.ready_at is not None:
                self.killing = now  # the template kills the child; its word that it did follows
                with contextlib.suppress(Exception):
                    self.conn.send(("kill",))
                return None
            self.close()  # not warm in time, or the template did not confirm the kill
            if self.ready_at is None:
                return self._finish(TaskFailed(f"its objective was not built within {BUILD_LIMIT_S:g} s",
                                               kind="timeout"))
            return self._finish(self._stopped_message())
        return None

    def _stopped_message(self) -> TaskFailed:
        took = (self.killing or time.monotonic()) - (self.ready_at or self.started_at)
        return TaskFailed(f"stopped after {took:.1f} s (its limit was {self.timeout:.1f} s): the run did not "
                          f"return in time", kind="timeout")

    def wait(self):
        """Block until :meth:`poll` has a result; return it (on any exception, close
        first: never leave the run going)."""
        return wait_for_result(self, self.close)

    def cancel(self) -> None:
        """Abandon the run it is doing: the template (and with it the run) is ended."""
        if self.busy:
            self.close()
            self._reset_run()

    def run(self, fn: Callable, item, timeout: float | None = None):
        """:meth:`submit` then :meth:`wait`."""
        return self.submit(fn, item, timeout).wait()


def run_with_retries(template: WarmTemplate, fn: Callable, item, timeout: float | None, retries: int):
    """Run ``fn(objective, item)`` on ``template``; a run whose process died without a result is
    started again (from the template, started again where it died too) up to ``retries`` times (a
    timeout is final). The result or a :class:`~arraysel.run.workers.TaskFailed`."""
    attempts = 0
    while True:
        attempts += 1
        res = template.run(fn, item, timeout)
        if not isinstance(res, TaskFailed):
            return res
        res.attempts = attempts
        if res.kind == "died" and attempts <= retries:
            continue
        if res.kind == "died" and retries:
            res.message = f"worker process died ({attempts} attempt(s)): {res.message}"
        return res


# ---------------------------------------------------------------------------
# the templates of a worker process that is not ours (a Dask worker)
# ---------------------------------------------------------------------------

_IDLE: dict[tuple, list[WarmTemplate]] = {}
_ALL: dict[tuple, list[WarmTemplate]] = {}
_POOL_LOCK = threading.Lock()


@contextlib.contextmanager
def borrowed_template(token: str, factory, threads: int):
    """A warm template of this process for ``(token, threads)``, kept for the next task (one per
    task that runs at the same time in this process: a Dask worker with several threads)."""
    key = (token, int(threads))
    with _POOL_LOCK:
        idle = _IDLE.setdefault(key, [])
        template = idle.pop() if idle else None
        if template is None:
            template = WarmTemplate(factory, threads)
            _ALL.setdefault(key, []).append(template)
    try:
        yield template
    finally:
        with _POOL_LOCK:
            _IDLE.setdefault(key, []).append(template)


def close_templates(token: str) -> None:
    """End this process's templates for ``token`` (a Dask worker plugin's teardown)."""
    with _POOL_LOCK:
        keys = [k for k in _ALL if k[0] == token]
        found = [t for k in keys for t in _ALL.pop(k)]
        for k in keys:
            _IDLE.pop(k, None)
    for t in found:
        t.close()
