"""The kernels of a neighbourhood base: :func:`form_base` and :func:`move_base`.

A neighbour of a selection (a swap, a segment shift, any move of a few elements) is scored from
the selection's *base*: its image on E ``y`` (1, 2 Npix) and its element rows
``G_e = sum_{j in mask} H_ej`` (Ne, 2 Npix), float64 (``H`` the pair images on E). The image is
bilinear in the selection, so a neighbour's image is ``y`` corrected by a few rows of ``G`` and
of ``H`` (:meth:`~arraysel.physics.psf.basis.PairBasis.swap_images`).

Forming a base afresh is one product with the basis (about 0.1 s on a 128-element scene,
:func:`form_base`); moving it along with a search is a few row sums (:func:`move_base`). Which
bases a search keeps, and from which one a selection's base is carried, is the search's state: it
lives with the objective (:class:`arraysel.objective.swapbases.SwapBases`), which hands it to
:meth:`~arraysel.physics.psf.basis.PairBasis.swap_base`.
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = ["form_base", "move_base"]


def move_base(basis, H: np.ndarray, y: np.ndarray, G: np.ndarray, gone: np.ndarray, new: np.ndarray) -> None:
    """Carry the base ``(y, G)`` of a selection of ``basis`` in place by the move ``gone`` off,
    ``new`` on (element indices), ``H`` every pair-image row on E (``basis._all_rows()``)."""
    from arraysel.physics.peakkernels import move_rows

    ln = basis.pair_lookup().numpy()
    y[:] = move_rows(H, y[0], G, gone[None], new[None], *basis._move_terms(gone[None], new[None]),
                     dtype=np.float64)
    for a in gone:
        G -= np.take(H, ln[:, a], axis=0)
    for b in new:
        G += np.take(H, ln[:, b], axis=0)


def form_base(basis, m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The base ``(y, G)`` of the boolean selection ``m`` (Ne,) formed afresh from the basis
    (``U``, ``V``), float64."""
    look = basis.pair_lookup()
    on = torch.nonzero(m).flatten()
    dev = basis.V.device
    sel = look[:, on]                                                         # (Ne, k)
    if basis.U is not None:
        R = basis.U[sel.reshape(-1).to(dev)].double().view(*sel.shape, -1).sum(1)   # (Ne, rank)
        G = (R.to(basis.V.dtype) @ basis.V).double()
        y = (R[on.to(dev)].sum(0) + basis.U[look[on, on].to(dev)].double().sum(0)) / 2
        y = (y.to(basis.V.dtype) @ basis.V)[None].double()
    else:
        G = basis.V[sel.reshape(-1).to(dev)].double().view(*sel.shape, -1).sum(1)
        y = ((G[on.to(dev)].sum(0) + basis.V[look[on, on].to(dev)].double().sum(0)) / 2)[None]
    return y.contiguous(), G.contiguous()
