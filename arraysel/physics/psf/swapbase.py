"""The neighbourhood bases of the swap searches: :class:`SwapBases`.

A neighbour of a selection (a swap, a segment shift, any move of a few elements) is scored from
the selection's *base*: its image on E ``y`` (1, 2 Npix) and its element rows
``G_e = sum_{j in mask} H_ej`` (Ne, 2 Npix), float64 (``H`` the pair images on E). The image is
bilinear in the selection, so a neighbour's image is ``y`` corrected by a few rows of ``G`` and
of ``H`` (:meth:`~arraysel.physics.psf.basis.PairBasis.swap_images`).

Forming a base afresh is one product with the basis (about 0.1 s on a 128-element scene);
moving it along with a search is a few row sums. :class:`SwapBases` keeps the bases of the
latest selections, so that descents taking turns (a search's race) each find their own. Its
limits are the basis's attributes ``swap_base_max_bytes``, ``swap_base_moved_max`` and
``swap_base_refresh`` (:class:`~arraysel.physics.psf.basis.PairBasis`).
"""
from __future__ import annotations

from collections import OrderedDict

import numpy as np
import torch

__all__ = ["SwapBases"]


class SwapBases:
    """The bases of the latest selections of one basis, the least recently used dropped first.

    ``kept`` maps a selection's key (its 0/1 mask's bytes) to ``(mask, y, G, moved)``: the mask
    (bool tensor), its base, and the elements moved by row updates since it was formed afresh.
    As many are kept as ``basis.swap_base_max_bytes`` holds (at most a quarter of the memory cap
    ``ARRAYSEL_MEMORY_GIB``), at least one.
    """

    def __init__(self):
        self.kept: OrderedDict = OrderedDict()

    def __len__(self) -> int:
        return len(self.kept)

    def latest(self) -> tuple:
        """The entry ``(mask, y, G, moved)`` of the selection asked for last."""
        return next(reversed(self.kept.values()))

    def base(self, basis, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(y, G)`` of the 0/1 selection ``mask`` on ``basis``: kept, carried by rows from the
        nearest kept base (:meth:`nearest`) when every pair row is at hand
        (``basis._all_rows()``: ``G -= H_.a`` for each element off, ``G += H_.b`` for each
        element on, ``y`` the neighbour's image), or formed afresh. The tensors returned are
        owned by the kept entry, which a later call may update in place."""
        m = (mask.cpu() != 0)
        key = m.numpy().tobytes()
        held = self.kept.get(key)
        if held is not None:
            self.kept.move_to_end(key)
            return held[1], held[2]
        H = basis._all_rows() if self.kept else None   # row updates need every pair row at hand
        near = self.nearest(basis, m) if H is not None else None
        if near is not None:
            old, gone, new = near
            _, y, G, moved = self.kept.pop(old)
            self._move(basis, H, y.numpy(), G.numpy(), gone, new)
            self.kept[key] = (m, y, G, moved + gone.size)
            return y, G
        y, G = self._form(basis, m)
        keep = self._room(basis, (G.numel() + y.numel()) * G.element_size())
        while len(self.kept) >= keep:
            self.kept.popitem(last=False)
        self.kept[key] = (m, y, G, 0)
        return y, G

    def nearest(self, basis, m: torch.Tensor):
        """``(key, gone, new)`` of the kept base nearest to the selection ``m`` that a move of at
        most ``basis.swap_base_moved_max`` elements reaches and whose row updates have not
        reached ``basis.swap_base_refresh`` elements (the most recently used first on ties), or
        None."""
        best = None
        for key, (prev, _, _, moved) in reversed(self.kept.items()):
            if moved >= basis.swap_base_refresh:
                continue
            gone, new = torch.nonzero(prev & ~m).flatten().numpy(), torch.nonzero(m & ~prev).flatten().numpy()
            if gone.size == new.size and 0 < gone.size <= basis.swap_base_moved_max \
                    and (best is None or gone.size < best[1].size):
                best = (key, gone, new)
        return best

    @staticmethod
    def _room(basis, entry_bytes: int) -> int:
        """How many bases of ``entry_bytes`` each may be kept."""
        from arraysel.physics.psf.settings import memory_limit_bytes

        cap = min(int(basis.swap_base_max_bytes), memory_limit_bytes() // 4)
        return max(1, cap // max(1, entry_bytes))

    @staticmethod
    def _move(basis, H: np.ndarray, y: np.ndarray, G: np.ndarray, gone: np.ndarray, new: np.ndarray) -> None:
        """Carry the base ``(y, G)`` in place by the move ``gone`` off, ``new`` on."""
        from arraysel.physics.pairkernels import move_rows

        ln = basis.pair_lookup().numpy()
        y[:] = move_rows(H, y[0], G, gone[None], new[None], *basis._move_terms(gone[None], new[None]),
                         dtype=np.float64)
        for a in gone:
            G -= np.take(H, ln[:, a], axis=0)
        for b in new:
            G += np.take(H, ln[:, b], axis=0)

    @staticmethod
    def _form(basis, m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The base of ``m`` formed afresh from the basis (``U``, ``V``), float64."""
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
