"""The neighbourhood bases a search keeps: :class:`SwapBases`.

A neighbour of a selection is scored from the selection's *base* (its image on E and its element
rows, :mod:`arraysel.physics.psf.swapbase`). Forming a base afresh is one product with the pair
basis (about 0.1 s on a 128-element scene); moving it along with a search is a few row sums.
:class:`SwapBases` keeps the bases of the latest selections, so that descents taking turns (a
search's race) each find their own: it is the search's state, kept by the objective (one for each
field point's basis) and handed to the physics kernels
(:meth:`~arraysel.physics.psf.basis.PairBasis.swap_base`). Its limits are the basis's attributes
``swap_base_max_bytes``, ``swap_base_moved_max`` and ``swap_base_refresh``
(:class:`~arraysel.physics.psf.basis.PairBasis`).
"""
from __future__ import annotations

from collections import OrderedDict

import torch

from arraysel.physics.psf.swapbase import form_base, move_base

__all__ = ["SwapBases"]


class SwapBases:
    """The bases of the latest selections of one basis, the least recently used dropped first.

    ``kept`` maps a selection's key (its 0/1 mask's bytes) to ``(mask, y, G, moved)``: the mask
    (bool tensor), its base, and the elements moved by row updates since it was formed afresh.
    As many are kept as ``basis.swap_base_max_bytes`` holds (at most a quarter of the memory cap
    ``ARRAYSEL_MEMORY_GIB``), at least one. Asked about another basis (a basis truncated to
    another rank), it drops what it kept.
    """

    def __init__(self):
        self.kept: OrderedDict = OrderedDict()
        self._basis = None

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
        if self._basis is not basis:
            self.kept.clear()
            self._basis = basis
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
            move_base(basis, H, y.numpy(), G.numpy(), gone, new)
            self.kept[key] = (m, y, G, moved + gone.size)
            return y, G
        y, G = form_base(basis, m)
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
