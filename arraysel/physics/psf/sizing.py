"""The memory and time sizing of a :class:`~arraysel.physics.psf.operator.PSFModel`: what building
its fast-path basis costs (bytes, seconds, the stored size), the channel window the basis will
use, and the exact path's peak memory, batch and pixel chunking and seconds per mask.

Every function takes the model and reads its interface (``setup``, ``n_elements``,
``transmits``, ``margin``, ``dtype``, ``cdtype``, ``device``, ``memory_limit``,
``plan_cache_elements``, ``other_bytes``, ``baseline_bytes``, ``basis``, ``fast_batch_bytes``,
``x_grid``, ``z_grid``); the model's methods of the same names call these. Two results are
cached on the model (``_window_samples``, ``_calib``): the memory guard and the cache's size hint
both ask for the window, and the time estimate times one DAS chunk once. The constants are
measured by ``benchmarks/exact_memory.py`` (``docs/performance.md``).
"""
from __future__ import annotations

import torch

from arraysel.errors import ParameterError
from arraysel.physics.beamform import das_apply, das_plan, das_positions
from arraysel.physics.psf.basis import PairBasis
from arraysel.physics.psf.build import BasisBuilder

__all__ = ["basis_bytes", "basis_stored_bytes", "basis_build_seconds", "basis_estimate", "window_estimate",
           "estimate_window", "plan_cache_bytes", "plan_cache_limit", "model_bytes", "exact_bytes",
           "exact_chunking", "masks_per_batch", "exact_seconds_per_mask", "check_exact_memory"]

#: resident memory of ``import arraysel`` and one model (0.28 GiB measured after the imports)
_BASELINE_BYTES = 450 * 2 ** 20
#: target size of one DAS call's temporaries, and how many (B, pixels x Ne) complex arrays they are
_DAS_BYTES = 128 * 2 ** 20
_DAS_TEMPS = 6
#: resident heap per byte of live tensors (``benchmarks/exact_memory.py``)
_HEAP_FACTOR = 1.2
#: largest batch the exact path hands to DAS at once
_EXACT_MAX_BATCH = 256


def basis_bytes(model) -> int:
    """Estimated peak memory (bytes) of building the fast path's basis (see
    :class:`PairBasis`): the windowed pair I/Q signals, the pair images of E (all of them
    for small probes, tiles of pixels and a sketch for larger ones, kept whole between the
    sketch's passes when they fit), the strips' pair images when they are kept, and the
    stored tensors."""
    return basis_estimate(model)[0]


def basis_stored_bytes(model) -> int:
    """Upper estimate (bytes) of the stored basis (the cache entry): the sketch's rank
    bound, the pair channels, the core and strips' pair images."""
    return basis_estimate(model)[2]


def basis_build_seconds(model) -> float:
    """Estimated wall time (s) of building the fast path's basis: the delay-and-sum of the
    pair images (``ntx Ne^2`` complex multiply-adds per pixel of E, once or twice: see
    :attr:`BasisBuilder.keep_images_max_bytes`, and per pixel of the strips), the float64
    products (the exact Gram matrix, or a sketched build's projection, QR and tile Gram
    matrices), the pair I/Q signals and the write of the stored basis, at rates measured on two
    cores (``docs/performance.md``), scaled by the torch threads."""
    return basis_estimate(model)[1]


def basis_estimate(model) -> tuple[int, float, int]:
    """``(peak build bytes, build seconds, stored bytes)`` of the fast path's basis."""
    s = model.setup
    ne = model.n_elements
    ntx = len(s.tilts)
    pairs = ne * (ne + 1) // 2
    rows = min(s.n_z, s.window + 2 * model.margin)
    cols = min(s.n_x, s.window + 2 * model.margin)
    npix, npix2 = rows * cols, rows * (s.n_x - cols)
    size = torch.finfo(model.dtype).bits // 8
    T = window_estimate(model)
    X = ntx * ne * T * ne * 8
    A = 2 * ntx * ne * T * ne * size
    sketch = BasisBuilder.sketch_columns
    passes = 1  # delay-and-sums of the pair images on E
    if pairs <= sketch:
        work = pairs * 2 * npix * 8 * 2 + pairs * pairs * 8 * 3
        flops = 2 * pairs * pairs * 2 * npix  # the Gram matrix (float64)
        rank = pairs
    else:
        tile = BasisBuilder.missed_tile
        groups = -(-rows // tile) * -(-cols // tile)
        call = max(BasisBuilder.build_tile_bytes // (pairs * 16), tile * tile)  # pixels a kernel call
        work = pairs * sketch * 8 * 2 + sketch * 2 * npix * 8 * 2 + 3 * call * 16 * pairs + \
            groups * (2 * tile * tile) ** 2 * 8
        # float64: the projection B = Q^T H, the sketch's QR (counted twice: slower than a
        # product) and the tiles' Gram matrices (symmetric updates)
        flops = 2 * pairs * sketch * 2 * npix + 8 * pairs * sketch ** 2 + 2 * pairs * groups * (2 * tile * tile) ** 2
        if BasisBuilder.keeps_images(pairs, npix, model.dtype):  # kept between the passes
            work += pairs * 2 * npix * size
        else:
            passes = 2
        rank = sketch
    strips = size * pairs * 2 * npix2
    if strips > PairBasis.strip_max_bytes:
        strips = 0
    stored = size * (pairs * rank + rank * 2 * npix + pairs * 2 * 1024) + A + strips
    macs = ntx * ne * ne * (npix * passes + (npix2 if strips else 0))
    iq = ntx * ne * ne * T  # the pair I/Q's products (their frequencies are not known here)
    seconds = (4.2e-9 * macs + 2.2e-11 * flops + 3.6e-7 * iq) / max(1, torch.get_num_threads()) + 6e-9 * stored
    return int(X + work + stored + (strips // size) * 8), seconds, int(stored)


def window_estimate(model) -> int:
    """Samples per channel window (:meth:`BasisBuilder.sample_ranges`), estimated from the
    DAS plans of a subsampled grid (every 8th row and column and the grid's edges); computed
    once per model (the memory guard and the cache's size hint both ask)."""
    if getattr(model, "_window_samples", None) is None:
        model._window_samples = estimate_window(model)
    return model._window_samples


def estimate_window(model) -> int:
    """:func:`window_estimate` computed (not cached)."""
    s = model.setup
    zi = torch.unique(torch.cat([torch.arange(0, s.n_z, 8), torch.tensor([s.n_z - 1])]))
    xi = torch.unique(torch.cat([torch.arange(0, s.n_x, 8), torch.tensor([s.n_x - 1])]))
    Z, X = torch.meshgrid(model.z_grid[zi], model.x_grid[xi], indexing="ij")
    span = 2
    for t in model.transmits:
        # the first sample index of each (pixel, element) of the DAS plan, without the plan's
        # weights and phase rotations
        _, pos, valid = das_positions(X, Z, t.delays, s.probe, s.acq.fs, s.acq.c, t.grid.n_time,
                                      fnumber=s.fnumber)
        i0 = torch.floor(torch.where(valid, pos, torch.zeros_like(pos))).to(torch.long)
        if bool(valid.any()):
            hi = torch.where(valid, i0, torch.full_like(i0, -1)).amax(0)
            lo = torch.where(valid, i0, torch.full_like(i0, 1 << 40)).amin(0)
            ok = hi >= lo
            if bool(ok.any()):
                span = max(span, int((hi - lo)[ok].max()) + 2)
    return -(-(span + 8) // 4) * 4


# ------------------------------------------------------------------ exact path: memory
# The exact path's peak resident memory, in bytes, for a batch of ``batch`` masks (no autograd):
#   baseline: interpreter, torch and the model (``baseline_bytes``, a constant)
# + DAS plans kept: entries (pixel, element, transmit) x (i0 + w + rot), capped at a quarter
#   of ``memory_limit``; in a several-point objective also its siblings' plans and tensors
#   (``other_bytes``)
# + building one plan chunk: ~12 float64 (pixels x Ne) temporaries
# + per mask: I/Q of every transmit (n_tx x Ne x T complex), one transmit's spectra and RF on
#   the way, the whole-grid image (row chunks, their concatenation, its magnitude)
# + one DAS call: _DAS_TEMPS (B, pixels x Ne) complex temporaries (gathered samples, their
#   index, differences, products), its pixels chosen to keep this near _DAS_BYTES;
# all but the baseline times _HEAP_FACTOR, the heap growth (fragmentation, blocks glibc
# keeps) measured on top of the live tensors by ``benchmarks/exact_memory.py``.
# :func:`exact_chunking` picks the batch so the total stays within ``memory_limit``.


def sizes(model):
    """``(complex item bytes, samples T, FFT length, frequencies F)`` of the longest transmit."""
    c = 8 if model.dtype == torch.float32 else 16
    T = max(t.grid.n_time for t in model.transmits)
    nfft = max(t.grid.n_fft for t in model.transmits)
    F = max(int(t.grid.f.numel()) for t in model.transmits)
    return c, T, nfft, F


def plan_rows(model) -> int:
    """Grid rows of one DAS plan chunk (about 2M pixel-element entries)."""
    return max(1, (2 ** 21) // max(1, model.setup.n_x * model.n_elements))


def plan_cache_bytes(model) -> int:
    """Memory (bytes) of the DAS plans the exact path keeps (whole grid, every transmit, capped)."""
    c = 8 if model.dtype == torch.float32 else 16
    return plan_cache_limit(model) * (8 + c // 2 + c)


def plan_cache_limit(model) -> int:
    """Plan entries kept: ``plan_cache_elements``, at most a quarter of ``memory_limit``, at most all."""
    s = model.setup
    c = 8 if model.dtype == torch.float32 else 16
    quarter = model.memory_limit // 4 // (8 + c // 2 + c)
    return int(min(model.plan_cache_elements, quarter, len(model.transmits) * s.n_z * s.n_x * model.n_elements))


def model_bytes(model) -> int:
    """Memory (bytes) of the model's own tensors: per transmit the spectra -> I/Q map (2F x 2T in
    the model's dtype) and the spectra factors (Ne x F complex128 twice)."""
    size = torch.finfo(model.dtype).bits // 8
    return sum(4 * int(t.tx_field.shape[-1]) * int(t.grid.n_time) * size + 2 * int(t.tx_field.numel()) * 16
               for t in model.transmits)


def per_mask_bytes(model) -> int:
    """Memory (bytes) the exact path holds per mask of a batch."""
    s = model.setup
    c, T, nfft, F = sizes(model)
    ne = model.n_elements
    return len(model.transmits) * ne * T * c + 2 * ne * (F + nfft) * c + (2 * c + c // 2) * s.n_z * s.n_x


def das_pixels(model, batch: int) -> int:
    """Pixels of one DAS call for ``batch`` masks (its temporaries near ``_DAS_BYTES``)."""
    s = model.setup
    c = sizes(model)[0]
    want = _DAS_BYTES // max(1, _DAS_TEMPS * batch * model.n_elements * c)
    return int(min(s.n_z * s.n_x, max(s.n_x, want)))


def exact_bytes(model, batch: int, pixels: int | None = None) -> int:
    """Estimated peak resident memory (bytes) of the process during an exact-path evaluation of
    ``batch`` masks with DAS calls of ``pixels`` pixels (default: :func:`exact_chunking`'s)."""
    s = model.setup
    c = sizes(model)[0]
    if pixels is None:
        pixels = das_pixels(model, batch)
    build = 12 * plan_rows(model) * s.n_x * model.n_elements * 8
    das = _DAS_TEMPS * batch * pixels * model.n_elements * c
    work = plan_cache_bytes(model) + model.other_bytes + build + batch * per_mask_bytes(model) + das
    return int(model.baseline_bytes + _HEAP_FACTOR * work)


def exact_chunking(model, batch: int | None = None) -> tuple[int, int]:
    """(masks per batch, pixels per DAS call) of the exact path within ``memory_limit``.

    With ``batch`` given, only the pixels per DAS call are chosen for it.
    """
    if batch is None:
        batch = _EXACT_MAX_BATCH
        while batch > 1 and exact_bytes(model, batch) > model.memory_limit:
            batch = max(1, min(batch - 1, int(batch * 0.85)))
    return batch, das_pixels(model, batch)


def masks_per_batch(model) -> int:
    """Masks an evaluation should hand to :meth:`PSFModel.kernels <arraysel.physics.psf.operator.PSFModel.kernels>` at once: on the fast path as many
    as keep the batch's per-selection tensors (:meth:`PairBasis.bytes_per_selection
    <arraysel.physics.psf.basis.PairBasis.bytes_per_selection>`) within
    the model's ``fast_batch_bytes`` (the paper scene: 256; the 128-element built-in scenes: about
    200), at most 256; on the exact path what its memory allows."""
    if model.basis is not None:
        fit = model.fast_batch_bytes // max(1, model.basis.bytes_per_selection())
        return int(max(1, min(_EXACT_MAX_BATCH, fit)))
    return exact_chunking(model)[0]


def exact_seconds_per_mask(model, batch: int | None = None) -> float:
    """Estimated wall time (s) of one mask on the exact path (whole-grid image), at ``batch`` masks
    per call (default: :func:`exact_chunking`'s).

    Calibrated once by timing one DAS plan chunk (build and apply) of this grid, so the
    estimate costs a fraction of a second and reflects the machine's current load.
    """
    import time

    if batch is None:
        batch = exact_chunking(model)[0]
    if getattr(model, "_calib", None) is None:
        s = model.setup
        rows = slice(0, min(s.n_z, plan_rows(model)))
        t = model.transmits[0]
        t0 = time.perf_counter()
        Z, X = torch.meshgrid(model.z_grid[rows], model.x_grid, indexing="ij")
        plan = das_plan(X, Z, t.delays, s.probe, s.acq.fs, s.acq.c, t.grid.n_time, fnumber=s.fnumber,
                        fc=s.probe.fc)
        plan.w, plan.rot = plan.w.to(model.device, model.dtype), plan.rot.to(model.device, model.cdtype)
        plan.i0 = plan.i0.to(model.device)
        t1 = time.perf_counter()
        iq = torch.ones(2, model.n_elements, t.grid.n_time, dtype=model.cdtype, device=model.device)
        das = []
        for _ in range(2):  # the first call pays for allocations
            t2 = time.perf_counter()
            das_apply(iq, plan.i0, plan.w, plan.rot)
            das.append((time.perf_counter() - t2) / 2)
        model._calib = ((t1 - t0) / (rows.stop * s.n_x), min(das) / (rows.stop * s.n_x))
    per_px_plan, per_px_das = model._calib
    s = model.setup
    pixels = len(model.transmits) * s.n_z * s.n_x
    total = pixels * model.n_elements
    cached = min(1.0, plan_cache_limit(model) / max(1, total))
    # DAS for every mask; plans that do not fit the cache are rebuilt on every call
    return pixels * (per_px_das + (1 - cached) * per_px_plan / max(1, batch))


def check_exact_memory(model) -> None:
    """Refuse, before any work, a scene whose exact path cannot fit ``memory_limit`` even one mask
    and one grid row at a time."""
    need = exact_bytes(model, 1, pixels=model.setup.n_x)
    if need > model.memory_limit:
        s = model.setup
        raise ParameterError(
            f"this scene needs about {need / 2 ** 30:.1f} GiB for one mask on the exact PSF path (grid "
            f"{s.n_x} x {s.n_z} pixels, {model.n_elements} elements, {len(model.transmits)} transmits), more "
            f"than the memory cap of {model.memory_limit / 2 ** 30:.1f} GiB: reduce grid.n_x / grid.n_z "
            f"(or coarsen grid.pixel), or raise the cap with ARRAYSEL_MEMORY_GIB")
