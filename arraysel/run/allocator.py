"""Process-wide tuning of the C allocator for large, short-lived tensors.

A batch of the fast path allocates and frees tensors of tens to hundreds of
MiB. glibc serves every allocation above its mmap threshold (at most 32 MiB)
with a fresh ``mmap`` and unmaps it on free, so each batch pays page faults
and zeroing for all of its memory again: on the 2-core reference machine
:meth:`arraysel.objective.psf_objective.Objective.evaluate` takes 2.86 ms per paper-scene
mask untuned against 1.95 ms tuned (``benchmarks/bench_psf.py
--no-malloc-tune`` against the default).

:func:`tune_malloc` asks glibc to serve large blocks from the heap and to keep
freed memory for reuse (``mallopt(M_MMAP_MAX, 0)`` and a 1 GiB
``M_TRIM_THRESHOLD``). The cost: the process keeps its peak heap size until
it exits. The ``arraysel`` command line and the benchmarks call it at start;
a library user may call it too. ``ARRAYSEL_MALLOC_TUNE=0`` disables it. On a
C library other than glibc it does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys

_log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_TRIM_BYTES = 1 << 30

_state: dict = {}


def malloc_tuning_enabled() -> bool:
    """False when ``ARRAYSEL_MALLOC_TUNE`` is 0/off/no/false."""
    raw = os.environ.get("ARRAYSEL_MALLOC_TUNE", "1").strip().lower()
    return raw not in ("0", "off", "no", "false")


def _glibc():
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version.restype = ctypes.c_char_p
        libc.gnu_get_libc_version()  # only glibc has it
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.mallopt.restype = ctypes.c_int
        return libc
    except (OSError, AttributeError):
        return None


def tune_malloc() -> bool:
    """Keep large freed blocks in the heap for reuse (see the module docstring).

    Returns True when the settings are in effect (also on repeated calls), False when disabled
    by ``ARRAYSEL_MALLOC_TUNE`` or not on glibc.
    """
    if "done" in _state:
        return _state["done"]
    done = False
    if malloc_tuning_enabled():
        libc = _glibc()
        if libc is not None:
            done = bool(libc.mallopt(_M_MMAP_MAX, 0)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_BYTES))
            if not done:
                _log.warning("mallopt refused the allocator settings; large tensors stay mmap-backed")
    _state["done"] = done
    return done
