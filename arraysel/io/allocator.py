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

:func:`malloc_tuned` applies the same settings for the duration of a ``with`` block only (the
PSF basis build, whose temporaries of hundreds of MiB otherwise map and zero tens of GB of
fresh pages), then restores glibc's defaults and returns the freed memory to the system.
"""
from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import logging
import os
import sys

_log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_TRIM_BYTES = 1 << 30
# glibc's defaults, restored by malloc_tuned
_DEFAULT_MMAP_MAX = 65536
_DEFAULT_TRIM_BYTES = 128 * 1024

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
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
        libc.malloc_trim.restype = ctypes.c_int
        return libc
    except (OSError, AttributeError):
        return None


def _apply_tuning():
    """Apply the settings (see the module docstring); glibc with them in effect, or None where
    tuning is disabled by ``ARRAYSEL_MALLOC_TUNE``, the C library is not glibc, or ``mallopt``
    refused them."""
    if not malloc_tuning_enabled():
        return None
    libc = _glibc()
    if libc is None:
        return None
    if libc.mallopt(_M_MMAP_MAX, 0) and libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_BYTES):
        return libc
    _log.warning("mallopt refused the allocator settings; large tensors stay mmap-backed")
    return None


def tune_malloc() -> bool:
    """Keep large freed blocks in the heap for reuse (see the module docstring).

    Returns True when the settings are in effect (also on repeated calls), False when disabled
    by ``ARRAYSEL_MALLOC_TUNE`` or not on glibc.
    """
    if "done" not in _state:
        _state["done"] = _apply_tuning() is not None
    return _state["done"]


@contextlib.contextmanager
def malloc_tuned():
    """The settings of :func:`tune_malloc` inside the ``with`` block, glibc's defaults and a
    ``malloc_trim`` after it (nothing changes where :func:`tune_malloc` is already in effect,
    tuning is disabled, or the C library is not glibc). The 256-element basis build: 172 s
    untuned, 151 s tuned (its pair I/Q step 23.6 -> 16.0 s, 9.0 -> 1.8 million page faults)."""
    libc = None if _state.get("done") else _apply_tuning()
    try:
        yield
    finally:
        if libc is not None:
            libc.mallopt(_M_MMAP_MAX, _DEFAULT_MMAP_MAX)
            libc.mallopt(_M_TRIM_THRESHOLD, _DEFAULT_TRIM_BYTES)
            libc.malloc_trim(0)
