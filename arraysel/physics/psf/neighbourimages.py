"""The images of a selection's neighbours from the pair images' rows, for
:class:`~arraysel.physics.psf.basis.PairBasis` (whose methods of the same names call these):
the index of every pair (:func:`pair_lookup`), the pair-image rows on E kept from one
neighbourhood to the next while they fit the memory cap (:func:`pair_rows`,
:func:`fill_pair_rows`, :func:`all_rows`), and a neighbour's image as its selection's corrected
by a few of those rows (:func:`swap_images`).

Each function takes the basis first and reads its tensors and limits; the rows and the lookup it
keeps are the basis's (``basis._swap_rows``, ``basis._pair_lookup``), dropped with it. The
selection's base is :mod:`~arraysel.physics.psf.swapbase`'s.
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = ["all_rows", "fill_pair_rows", "move_terms", "moved_rows", "pair_lookup", "pair_rows", "row_store",
           "swap_images"]


def pair_lookup(basis) -> torch.Tensor:
    """(Ne, Ne) long: the index of pair (e, j) (either order) among :attr:`PairBasis.pairs_e`,
    :attr:`PairBasis.pairs_j`."""
    look = basis.__dict__.get("_pair_lookup")
    if look is None:
        ne = basis.model.n_elements
        look = torch.empty(ne, ne, dtype=torch.long)
        idx = torch.arange(basis.pairs_e.numel())
        look[basis.pairs_e.cpu(), basis.pairs_j.cpu()] = idx
        look[basis.pairs_j.cpu(), basis.pairs_e.cpu()] = idx
        basis._pair_lookup = look
    return look


def row_store(basis):
    """``(H, have)``: the kept pair-image rows on E and which of them are formed, made empty on
    first use; ``None`` when all P rows do not fit :meth:`PairBasis.swap_rows_cap` (or ``V`` holds the
    rows itself)."""
    if basis.U is None:
        return None
    store = basis.__dict__.get("_swap_rows")
    if store is None and basis.bytes_of_pair_rows() <= basis.swap_rows_cap():
        store = basis._swap_rows = (torch.empty(basis.pairs_e.numel(), basis.V.shape[1], dtype=basis.V.dtype,
                                               device=basis.V.device),
                                   torch.zeros(basis.pairs_e.numel(), dtype=torch.bool))
    return store


def pair_rows(basis, pairs: torch.Tensor) -> torch.Tensor:
    """(n, 2 Npix) pair images on E ([re | im]) of the pairs ``pairs`` (long (n,)): rows of
    ``U V`` (of ``V`` without compression). Rows formed once are kept while all P of them fit
    :meth:`PairBasis.swap_rows_cap`: a search's next neighbourhood needs mostly the same rows."""
    if basis.U is None:
        return basis.V[pairs.to(basis.V.device)]
    store = row_store(basis)
    if store is None:
        return basis.U[pairs.to(basis.U.device)] @ basis.V
    H, have = store
    pairs = pairs.cpu()
    need = torch.unique(pairs[~have[pairs]])
    if need.numel():
        H[need.to(H.device)] = basis.U[need.to(basis.U.device)] @ basis.V
        have[need] = True
    return H[pairs.to(H.device)]


def fill_pair_rows(basis, block: int = 256) -> bool:
    """Form now every pair-image row :func:`pair_rows` keeps (``block`` rows a product), so that
    a search's neighbourhoods (:func:`swap_images`) gather rows instead of forming them: the
    one-off work of a swap search (a few seconds, :meth:`PairBasis.bytes_of_pair_rows` of memory), done
    before its budget starts. Returns whether all rows are kept (False: they do not fit
    :meth:`PairBasis.swap_rows_cap`, and each neighbourhood forms the rows it needs)."""
    if basis.U is None:
        return True
    store = row_store(basis)
    if store is None:
        return False
    H, have = store
    todo = torch.nonzero(~have).flatten()
    for i in range(0, todo.numel(), block):
        idx = todo[i:i + block]
        H.index_copy_(0, idx.to(H.device), basis.U[idx.to(basis.U.device)] @ basis.V)
        have[idx] = True
    return True


def all_rows(basis):
    """Every pair-image row on E as one numpy array (P, 2 Npix), on the CPU, when they are all
    at hand (kept by :func:`fill_pair_rows`, or ``V`` itself without compression); else None.
    (numpy's gathers and float32 -> float64 sums of rows run several times faster than
    torch's on one thread.)"""
    if basis.V.device.type != "cpu":
        return None
    if basis.U is None:
        return basis.V.numpy()
    store = basis.__dict__.get("_swap_rows")
    if store is None or not bool(store[1].all()):
        return None
    return store[0].numpy()


def move_terms(basis, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(pidx, sign)``, (B, 2 m^2) each: the pair-image rows (indices into :attr:`PairBasis.pairs_e`)
    that the moves ``a[i]`` off, ``b[i]`` on ((B, m) each, ``-1`` for none) add to an image
    besides the element rows ``G``: the pairs within ``b`` (diagonal included) and within
    ``a`` (sign 1), and the pairs between them (sign -1); sign 0 where a pair names a
    padding entry."""
    m = a.shape[1]
    ln = pair_lookup(basis).numpy()
    pairs = [(1.0, b[:, i], b[:, j]) for i in range(m) for j in range(i, m)]
    pairs += [(1.0, a[:, i], a[:, j]) for i in range(m) for j in range(i + 1, m)]
    pairs += [(-1.0, a[:, i], b[:, j]) for i in range(m) for j in range(m)]
    if not pairs:  # moves of none
        return np.zeros((a.shape[0], 0), dtype=np.int64), np.zeros((a.shape[0], 0))
    return (np.stack([ln[np.maximum(p, 0), np.maximum(q, 0)] for _, p, q in pairs], axis=1),
            np.stack([s * ((p >= 0) & (q >= 0)) for s, p, q in pairs], axis=1))


def moved_rows(basis, mask: torch.Tensor, a: np.ndarray, b: np.ndarray, bases=None) -> torch.Tensor:
    """(B, 2 Npix) images on E ([re | im], :attr:`PairBasis.V`'s dtype) of the neighbours of ``mask``
    that switch ``a[i]`` off and ``b[i]`` on ((B, m) each, ``-1`` for none), from its image,
    its element rows and the pair-image rows (:func:`swap_images`)."""
    y, G = basis.swap_base(mask, bases)
    m = a.shape[1]
    pidx, sign = move_terms(basis, a, b)
    H = all_rows(basis)
    if H is not None:  # compiled: one pass over the kept rows
        from arraysel.physics.pairkernels import move_rows

        return torch.from_numpy(move_rows(H, y.numpy()[0], G.numpy(), a, b, pidx, sign))
    dev = G.device
    Gz = torch.cat([G, torch.zeros_like(G[:1])])      # row Ne: the padding entries' (zero)
    at, bt = (torch.from_numpy(np.where(v >= 0, v, G.shape[0])).to(dev) for v in (a, b))
    yb = y.expand(a.shape[0], -1).clone()
    for i in range(m):
        yb.sub_(Gz[at[:, i]]).add_(Gz[bt[:, i]])
    for t in range(pidx.shape[1]):
        rows = pair_rows(basis, torch.from_numpy(pidx[:, t]))
        if (sign[:, t] == sign[0, t]).all():                # no padding in this term: one sign
            yb.add_(rows, alpha=float(sign[0, t]))
        else:
            yb.add_(rows.to(yb.dtype) * torch.from_numpy(sign[:, t]).to(dev, yb.dtype)[:, None])
    return yb.to(basis.V.dtype)


def swap_images(basis, mask: torch.Tensor, out: torch.Tensor, into: torch.Tensor, w: torch.Tensor, bases=None):
    """:meth:`PairBasis.images` ``(w, with_error=True)`` of the neighbours ``w`` (B, Ne) of the 0/1
    selection ``mask`` (Ne,) that switch the elements ``out[b]`` off and ``into[b]`` on (int
    (B,): one-swap neighbours, or (B, m): m elements each, ``-1`` for none). The image is bilinear in the
    selection: with ``G_e = sum_{j in mask} H_ej`` the image rows of element e (``H`` the pair
    images, :func:`pair_rows`; ``G`` and the image from :meth:`PairBasis.swap_base`, in float64), a
    neighbour's image on E is the selection's, less ``G_a`` of each ``a`` in ``out[b]``, plus
    ``G_c`` of each ``c`` in ``into[b]``, plus ``H_cc'`` of each pair ``c <= c'`` of ``into[b]``
    and ``H_aa'`` of each pair ``a < a'`` of ``out[b]``, less ``H_ac`` of every ``a``, ``c``
    (for one swap: ``y - G_a + G_c + H_cc - H_ac``): 2 m (m + 1) sums of rows where
    :meth:`PairBasis.images` forms the product ``(c U) V`` of every neighbour (which it still forms
    while those rows cost more: :attr:`PairBasis.move_row_cost`). The error bounds are :meth:`PairBasis.images`'
    own (from ``c U``). ``bases``: the kept bases :meth:`PairBasis.swap_base` takes the selection's from
    (None: formed afresh). No gradient."""
    with torch.no_grad():
        c = basis._pairs(w)
        cu = c @ basis.U if basis.U is not None else None
        eps, win_err = basis._image_errors(c, cu)
        a, b = (v.cpu().reshape(-1, 1) if v.ndim < 2 else v.cpu() for v in (out, into))
        a, b = a.numpy(), b.numpy()
        a, b = -np.sort(-a, axis=1), -np.sort(-b, axis=1)   # each row's elements first, then -1
        count = (a >= 0).sum(1)
        # many rows a neighbour: the product of its coefficients costs less
        wide = torch.from_numpy(2 * count * (count + 1) * basis.move_row_cost > cu.shape[1]) if cu is not None \
            else torch.zeros(a.shape[0], dtype=torch.bool)
        if bool(wide.all()):
            yb = cu @ basis.V
        elif not bool(wide.any()):
            yb = moved_rows(basis, mask, a, b, bases)
        else:
            narrow = ~wide.numpy()
            width = max(1, int(count[narrow].max()))
            yb = torch.empty(a.shape[0], basis.V.shape[1], dtype=basis.V.dtype)
            yb[~wide] = moved_rows(basis, mask, a[narrow, :width], b[narrow, :width], bases)
            yb[wide] = (cu[wide.to(cu.device)] @ basis.V).to(yb.device)
        img = torch.complex(yb[:, : basis.npix], yb[:, basis.npix:]).reshape(w.shape[0], *basis.shape)
    return img, eps, win_err
