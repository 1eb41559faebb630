"""Isolation: each run in a fresh child process that can be killed (``arraysel compare`` without
``--in-process``, and every run of ``--executor process`` or ``dask``).

A run gets a process of its own (:class:`OneShot`): the child builds the objective from its
picklable factory (the PSF basis is memory-mapped from the cache, so this is cheap), runs the
task, sends the result back and ends with ``os._exit``. So a plugin that edits or wraps the
objective it was given, patches a module, or leaves threads running changes nothing for the runs
that follow; a run that hangs is killed at its deadline, one that exits its process
(``sys.exit``, ``os._exit``) or crashes it costs only its own row. The child also watches its
supervisor and its own deadline, so it never outlives either (no orphans when the supervising
process is killed).
"""
from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.util
import os
import threading
import time
from typing import Callable

from arraysel.errors import error_text as _error_text
from arraysel.run.workers import (BUILD_LIMIT_S, _SELF_STOP_MARGIN_S, TaskFailed, _children_allowed, _end,  # noqa: F401
                                  _process_init, _watch, mp_context as _mp_context, wait_for_result)

__all__ = ["DEFAULT_GRACE_S", "UNTIMED_LIMIT_S", "BUILD_LIMIT_S", "OneShot", "IsolatedWorker", "run_one_shot"]


#: seconds a run may go past its time budget before its process is stopped
DEFAULT_GRACE_S = 30.0
#: seconds a run without a time budget (an evaluation budget only) may take, unless a grace
#: period is given (which is then its limit)
UNTIMED_LIMIT_S = 3600.0


def _one_shot_main(conn, factory, fn, item, threads: int, alive, timeout, verify, env) -> None:
    """Child side of :class:`OneShot`: build the objective, say ``ready``, run ``fn(objective,
    item)`` once, send the result and end (stray threads of the task end with the process).
    ``env``: the supervisor's environment now (a forkserver's children would otherwise get the
    environment of the moment the server started)."""
    os.environ.clear()
    os.environ.update(env)
    limit = [time.monotonic() + BUILD_LIMIT_S + _SELF_STOP_MARGIN_S]
    threading.Thread(target=_watch, args=(alive, limit), daemon=True, name="arraysel-watchdog").start()
    _process_init(None, None, threads)
    if verify:
        os.environ["ARRAYSEL_CACHE_VERIFY"] = verify
    try:
        objective = factory()
    except Exception as exc:
        conn.send(("failed", f"the objective could not be built: {_error_text(exc)}"))
        _end()
    limit[0] = None if timeout is None else time.monotonic() + timeout + _SELF_STOP_MARGIN_S
    conn.send(("ready", None))
    try:
        result = ("ok", fn(objective, item))
    except Exception as exc:  # the task's own failure (unpickling the selector, a plugin's error)
        result = ("failed", _error_text(exc))
    # release what this process registered for cleanup (numba's lock, a named semaphore) before
    # the result goes: the supervisor kills the child as soon as it has it, which would leave the
    # semaphore to the resource tracker (a warning at exit)
    with contextlib.suppress(Exception):
        multiprocessing.util._run_finalizers(0)  # noqa: SLF001 - what a normal exit runs
    try:
        conn.send(result)
    except Exception as exc:  # a result that does not pickle
        conn.send(("failed", f"its result could not be sent back: {_error_text(exc)}"))
    conn.close()
    _end()


class OneShot:
    """One task ``fn(objective, item)`` in a fresh child process (``forkserver``, else ``spawn``).

    :meth:`start` starts it; :meth:`poll` returns ``None`` while it runs, then its result or a
    :class:`TaskFailed` (``kind`` ``"timeout"``: stopped ``timeout`` seconds after the objective
    was built; ``"died"``: the process ended without a result; ``"failed"``: the task raised).
    :meth:`wait` blocks until then. The child is killed when it is done, stopped or abandoned
    (:meth:`kill`). ``verify``: the child's ``ARRAYSEL_CACHE_VERIFY`` (``"size"`` where this
    process has just loaded, and so checked, the same cache entries; ``None``: the default).
    """

    def __init__(self, factory, fn: Callable, item, timeout: float | None = None, threads: int = 0,
                 verify: str | None = None):
        self.factory, self.fn, self.item = factory, fn, item
        self.timeout = timeout
        self.threads = int(threads or 0)
        self.verify = verify
        self.proc = None
        self.conn = None
        self.alive = None
        self.ready_at: float | None = None
        self.started_at: float | None = None
        self.result = None

    def start(self) -> "OneShot":
        ctx = _mp_context()
        parent, child = ctx.Pipe(duplex=False)
        alive_r, alive_w = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=_one_shot_main, name="arraysel-run", daemon=True,
                                args=(child, self.factory, self.fn, self.item, self.threads, alive_r,
                                      self.timeout, self.verify, dict(os.environ)))
        with _children_allowed():
            self.proc.start()
        child.close()
        alive_r.close()
        self.conn = parent
        self.alive = alive_w
        self.started_at = time.monotonic()
        return self

    @property
    def deadline(self) -> float:
        """``time.monotonic()`` at which the child is stopped (``inf``: never)."""
        if self.ready_at is None:
            return self.started_at + BUILD_LIMIT_S
        return self.ready_at + self.timeout if self.timeout is not None else float("inf")

    def waitables(self) -> list:
        return [] if self.result is not None else [self.conn, self.proc.sentinel]

    def _finish(self, result):
        self.result = result
        self.kill()
        return result

    def poll(self):
        """The result once there is one (the child is then gone), else ``None``."""
        if self.result is not None:
            return self.result
        try:
            while self.conn.poll():
                status, payload = self.conn.recv()
                if status == "ready":
                    self.ready_at = time.monotonic()
                    continue
                if status == "ok":
                    return self._finish(payload)
                return self._finish(TaskFailed(payload, kind="failed"))
        except (EOFError, OSError):  # the child ended without a result
            self.proc.join(5)
            code = self.proc.exitcode
            return self._finish(TaskFailed(f"the run ended its process (exit code {code}) without a result",
                                           kind="died"))
        now = time.monotonic()
        if now >= self.deadline:
            if self.ready_at is None:
                msg = f"its objective was not built within {BUILD_LIMIT_S:g} s"
            else:
                msg = (f"stopped after {now - self.ready_at:.1f} s (its limit was {self.timeout:.1f} s): "
                       f"the run did not return in time")
            return self._finish(TaskFailed(msg, kind="timeout"))
        return None

    def wait(self):
        """Block until :meth:`poll` has a result; return it (on any exception, kill
        first: never leave the child running)."""
        return wait_for_result(self, self.kill)

    def kill(self) -> None:
        """Stop the child (if alive) and release its pipe."""
        proc = self.proc
        if proc is not None:
            if proc.is_alive():
                proc.kill()
            proc.join(10)
            with contextlib.suppress(Exception):
                proc.close()
            self.proc = None
        for end in (self.conn, self.alive):
            if end is not None:
                end.close()
        self.conn = self.alive = None


def run_one_shot(factory, fn: Callable, item, timeout: float | None = None, threads: int = 0,
                 retries: int = 0, verify: str | None = None):
    """Run ``fn(objective, item)`` in a fresh child; a child that dies without a result is
    started again up to ``retries`` times (a timeout is final). The result or a :class:`TaskFailed`."""
    attempts = 0
    while True:
        attempts += 1
        res = OneShot(factory, fn, item, timeout, threads, verify).start().wait()
        if not isinstance(res, TaskFailed):
            return res
        res.attempts = attempts
        if res.kind == "died" and attempts <= retries:
            continue
        if res.kind == "died" and retries:
            res.message = f"worker process died ({attempts} attempt(s)): {res.message}"
        return res


def default_threads() -> int:
    """torch threads of this process (what a child gets unless told otherwise)."""
    try:
        import torch
        return int(torch.get_num_threads())
    except Exception:  # pragma: no cover - torch is a dependency
        return 0


class IsolatedWorker:
    """Runs ``fn(objective, item)`` tasks one at a time, each in a fresh child process forked from
    a warm template (:class:`~arraysel.run.template.WarmTemplate`: the objective is built and
    warmed once, before the first run's clock starts), so that a task that hangs, exits its
    process, crashes it or changes the objective (or anything else in its process) costs only its
    own result.

    :meth:`run` returns the task's result, or a :class:`TaskFailed` saying what happened: the
    process was stopped ``timeout`` seconds after it started, or it ended (exit code) without a
    result. ``starts`` counts the children started; ``warm_ups`` lists the template's warm-ups
    (one, unless a run killed its template). ``threads``: each run's threads (default: this
    process's torch threads). ``verify``: see :class:`OneShot`.
    """

    def __init__(self, factory, threads: int | None = None, verify: str | None = None):
        self.factory = factory
        self.threads = threads
        self.verify = verify
        self.starts = 0
        self._template = None

    @property
    def warm_ups(self) -> list[dict]:
        return [] if self._template is None else list(self._template.warm_ups)

    def run(self, fn: Callable, item, timeout: float | None = None):
        from arraysel.run.template import WarmTemplate

        if self._template is None:
            threads = default_threads() if self.threads is None else self.threads
            self._template = WarmTemplate(self.factory, threads, self.verify)
        self.starts += 1
        return self._template.run(fn, item, timeout)

    def close(self) -> None:
        if self._template is not None:
            self._template.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
