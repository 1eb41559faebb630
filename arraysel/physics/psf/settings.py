"""The environment variables the PSF operator reads (here and nowhere else in the physics).

``ARRAYSEL_MEMORY_GIB``
    Memory cap (GiB, a number > 0 and at most 1e6) of the exact PSF path: its batches and DAS
    plan cache are sized to stay within it, and a scene that cannot fit one mask under it is
    refused before any work. The grid-sized steps of setting a scene up (:func:`grid_bytes`)
    are held to it too, from the sizes alone, before anything is allocated. Default: min(4 GiB,
    a quarter of the physical memory).
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


#: float64 (pixels x elements) arrays alive at once while the window estimate
#: (:meth:`~arraysel.physics.psf.operator.PSFModel.window_estimate`) computes the DAS sample
#: positions of every 8th row and column of the grid (measured from the peak resident memory:
#: ``docs/performance.md``, "Tuning constants")
WINDOW_ESTIMATE_ARRAYS = 9
#: bytes per pixel of one mask's whole-grid image on the exact path (complex64 row chunks, their
#: concatenation and its magnitude), and per window pixel of its kernel (complex64 and magnitude)
IMAGE_BYTES_PER_PIXEL = 20
KERNEL_BYTES_PER_PIXEL = 12
#: heap growth on top of the live arrays (as the exact path's own estimate)
HEAP_FACTOR = 1.2


def grid_bytes(n_x: int, n_z: int, window: int, n_elements: int) -> tuple[int, str]:
    """Estimated peak memory (bytes) of the steps of setting a scene up and evaluating one mask
    whose size follows the grid alone, from the sizes (nothing is allocated), and the step: the
    window estimate's sample positions (every 8th row and column, every element, float64), or
    one mask's whole-grid image and its kernel. A lower bound of what the PSF operator needs:
    its own checks, made later, count more."""
    sub = (-(-n_z // 8) + 1) * (-(-n_x // 8) + 1)
    positions = WINDOW_ESTIMATE_ARRAYS * 8 * sub * n_elements
    image = IMAGE_BYTES_PER_PIXEL * n_x * n_z + KERNEL_BYTES_PER_PIXEL * window * window
    if positions >= image:
        return int(HEAP_FACTOR * positions), "the DAS sample positions of its window estimate"
    return int(HEAP_FACTOR * image), "one mask's whole-grid image on the exact path"


def largest_grid_pixels(n_elements: int, limit: int) -> int:
    """About the most grid pixels (``n_x * n_z``) :func:`grid_bytes` allows under ``limit`` bytes."""
    per_pixel = max(WINDOW_ESTIMATE_ARRAYS * 8 * n_elements / 64, IMAGE_BYTES_PER_PIXEL + KERNEL_BYTES_PER_PIXEL)
    return int(limit / (HEAP_FACTOR * per_pixel))
