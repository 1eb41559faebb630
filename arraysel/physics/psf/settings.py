"""The environment variables the PSF operator reads (here and nowhere else in the physics).

``ARRAYSEL_MEMORY_GIB``
    Memory cap (GiB, a number > 0 and at most 1e6) of the exact PSF path: its batches and DAS
    plan cache are sized to stay within it, and a scene that cannot fit one mask under it is
    refused before any work. Default: min(4 GiB, a quarter of the physical memory).
``ARRAYSEL_BASIS_MAX_GIB``
    Largest estimated peak memory (GiB, a number > 0) of building the fast path's pair basis;
    a scene above it runs on the exact path only (with a warning). Default: 8.

The cache location (``ARRAYSEL_CACHE``) and its verification (``ARRAYSEL_CACHE_VERIFY``) are
read by :mod:`arraysel.io.cache`.

A bad value raises :class:`~arraysel.errors.ParameterError` naming the variable and the
allowed range.
"""
from __future__ import annotations

import os

from arraysel.errors import ParameterError, check_number

MEMORY_GIB = "ARRAYSEL_MEMORY_GIB"
BASIS_MAX_GIB = "ARRAYSEL_BASIS_MAX_GIB"

#: default of ``ARRAYSEL_BASIS_MAX_GIB``
DEFAULT_BASIS_MAX_GIB = 8.0


def _gib(name: str, raw: str, hi: float | None = None) -> int:
    try:
        gib = float(raw)
    except ValueError:
        raise ParameterError(f"{name} = {raw!r} must be a number of GiB (> 0)") from None
    check_number(name, gib, lo=0, lo_open=True, hi=hi)
    return int(gib * 2 ** 30)


def memory_limit_bytes() -> int:
    """Memory cap (bytes) of the exact PSF path: ``$ARRAYSEL_MEMORY_GIB``, default min(4 GiB, RAM / 4)."""
    raw = os.environ.get(MEMORY_GIB)
    if raw is None:
        try:
            ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):  # not POSIX
            ram = 24 * 2 ** 30
        return int(min(4 * 2 ** 30, ram / 4))
    return _gib(MEMORY_GIB, raw, hi=1e6)


def basis_limit_bytes() -> int:
    """Largest peak memory (bytes) of a fast-path basis build: ``$ARRAYSEL_BASIS_MAX_GIB``, default 8 GiB."""
    return _gib(BASIS_MAX_GIB, os.environ.get(BASIS_MAX_GIB, str(DEFAULT_BASIS_MAX_GIB)))
