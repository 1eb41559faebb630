"""PSF metrics (Table 1 of the paper; ``docs/metrics.md``) and the circular convolution of the image model.

The training loss terms (``docs/metrics.md``, "Training terms") live in :mod:`arraysel.objective.losses`.

Everything here is written with torch, works on any device, accepts
float32/float64 and complex64/complex128 tensors, is batched over leading
dimensions and is differentiable with respect to the kernel ``kappa``. A batch
that needs no gradient on the CPU is scored by one compiled pass per kernel
instead (:mod:`arraysel.objective.metric_kernels`, the same definitions; the
tests run every metric both ways).
Non-smooth points (the argmax that locates the peak, the max over the main
lobe, the side-lobe quantile, ``|z|`` at ``z = 0``) give finite
sub-gradients, never NaN.

Conventions (see ``docs/metrics.md``):

* a PSF kernel ``kappa`` has shape ``(..., H, W)``; axis ``-2`` is the row
  axis, axis ``-1`` the column axis; ``pitch`` is the pixel pitch in metres,
  one number for both axes or ``(pitch_rows, pitch_cols)``;
* distances ``r`` are measured, in metres, from the pixel of the peak of
  ``|kappa|`` (first maximum in row-major order when there are ties);
* ``r_main`` and ``r_guard`` are given in wavelengths (multiples of
  ``wavelength``, metres); region boundaries are inclusive, with a relative
  tolerance of ``1e-9`` on ``r**2`` so that a pixel lying exactly on a
  boundary (e.g. 24 pixels = 1.5 wavelengths at pitch wavelength/16) is
  inside whatever the rounding of ``pitch`` and ``wavelength``.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Iterable, Sequence

import torch
from torch import Tensor

from arraysel.errors import NumericalError, ParameterError, check_number
from arraysel.objective import reductions as R
from arraysel.objective.tensors import _check_kernel_shape, _check_tensor
from arraysel.physics import compiled as physics_compiled

__all__ = [
    "METRIC_NAMES",
    "PSF_TERMS",
    "PSFRegions",
    "safe_abs",
    "si_mse",
    "psf_regions",
    "psf_metrics",
    "circular_convolve",
    "kernel_spectrum",
    "check_finite",
    "check_kernels",
    "check_regions",
]

#: names of the quantities :func:`psf_metrics` can return, in the order of ``docs/metrics.md``
#: the Table-1 metrics, in table order (defined in :mod:`arraysel.objective.names`, torch-free)
from arraysel.objective.names import METRIC_NAMES  # noqa: E402
PSF_TERMS = METRIC_NAMES


# the shared reductions (arraysel.objective.reductions), under this module's historical names
_BOUNDARY_RTOL = R.BOUNDARY_RTOL
_broadcast_shapes, _safe_div, _detached_scale = R.broadcast_shapes, R.safe_div, R.detached_scale
_divide_by_scale, _inner, _rowdot, _sqnorm, _promote = R.divide_by_scale, R.inner, R.rowdot, R.sqnorm, R.promote
_scaled_abs2, _peak_index, _safe_sqrt, _masked_quantile = R.scaled_abs2, R.peak_index, R.safe_sqrt, R.masked_quantile


# --------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------


def safe_abs(z: Tensor) -> Tensor:
    """``|z|`` for a real or complex tensor, with gradient 0 (not NaN) where ``z == 0``.

    The value equals ``torch.abs(z)`` (no overflow for large entries); the
    double ``where`` keeps the backward pass away from ``z / |z|`` at zero.
    """
    z = _check_tensor("z", z)
    nz = z != 0
    one = torch.ones((), dtype=z.dtype, device=z.device)
    mag = torch.abs(torch.where(nz, z, one))
    return torch.where(nz, mag, torch.zeros_like(mag))


def check_finite(name: str, tensor: Tensor) -> Tensor:
    """Return ``tensor`` if all its entries are finite; else raise :class:`NumericalError`.

    The message names the quantity ``name`` and counts NaN and Inf entries.
    (Costs one device synchronisation.)
    """
    if not isinstance(tensor, Tensor):
        tensor = torch.as_tensor(tensor)
    if tensor.is_floating_point() or tensor.is_complex():
        finite = torch.isfinite(tensor)
        if not bool(finite.all()):
            n_nan = int(torch.isnan(tensor).sum())
            n_bad = int((~finite).sum())
            raise NumericalError(
                f"{name} is not finite: {n_nan} NaN and {n_bad - n_nan} Inf value(s) "
                f"out of {tensor.numel()} (shape {tuple(tensor.shape)})")
    return tensor


def check_kernels(kappa: Tensor, kappa_ref: Tensor | None = None) -> None:
    """Raise :class:`NumericalError` if a PSF kernel is unusable for the metrics.

    Checks that ``kappa`` (and ``kappa_ref`` when given) are finite and that
    no kernel in the batch is identically zero (SI-MSE and the ratios of
    :func:`psf_metrics` are undefined there; the differentiable functions
    then return finite placeholder values instead of NaN). This helper
    synchronises with the device: call it outside hot loops.
    """
    for name, x in (("kappa", kappa), ("kappa_ref", kappa_ref)):
        if x is None:
            continue
        x = _check_tensor(name, x)
        _check_kernel_shape(name, x)
        check_finite(name, x)
        zero = (x == 0).flatten(-2).all(-1)
        if bool(zero.any()):
            idx = [tuple(i) for i in torch.nonzero(zero).tolist()][:5]
            where = "" if x.dim() == 2 else f" at batch index(es) {idx}"
            raise NumericalError(f"{name} is identically zero{where}; its PSF metrics are undefined")


# --------------------------------------------------------------------------
# SI-MSE
# --------------------------------------------------------------------------


def si_mse(kappa: Tensor, kappa_ref: Tensor) -> Tensor:
    """Scale-invariant MSE ``L_PSF`` (``docs/metrics.md``).

    ``||a* kappa - kappa_ref||^2 / ||kappa_ref||^2`` with
    ``a* = <kappa, kappa_ref> / <kappa, kappa>`` and ``<u, v> = sum(conj(u) v)``
    over the last two axes. ``kappa`` has shape ``(..., H, W)``;
    ``kappa_ref`` broadcasts against it. Returns a real tensor of the
    broadcast leading shape, in ``[0, 1]``.

    Degenerate inputs give finite values, not NaN: a zero ``kappa`` gives
    ``a* = 0`` (loss 1, gradient 0); a zero ``kappa_ref`` gives 0. Use
    :func:`check_kernels` to reject them explicitly.
    """
    kappa = _check_tensor("kappa", kappa)
    kappa_ref = _check_tensor("kappa_ref", kappa_ref)
    _check_kernel_shape("kappa", kappa)
    _check_kernel_shape("kappa_ref", kappa_ref)
    try:
        _broadcast_shapes(kappa.shape, kappa_ref.shape)
    except RuntimeError as exc:
        raise ParameterError(f"kappa {tuple(kappa.shape)} and kappa_ref {tuple(kappa_ref.shape)} "
                             f"do not broadcast") from exc
    k, r = _promote(kappa, kappa_ref)
    # L is invariant to the scale of kappa and of kappa_ref separately: divide
    # each kernel by a detached scale so float32 sums cannot under/overflow
    # (no gradient is lost: the loss does not depend on those scales).
    k = _divide_by_scale(k, _detached_scale(k))
    r = _divide_by_scale(r, _detached_scale(r))
    kk = _sqnorm(k)
    kr = _inner(k, r)
    rr = _sqnorm(r)
    tiny = torch.finfo(kk.dtype).tiny
    a = _safe_div(kr, torch.where(kk > tiny, kk, torch.zeros_like(kk)))
    # the residual is formed explicitly (not as rr - |kr|^2/kk) so that L = 0 is
    # reached to rounding; it is insensitive to first order to errors in a*.
    resid = _sqnorm(a[..., None, None] * k - r)
    return _safe_div(resid, rr)


# --------------------------------------------------------------------------
# regions
# --------------------------------------------------------------------------

@dataclass
class PSFRegions:
    """Regions of a batch of PSF kernels, all relative to each kernel's peak.

    Attributes
    ----------
    peak : LongTensor ``(..., 2)``
        (row, column) index of the peak of ``|kappa|`` (first maximum).
    main : BoolTensor ``(..., H, W)``
        ``Omega_main = {r <= r_main}`` (always contains the peak).
    side : BoolTensor ``(..., H, W)``
        ``Omega_side = {r >= r_guard}`` (may be empty for a small window).
    r : Tensor ``(..., H, W)`` or None
        distance to the peak in metres (real dtype of ``kappa``); ``None``
        when not requested.
    """

    peak: Tensor
    main: Tensor
    side: Tensor
    r: Tensor | None = None


def _parse_pitch(pitch: float | Sequence[float]) -> tuple[float, float]:
    if isinstance(pitch, Tensor):
        pitch = pitch.tolist()
    if isinstance(pitch, (list, tuple)):
        if len(pitch) != 2:
            raise ParameterError(f"pitch must be a number or (pitch_rows, pitch_cols), got {pitch!r}")
        return (check_number("pitch[0]", pitch[0], lo=0, lo_open=True),
                check_number("pitch[1]", pitch[1], lo=0, lo_open=True))
    p = check_number("pitch", pitch, lo=0, lo_open=True)
    return p, p


@functools.lru_cache(maxsize=32)
def _offset_tables(h: int, w: int, pr: float, pc: float, r_main: float, r_guard: float):
    """Tables over all offsets (di, dj), di in [-(h-1), h-1]: d^2, main mask, side mask (CPU)."""
    di = torch.arange(-(h - 1), h, dtype=torch.float64) * pr
    dj = torch.arange(-(w - 1), w, dtype=torch.float64) * pc
    d2 = di[:, None] ** 2 + dj[None, :] ** 2
    main = d2 <= (r_main ** 2) * (1 + _BOUNDARY_RTOL)
    side = d2 >= (r_guard ** 2) * (1 - _BOUNDARY_RTOL)
    return d2, main, side


@functools.lru_cache(maxsize=16)
def _device_masks(h: int, w: int, pr: float, pc: float, r_main: float, r_guard: float,
                  device: torch.device, dtype: torch.dtype = torch.bool) -> tuple[Tensor, Tensor]:
    """The main/side offset tables as ``dtype`` (bool or 0/1 float), cached on ``device``."""
    _, main, side = _offset_tables(h, w, pr, pc, r_main, r_guard)
    return main.to(device=device, dtype=dtype), side.to(device=device, dtype=dtype)


def _region_radii(pitch, wavelength, r_main, r_guard) -> tuple[float, float, float, float]:
    """Validated (pitch_rows, pitch_cols, r_main, r_guard), the radii in metres."""
    pr, pc = _parse_pitch(pitch)
    lam = check_number("wavelength", wavelength, lo=0, lo_open=True)
    rm = check_number("r_main", r_main, lo=0)
    rg = check_number("r_guard", r_guard, lo=0)
    if rg < rm:
        raise ParameterError(f"r_guard = {r_guard!r} must be >= r_main = {r_main!r} (both in wavelengths)")
    return pr, pc, rm * lam, rg * lam


def _regions_flat(kappa: Tensor, pitch, wavelength, r_main, r_guard, distance: bool,
                  flat_peak: Tensor | None = None, mask_dtype: torch.dtype = torch.bool) -> PSFRegions:
    """Regions for kappa of shape (B, H, W); masks as ``mask_dtype`` (bool or 0/1 float)."""
    pr, pc, rm, rg = _region_radii(pitch, wavelength, r_main, r_guard)
    b, h, w = kappa.shape
    dev = kappa.device
    tmain, tside = _device_masks(h, w, pr, pc, rm, rg, dev, mask_dtype)
    if flat_peak is None:
        flat_peak = _peak_index(_scaled_abs2(kappa.detach()))
    i0 = torch.div(flat_peak, w, rounding_mode="floor")
    j0 = flat_peak - i0 * w
    rows = torch.arange(h, device=dev)[None, :] - i0[:, None] + (h - 1)  # (B, H)
    cols = torch.arange(w, device=dev)[None, :] - j0[:, None] + (w - 1)  # (B, W)
    ri, ci = rows[:, :, None], cols[:, None, :]
    main = tmain[ri, ci]
    side = tside[ri, ci]
    r = None
    if distance:
        rdt = kappa.real.dtype if kappa.is_complex() else kappa.dtype
        d2 = _offset_tables(h, w, pr, pc, rm, rg)[0]
        r = d2.sqrt().to(device=dev, dtype=rdt)[ri, ci]
    return PSFRegions(peak=torch.stack([i0, j0], dim=-1), main=main, side=side, r=r)


def _flatten_kernel(name: str, kappa: Tensor) -> tuple[Tensor, torch.Size]:
    kappa = _check_tensor(name, kappa)
    _check_kernel_shape(name, kappa)
    lead = kappa.shape[:-2]
    return kappa.reshape((-1,) + tuple(kappa.shape[-2:])), lead


def psf_regions(kappa: Tensor, *, pitch: float | Sequence[float], wavelength: float,
                r_main: float = 1.5, r_guard: float = 2.5, distance: bool = True) -> PSFRegions:
    """Peak, distance map and regions of each kernel of ``kappa`` ``(..., H, W)``.

    ``r`` is the distance in metres from the pixel of the peak of ``|kappa|``
    (argmax, first in row-major order on ties; no gradient flows through it)
    using ``pitch`` (metres, one number or ``(rows, cols)``).
    ``Omega_main = {r <= r_main * wavelength}``,
    ``Omega_side = {r >= r_guard * wavelength}``, boundaries inclusive.
    Each batch item has its own regions since its peak can be anywhere.
    """
    flat, lead = _flatten_kernel("kappa", kappa)
    reg = _regions_flat(flat, pitch, wavelength, r_main, r_guard, distance)
    hw = tuple(flat.shape[-2:])
    return PSFRegions(peak=reg.peak.reshape(tuple(lead) + (2,)),
                      main=reg.main.reshape(tuple(lead) + hw),
                      side=reg.side.reshape(tuple(lead) + hw),
                      r=None if reg.r is None else reg.r.reshape(tuple(lead) + hw))


def check_regions(regions: PSFRegions) -> None:
    """Raise :class:`ParameterError` if some kernel has an empty side region.

    That happens when the window is too small for ``r_guard`` around the
    peak; :func:`psf_metrics` then returns 0 for the side-lobe terms of that
    kernel. (Synchronises with the device.)
    """
    empty = ~regions.side.flatten(-2).any(-1)
    if bool(empty.any()):
        raise ParameterError(
            f"the side region r >= r_guard is empty for {int(empty.sum())} kernel(s): "
            f"use a larger window or a smaller r_guard")


# --------------------------------------------------------------------------
# PSF metrics
# --------------------------------------------------------------------------


def _parse_terms(terms: Iterable[str] | None, have_ref: bool) -> tuple[str, ...]:
    if terms is None:
        return PSF_TERMS if have_ref else tuple(t for t in PSF_TERMS if t not in ("L_PSF", "Mean"))
    if isinstance(terms, str):
        terms = (terms,)
    out = []
    for t in terms:
        if t not in PSF_TERMS:
            raise ParameterError(f"unknown PSF metric {t!r}; choose among {list(PSF_TERMS)}")
        if t in ("L_PSF", "Mean") and not have_ref:
            raise ParameterError(f"metric {t!r} needs kappa_ref")
        if t not in out:
            out.append(t)
    return tuple(out)


def _compiled_applies(flat: Tensor, ref: Tensor | None, compiled: bool | None) -> bool:
    """Whether :func:`psf_metrics` takes the compiled pass
    (:mod:`arraysel.objective.metric_kernels`): kernels on the CPU, no gradient wanted, and
    (with ``L_PSF``) one reference kernel of no higher precision. ``compiled=False``: never;
    ``None``: whenever it applies to a batch of at least
    :data:`~arraysel.physics.compiled.MIN_BATCH` kernels."""
    if compiled is False or (compiled is None and flat.shape[0] < physics_compiled.MIN_BATCH):
        return False
    if flat.device.type != "cpu" or flat.shape[0] == 0 or flat.dtype.to_real() not in (torch.float32, torch.float64):
        return False
    if torch.is_grad_enabled() and (flat.requires_grad or (ref is not None and ref.requires_grad)):
        return False
    if ref is None:
        return True
    if ref.device.type != "cpu" or ref.numel() != flat.shape[-2] * flat.shape[-1]:
        return False
    return torch.promote_types(flat.dtype, ref.dtype).to_real() == flat.dtype.to_real()


def _compiled_terms(flat: Tensor, ref: Tensor | None, pitch, wavelength, r_main, r_guard,
                    q: float) -> dict[str, Tensor]:
    """L_PSF (with a reference) and the lobe terms of the kernels ``flat`` (B, H, W), real or
    complex, by the compiled pass, as (B,) tensors in the kernels' real dtype. A real kernel
    is read as complex with a zero imaginary part: the same ``|kappa|^2`` to the bit."""
    from arraysel.objective.metric_kernels import psf_metrics_compiled

    b, h, w = flat.shape
    pr, pc, rm, rg = _region_radii(pitch, wavelength, r_main, r_guard)
    _, main, side = _offset_tables(h, w, pr, pc, rm, rg)
    cdt = flat.dtype if flat.is_complex() else flat.dtype.to_complex()
    if ref is None:
        rv, rr = torch.zeros(h * w, 2, dtype=flat.dtype.to_real()), 0.0
    else:
        r = ref.detach().reshape(h, w).to(cdt)
        r = _divide_by_scale(r, _detached_scale(r))
        rv = torch.view_as_real(r.resolve_conj()).reshape(h * w, 2)
        rr = float((rv.double() ** 2).sum())
    kv = torch.view_as_real(flat.detach().to(cdt).resolve_conj()).reshape(b, h * w, 2)
    vals = psf_metrics_compiled(kv.numpy(), rv.contiguous().numpy(), rr, (h, w), main.numpy(), side.numpy(), q)
    vals = torch.from_numpy(vals).to(flat.dtype.to_real())
    names = ("L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i")
    return {n: vals[:, i] for i, n in enumerate(names) if ref is not None or n != "L_PSF"}


def _checked_reference(kappa: Tensor, kappa_ref) -> Tensor:
    """``kappa_ref`` checked: a real or complex tensor ``(..., H, W)`` that broadcasts to ``kappa``."""
    ref = _check_tensor("kappa_ref", kappa_ref)
    _check_kernel_shape("kappa_ref", ref)
    try:
        shape = _broadcast_shapes(kappa.shape, ref.shape)
    except RuntimeError:
        shape = None
    if shape != kappa.shape:
        raise ParameterError(f"kappa_ref of shape {tuple(ref.shape)} must broadcast to kappa's "
                             f"shape {tuple(kappa.shape)}")
    return ref


def _lobe_terms(flat: Tensor, lobe_terms: set, pitch, wavelength, r_main, r_guard, q: float) -> dict[str, Tensor]:
    """The lobe terms ``lobe_terms`` (among ``L_contrast``, ``L_SLR_q``, ``L_SLR_i``) of kernels
    ``flat`` (B, H, W), each ``(B,)``, by torch operations (differentiable)."""
    res: dict[str, Tensor] = {}
    b, h, w = flat.shape
    # k2 = |kappa|^2 up to a per-kernel constant, so m^2 = k2 / max(k2);
    # max(k2) cancels in every ratio below and is never divided out.
    k2 = _scaled_abs2(flat)                                          # (B, N)
    flat_peak = _peak_index(k2)
    # kernels cut around their peak share one peak pixel (and so one pair of regions):
    # then the masks are (1, N) and broadcast, instead of gathered per kernel
    shared = b > 1 and bool((flat_peak == flat_peak[0]).all())
    rows = 1 if shared else b
    reg = _regions_flat(flat[:rows], pitch, wavelength, r_main, r_guard, distance=False,
                        flat_peak=flat_peak[:rows], mask_dtype=k2.dtype)
    main = reg.main.reshape(rows, h * w)                             # 0/1 floats
    side = reg.side.reshape(rows, h * w)
    if {"L_contrast", "L_SLR_i"} & lobe_terms:
        s_main = _rowdot(k2, main)
        s_side = _rowdot(k2, side)
        if "L_SLR_i" in lobe_terms:
            res["L_SLR_i"] = _safe_div(s_side, s_main)
        if "L_contrast" in lobe_terms:
            res["L_contrast"] = _safe_div(_safe_div(s_side, side.sum(-1)),
                                          _safe_div(s_main, main.sum(-1)))
    if "L_SLR_q" in lobe_terms:
        # quantile of m = sqrt(k2 / max k2): sqrt is increasing, so rank k2.
        # The peak is the global maximum and lies in the main lobe (r = 0), so
        # max(m over main) is m at the peak.
        main_max = _safe_sqrt(k2.gather(-1, flat_peak[:, None]).squeeze(-1))
        q_side = _masked_quantile(k2, side.expand(b, -1), q, transform=_safe_sqrt)
        res["L_SLR_q"] = _safe_div(q_side, main_max)
    return res


def psf_metrics(kappa: Tensor, *, pitch: float | Sequence[float], wavelength: float,
                kappa_ref: Tensor | None = None, r_main: float = 1.5, r_guard: float = 2.5,
                quantile: float = 0.99, terms: Iterable[str] | None = None,
                compiled: bool | None = None) -> dict[str, Tensor]:
    """PSF quality metrics of Table 1 of the paper (``docs/metrics.md``); lower is better.

    Parameters
    ----------
    kappa : Tensor ``(..., H, W)`` (typically ``(B, H, W)`` or ``(H, W)``)
        PSF kernels, real or complex.
    pitch : float or (float, float)
        pixel pitch in metres (rows, columns).
    wavelength : float
        lambda0 = c / fc in metres; ``r_main`` and ``r_guard`` are multiples of it.
    kappa_ref : Tensor, optional
        reference kernel(s) broadcastable to ``kappa``; needed for
        ``L_PSF`` and ``Mean``.
    r_main, r_guard : float
        radii of ``Omega_main = {r <= r_main}`` and ``Omega_side = {r >= r_guard}``,
        in wavelengths.
    quantile : float
        q of ``L_SLR_q`` (linear interpolation, like ``torch.quantile``).
    terms : iterable of str, optional
        subset of :data:`PSF_TERMS` to compute (default: all that the inputs
        allow, i.e. without ``L_PSF``/``Mean`` when no ``kappa_ref``).
    compiled : bool, optional
        kernels on the CPU that need no gradient are scored by one compiled pass per kernel
        (:mod:`arraysel.objective.metric_kernels`: the same values to float rounding, several
        times faster); ``False`` keeps the torch operations, ``None`` (default) takes the
        compiled pass wherever it applies to a batch of at least
        :data:`arraysel.physics.compiled.MIN_BATCH` kernels, ``True`` to any batch.

    Returns
    -------
    dict mapping each requested name to a real tensor of shape ``kappa.shape[:-2]``
    (0-dim for a single ``(H, W)`` kernel):

    * ``L_PSF``: :func:`si_mse` ``(kappa, kappa_ref)``
    * ``L_contrast``: mean(m^2 over side) / mean(m^2 over main)
    * ``L_SLR_q``: quantile_q(m over side) / max(m over main)
    * ``L_SLR_i``: sum(m^2 over side) / sum(m^2 over main)
    * ``L_SLR``: (L_SLR_q + L_SLR_i) / 2
    * ``Mean``: (L_PSF + L_contrast + L_SLR_q + L_SLR_i) / 4

    with ``m = |kappa| / max|kappa|``. A kernel whose side region is empty
    gets 0 for the side terms; a zero kernel gets 0 for the ratios (see
    :func:`check_regions`, :func:`check_kernels`).
    """
    flat, lead = _flatten_kernel("kappa", kappa)
    q = check_number("quantile", quantile, lo=0, hi=1)
    want = _parse_terms(terms, kappa_ref is not None)
    need = set(want)
    if "L_SLR" in need:
        need |= {"L_SLR_q", "L_SLR_i"}
    if "Mean" in need:
        need |= {"L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i"}

    out: dict[str, Tensor] = {}
    ref = None
    if "L_PSF" in need:
        ref = _checked_reference(kappa, kappa_ref)
    if _compiled_applies(flat, ref, compiled):
        vals = _compiled_terms(flat, ref, pitch, wavelength, r_main, r_guard, q)
        out.update({name: v.reshape(lead) for name, v in vals.items() if name in need})
    elif ref is not None:
        out["L_PSF"] = si_mse(kappa, ref).reshape(lead)

    lobe_terms = (need - set(out)) & {"L_contrast", "L_SLR_q", "L_SLR_i"}
    if lobe_terms:
        out.update({k: v.reshape(lead) for k, v in _lobe_terms(flat, lobe_terms, pitch, wavelength, r_main,
                                                                  r_guard, q).items()})

    if "L_SLR" in need:
        out["L_SLR"] = 0.5 * (out["L_SLR_q"] + out["L_SLR_i"])
    if "Mean" in need:
        out["Mean"] = 0.25 * (out["L_PSF"] + out["L_contrast"] + out["L_SLR_q"] + out["L_SLR_i"])
    return {t: out[t] for t in want}


# --------------------------------------------------------------------------
# circular convolution (the imaging model of the data terms)
# --------------------------------------------------------------------------

def circular_convolve(kappa: Tensor, image: Tensor) -> Tensor:
    """Circular 2-D convolution ``Y = IFFT2(FFT2(kappa0) * FFT2(image))``.

    ``kappa`` ``(..., h, w)`` with ``h <= H``, ``w <= W`` and ``image``
    ``(..., H, W)``; leading dimensions broadcast. Centring convention: the
    kernel pixel ``(h // 2, w // 2)`` (``(64, 64)`` for a 128 x 128 window,
    where the kernel convention puts the peak) is the zero shift. ``kappa0`` is ``kappa``
    zero-padded to ``(H, W)`` and rolled so that pixel goes to ``(0, 0)``
    (for ``h = H``, ``w = W`` this is ``ifftshift``). Hence a delta kernel
    at its centre returns ``image`` unchanged, and
    ``Y[i, j] = sum_{a,b} kappa[a, b] image[(i - a + h//2) % H, (j - b + w//2) % W]``.
    The result is real when both inputs are real, complex otherwise.
    """
    image = _check_tensor("image", image)
    _check_kernel_shape("image", image)
    H, W = image.shape[-2:]
    k0 = _centred_kernel(kappa, (H, W))
    if not kappa.is_complex() and not image.is_complex():
        k0, image = _promote(k0, image)
        return torch.fft.irfft2(torch.fft.rfft2(k0) * torch.fft.rfft2(image), s=(H, W))
    return torch.fft.ifft2(torch.fft.fft2(k0) * torch.fft.fft2(image))


def _centred_kernel(kappa: Tensor, grid: tuple[int, int]) -> Tensor:
    """``kappa0``: ``kappa`` zero-padded to ``grid = (H, W)`` and rolled so that its pixel
    ``(h // 2, w // 2)`` is at ``(0, 0)`` (the convention of :func:`circular_convolve`)."""
    kappa = _check_tensor("kappa", kappa)
    _check_kernel_shape("kappa", kappa)
    h, w = kappa.shape[-2:]
    H, W = grid
    if h > H or w > W:
        raise ParameterError(f"kernel window {h}x{w} is larger than the image {H}x{W}")
    k0 = torch.nn.functional.pad(kappa, (0, W - w, 0, H - h)) if (h, w) != (H, W) else kappa
    return torch.roll(k0, shifts=(-(h // 2), -(w // 2)), dims=(-2, -1))


def kernel_spectrum(kappa: Tensor, grid: tuple[int, int]) -> Tensor:
    """``FFT2(kappa0)`` on a ``grid = (H, W)``: the transfer function of
    :func:`circular_convolve`, so ``circular_convolve(kappa, x) == IFFT2(kernel_spectrum(kappa,
    x.shape[-2:]) * FFT2(x))`` (for complex inputs). Operators that apply one kernel many times
    (``arraysel.e2e.recon.ConvolutionOperator``) keep it."""
    return torch.fft.fft2(_centred_kernel(kappa, grid))
