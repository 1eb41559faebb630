"""A deadline for a run made in this process (``compare --in-process``, ``api.compare``).

A run in a child process is killed at its deadline; a run in this process cannot be, so
:func:`call_with_deadline` interrupts it instead: at the deadline a watcher thread raises
:class:`RunStopped` in the thread making the run (in the main thread through a signal, which
also wakes a ``time.sleep`` or a blocking wait there; in another thread as an asynchronous
exception, delivered at its next Python instruction), and again every
:data:`REPEAT_S` seconds until the run has ended. :class:`RunStopped` derives from
``BaseException``, so a selector's ``except Exception`` does not swallow it; a selector that
catches ``BaseException`` and carries on, or waits in compiled code that never returns, cannot
be stopped in this process (run it isolated, without ``--in-process``).
"""
from __future__ import annotations

import ctypes
import signal
import threading
import time
from typing import Callable

__all__ = ["RunStopped", "call_with_deadline", "REPEAT_S"]

#: seconds between two interruptions of a run that carried on past its deadline
REPEAT_S = 0.5
#: the signal that interrupts a run in the main thread (a real-time one: nothing else uses it)
_SIGNAL = getattr(signal, "SIGRTMIN", None)
_SIGNAL = _SIGNAL + 7 if _SIGNAL is not None else getattr(signal, "SIGUSR2", None)


class RunStopped(BaseException):
    """Raised in a run made in this process when its deadline has passed."""


class _Watch:
    """The state of one run under a deadline."""

    def __init__(self, seconds: float):
        self.seconds = float(seconds)
        self.started = time.monotonic()
        self.thread = threading.get_ident()
        self.main = threading.current_thread() is threading.main_thread()
        self.active = True
        self.lock = threading.Lock()
        self.over = threading.Event()

    def stop(self) -> None:
        """Raise :class:`RunStopped` in the run's thread (called by the watcher, lock held)."""
        if self.main:
            signal.pthread_kill(self.thread, _SIGNAL)
        else:
            ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(self.thread), ctypes.py_object(RunStopped))

    def watch(self) -> None:
        if self.over.wait(self.seconds):
            return
        while True:
            with self.lock:
                if not self.active:
                    return
                self.stop()
            if self.over.wait(REPEAT_S):
                return

    def end(self) -> None:
        """The run has ended: no interruption from now on (a pending one is withdrawn)."""
        with self.lock:
            self.active = False
            if not self.main:
                ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(self.thread), None)
        self.over.set()


#: the run under a deadline in the main thread (the signal handler's to interrupt), or None
_MAIN: list = [None]
_INSTALLED: list = [False]


def _on_signal(signum, frame) -> None:
    watch = _MAIN[0]
    if watch is not None and watch.active:
        raise RunStopped(f"stopped after {time.monotonic() - watch.started:.1f} s")


def _can_signal() -> bool:
    """Whether the main thread can be interrupted by :data:`_SIGNAL` (installing its handler once:
    it is never taken away, so a signal that arrives late finds it and does nothing)."""
    if _SIGNAL is None or not hasattr(signal, "pthread_kill"):
        return False
    if not _INSTALLED[0]:
        current = signal.getsignal(_SIGNAL)
        if current not in (signal.SIG_DFL, signal.SIG_IGN, None):  # someone else's: leave it alone
            return False
        signal.signal(_SIGNAL, _on_signal)
        _INSTALLED[0] = True
    return True


def call_with_deadline(fn: Callable, seconds: float | None):
    """``fn()``, interrupted with :class:`RunStopped` once ``seconds`` have passed (``None``: no
    deadline). The exception carries ``elapsed``, the seconds the run had taken."""
    if seconds is None:
        return fn()
    watch = _Watch(seconds)
    if watch.main and not _can_signal():
        watch.main = False  # interrupted as any other thread is
    watcher = threading.Thread(target=watch.watch, name="arraysel-deadline", daemon=True)
    if watch.main:
        _MAIN[0] = watch
    try:
        watcher.start()
        try:
            return fn()
        finally:
            watch.end()
    except RunStopped as exc:
        exc.elapsed = time.monotonic() - watch.started
        raise
    finally:
        watch.end()
        watcher.join()
        if _MAIN[0] is watch:
            _MAIN[0] = None
