"""Isolation: one run at a time in a child process that can be killed (``arraysel compare`` without
``--in-process``), so a run that hangs, exits its process or crashes it costs only its own row."""
from __future__ import annotations

import time
import uuid
from typing import Callable

from arraysel.errors import error_text as _error_text
from arraysel.run.workers import TaskFailed, _process_init, _run_on_worker, mp_context as _mp_context

__all__ = ["DEFAULT_GRACE_S", "IsolatedWorker"]


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
