"""Fixtures several test modules share (imported by name; pytest finds tests/ through its conftest).

* :func:`time_limit` -- an autouse fixture that fails, instead of hanging, a test that runs longer
  than its limit: ``_bounded = time_limit(120)`` in a module;
* :func:`own_plugin_manager` -- a process-wide plugin manager of the built-ins only (no installed
  entry points, no disable list from the environment), restored afterwards:
  ``from support import own_plugin_manager`` in a module, with ``pytestmark`` or autouse as it needs.
"""
from __future__ import annotations

import signal

import pytest


def time_limit(seconds: int):
    """An autouse fixture: SIGALRM after ``seconds`` raises TimeoutError in the test."""
    @pytest.fixture(autouse=True)
    def _bounded():
        def stop(signum, frame):
            raise TimeoutError(f"test took more than {seconds} s")
        old = signal.signal(signal.SIGALRM, stop)
        signal.alarm(seconds)
        yield
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    return _bounded


@pytest.fixture(autouse=True)
def own_plugin_manager(monkeypatch):
    """A process-wide plugin manager of the built-ins only, restored afterwards (autouse where
    imported)."""
    from arraysel.selectors import registry

    monkeypatch.delenv(registry.DISABLE_ENV, raising=False)
    registry.reset()
    registry._PM = registry.build_plugin_manager(load_entrypoints=False)
    try:
        yield
    finally:
        registry.reset()
