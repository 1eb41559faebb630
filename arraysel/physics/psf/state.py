"""The pair basis's stored state: the tensors a build leaves, their rigorous error constants, and
their serialisation to a dict of named tensors (what :mod:`arraysel.physics.psf.store` caches).

Stored tensors (model dtype unless noted): ``U``, ``V`` (the truncated SVD of the pair images on
E); ``strip_images`` (P, 2 Npix2) the strips' pair images in block-major column order;
``strip_left``, ``strip_right``, ``strip_sigma``, ``strip_sigma_next`` their per-block
rank-``strip_rank`` factors; ``core_images`` the core's exact pair images; ``pair_channels``
(Ne, Ne 2 ntx T) the windowed pair I/Q signals (receive element, real and imaginary part,
transmit, then samples segment-offset major); ``window_offset`` (ntx, Ne) the first record sample
of each channel's window of ``window_samples`` samples; ``max_run`` the longest run of segments
a block reads; ``block_envelopes_e`` / ``block_envelopes_band`` the certificates' sparse block
matrices; ``error`` the :class:`ErrorConstants`. The certificates' tensors (``pair_channels``,
``window_offset``, ``window_samples``, ``max_run``, ``segment`` and the block matrices) are read
from and restored to ``basis.certificates``; the others are the basis's own.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from arraysel.physics.psf.certificate import sparse_csr

__all__ = ["ErrorConstants", "DENSE", "CERTIFICATE_DENSE", "SPARSE", "basis_state", "restore_state"]


class ErrorConstants(NamedTuple):
    """The constants of a basis's rigorous error bounds (all >= 0)."""

    #: largest residual pixel-column norm of the truncated SVD on E, ``max_p |(I - U U^T) H_p|``
    pixel_residual: float
    #: largest pixel-column norm of the pair images on E
    column_e: float
    #: largest pixel-column norm of the strips' pair images
    column_strips: float
    #: bound of the spectral norm of ``(I - U U^T) H`` (the largest discarded singular value)
    spectral_tail: float


#: stored key -> attribute of the basis's dense tensors kept in the model's dtype (the keys are
#: the serialised format: keep them, or bump :data:`~arraysel.physics.psf.store.BASIS_VERSION`)
DENSE = {"V": "V", "H2": "strip_images", "Hc": "core_images", "SF": "strip_left",
         "SG": "strip_right", "SS": "strip_sigma"}
#: stored key -> attribute of the certificates' (``basis.certificates``) dense tensor in the
#: model's dtype
CERTIFICATE_DENSE = {"A": "pair_channels"}
#: stored key prefix -> attribute of the certificates' sparse block matrices
SPARSE = {"S1": "block_envelopes_e", "S2": "block_envelopes_band"}


def basis_state(basis) -> dict:
    """The stored tensors of ``basis`` and its certificates by name (see :data:`DENSE`,
    :data:`CERTIFICATE_DENSE` and :data:`SPARSE`), on the CPU."""
    cert = basis.certificates
    st = {key: getattr(basis, attr).cpu() for key, attr in DENSE.items()}
    st.update({key: getattr(cert, attr).cpu() for key, attr in CERTIFICATE_DENSE.items()})
    st.update({"err": torch.tensor(list(basis.error), dtype=torch.float64), "core_pix": basis.core_pix,
               "Snext": basis.strip_sigma_next.cpu(),
               "meta": torch.tensor([cert.window_samples, cert.max_run, basis.rank, cert.segment,
                                     int(basis.strips)]),
               "rank_tail": torch.tensor(basis.rank_tail), "off": cert.window_offset.cpu(),
               "row_energy": basis.row_energy, "missed": torch.tensor(basis.missed, dtype=torch.float64)})
    if basis.U is not None:
        st["U"] = basis.U.cpu()
    for key, attr in SPARSE.items():
        S = getattr(cert, attr)
        st[key + "_crow"], st[key + "_col"], st[key + "_val"] = (
            S.crow_indices().cpu(), S.col_indices().cpu(), S.values().cpu())
        st[key + "_shape"] = torch.tensor(list(S.shape))
    return st


def restore_state(basis, st: dict) -> None:
    """Set the stored tensors of ``st`` (:func:`basis_state`) on ``basis``, in its model's device
    and dtype, and its :class:`~arraysel.physics.psf.certificate.Certificates` made from theirs;
    its layout loses the strips when the stored basis had none."""
    import dataclasses

    from arraysel.physics.psf.certificate import Certificates

    dev, dt = basis.model.device, basis.model.dtype
    basis.U = st["U"].to(dev, dt) if "U" in st else None
    for key, attr in DENSE.items():
        setattr(basis, attr, st[key].to(dev, dt))
    basis.strip_sigma_next = st["Snext"].double().to(dev)
    window_samples, max_run, basis.rank, segment, strips = (int(v) for v in st["meta"])
    basis.row_energy = st["row_energy"].double()
    basis.layout = dataclasses.replace(basis.layout, core_pix=st["core_pix"].long())
    if not strips:
        basis.layout = basis.layout.without_strips()
    basis.rank_tail = float(st["rank_tail"])
    basis.missed = float(st["missed"])
    basis.error = ErrorConstants(*(float(v) for v in st["err"].double()))
    sparse = {}
    for key, attr in SPARSE.items():
        shape = tuple(int(v) for v in st[key + "_shape"])
        sparse[attr] = sparse_csr(st[key + "_crow"], st[key + "_col"], st[key + "_val"].to(dt), shape).to(dev)
    dense = {attr: st[key].to(dev, dt) for key, attr in CERTIFICATE_DENSE.items()}
    basis.certificates = Certificates(basis.model, window_offset=st["off"].long(), window_samples=window_samples,
                                      max_run=max_run, segment=segment, **dense, **sparse)
