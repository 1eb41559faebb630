"""The pair basis's layout: the pixels each tier covers, the element pairs, the grid blocks each
certificate bounds, and the column order of the strips' pair images.

A :class:`BasisLayout` follows from the model's grid, window, ``margin`` and ``block`` alone (no
physics): :meth:`BasisLayout.of`. The regions (grid rows ``rows`` = the window plus a margin
around the scatterer):

* tier 1, ``E``: the columns ``cols`` of the window plus the margin (``shape``, ``npix`` pixels);
* tier 2, the *strips*: the remaining columns ``strip_cols`` of the same rows (``npix2``
  pixels), so that E and the strips make the full-width band ``rows x all columns``.

It is the first part of :class:`~arraysel.physics.psf.basis.PairBasis`, which reads every name
below as its own attribute.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

__all__ = ["BasisLayout", "pair_index", "LAYOUT_FIELDS"]


def pair_index(ne: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices (e, j) with e <= j of the Ne(Ne+1)/2 element pairs."""
    e, j = torch.triu_indices(ne, ne)
    return e, j


@dataclass(frozen=True)
class BasisLayout:
    """Where the basis's pixels, pairs and blocks are (see the module)."""

    #: grid rows of the band (E and the strips)
    rows: slice
    #: grid columns of E
    cols: slice
    #: (rows, columns) of E
    shape: tuple[int, int]
    #: pixels of E
    npix: int
    #: grid columns of the strips (all but E's), and their pixels (0 without strips)
    strip_cols: torch.Tensor
    npix2: int
    #: the element pairs (e <= j), :func:`pair_index`
    pairs_e: torch.Tensor
    pairs_j: torch.Tensor
    #: (nbz, nbx) bool: the grid blocks not inside E (tier 1) and not inside the band (tier 2)
    outside1: torch.Tensor
    outside2: torch.Tensor
    #: (nQ1, 2) the tier-1 blocks (rows of ``block_envelopes_e``) as (qz, qx); (nQ2, 2) tier 2's
    blocks1: torch.Tensor
    blocks2: torch.Tensor
    #: column order of ``strip_images``: old [re | im] column of each new column, its inverse, and
    #: (nQ1,) the first column of each tier-1 block wholly inside the strips (-1 elsewhere)
    h2_cols: torch.Tensor
    h2_inv: torch.Tensor
    strip_block_col: torch.Tensor
    #: row-major E-pixel indices of the core around the scatterer (:meth:`core_pixels`)
    core_pix: torch.Tensor
    #: whether tier 2 (the strips' pair images) is kept
    strips: bool = True

    @classmethod
    def of(cls, model, core: int = 16) -> "BasisLayout":
        """The layout of ``model``'s basis (its ``setup``, ``n_elements``, ``margin``, ``block``);
        ``core``: half side (pixels) of the core around the scatterer."""
        s = model.setup
        win, m = s.window, model.margin
        iz, ix = s.scatterer_pixel
        half = win // 2
        z_lo = max(0, min(iz - half - m, s.n_z - win - 2 * m))
        x_lo = max(0, min(ix - half - m, s.n_x - win - 2 * m))
        rows = slice(z_lo, min(s.n_z, z_lo + win + 2 * m))
        cols = slice(x_lo, min(s.n_x, x_lo + win + 2 * m))
        shape = (rows.stop - rows.start, cols.stop - cols.start)
        strip_cols = torch.cat([torch.arange(0, cols.start), torch.arange(cols.stop, s.n_x)])
        npix2 = shape[0] * strip_cols.numel()
        pairs_e, pairs_j = pair_index(model.n_elements)
        outside1, outside2 = _outside_blocks(s.n_z, s.n_x, model.block, rows, cols)
        blocks1 = torch.nonzero(outside1)
        h2_cols, strip_block_col = _strip_order(blocks1, model.block, s.n_x, rows, cols, strip_cols.numel(), npix2)
        return cls(rows=rows, cols=cols, shape=shape, npix=shape[0] * shape[1], strip_cols=strip_cols,
                   npix2=npix2, pairs_e=pairs_e, pairs_j=pairs_j, outside1=outside1, outside2=outside2,
                   blocks1=blocks1, blocks2=torch.nonzero(outside2), h2_cols=h2_cols,
                   h2_inv=torch.argsort(h2_cols), strip_block_col=strip_block_col,
                   core_pix=_core_pixels(s.scatterer_pixel, rows, cols, shape, core))

    def strip_bytes(self, item_bytes: int, strip_rank: int) -> int:
        """Memory of the strips' pair images and block factors at ``item_bytes`` a number."""
        nw = int((self.strip_block_col >= 0).sum())
        return item_bytes * self.pairs_e.numel() * (2 * self.npix2 + nw * strip_rank)

    def without_strips(self) -> "BasisLayout":
        """The layout without tier 2: loose blocks outside E are beamformed exactly."""
        empty = torch.zeros(0, dtype=torch.long)
        return dataclasses.replace(self, strips=False, npix2=0, strip_cols=empty, h2_cols=empty, h2_inv=empty,
                                   strip_block_col=torch.full_like(self.strip_block_col, -1))


#: the names :class:`~arraysel.physics.psf.basis.PairBasis` reads from its layout
LAYOUT_FIELDS = tuple(f.name for f in dataclasses.fields(BasisLayout))


def _outside_blocks(n_z: int, n_x: int, b: int, rows: slice, cols: slice):
    """(nbz, nbx) bool masks of the blocks not inside E (tier 1) and not inside the band (tier 2)."""
    bz = torch.arange(-(-n_z // b))
    bx = torch.arange(-(-n_x // b))
    in_rows = (bz * b >= rows.start) & ((bz + 1) * b <= rows.stop)
    in_cols = (bx * b >= cols.start) & ((bx + 1) * b <= cols.stop)
    outside1 = ~(in_rows[:, None] & in_cols[None, :])
    outside2 = ~(in_rows[:, None] & torch.ones(bx.numel(), dtype=torch.bool)[None, :])
    return outside1, outside2


def _strip_order(blocks1: torch.Tensor, b: int, n_x: int, rows: slice, cols: slice, nstrip: int, npix2: int):
    """Column order of ``strip_images`` (``H2``): block-major, so the pair images of one grid block
    of the strips are ``2 block^2`` adjacent columns ([re | im] of its pixels, row-major), followed
    by the pixels no whole block covers. Returns ``h2_cols`` (old [re | im] column of each new
    column) and ``strip_block_col`` (nQ1,): the first column of each tier-1 block in
    ``strip_images``, -1 where the block is not wholly inside the strips."""
    qz, qx = blocks1[:, 0], blocks1[:, 1]
    in_rows = (qz * b >= rows.start) & ((qz + 1) * b <= rows.stop)
    in_grid = (qx + 1) * b <= n_x
    in_strip = ((qx + 1) * b <= cols.start) | (qx * b >= cols.stop)
    whole = torch.nonzero(in_rows & in_grid & in_strip).flatten()
    ar = torch.arange(b)
    z = qz[whole, None, None] * b + ar[None, :, None] - rows.start  # (nW, b, 1)
    x = qx[whole, None, None] * b + ar[None, None, :]
    j = torch.where(x < cols.start, x, x - (cols.stop - cols.start))
    pix = (z * nstrip + j).reshape(whole.numel(), b * b)  # strip pixels of each whole block
    covered = torch.zeros(npix2, dtype=torch.bool)
    covered[pix.reshape(-1)] = True
    rest = torch.nonzero(~covered).flatten()
    h2_cols = torch.cat([torch.cat([pix, pix + npix2], dim=1).reshape(-1), rest, rest + npix2])
    strip_block_col = torch.full((blocks1.shape[0],), -1, dtype=torch.long)
    strip_block_col[whole] = torch.arange(whole.numel()) * 2 * b * b
    return h2_cols, strip_block_col


def _core_pixels(scatterer_pixel, rows: slice, cols: slice, shape: tuple[int, int], core: int) -> torch.Tensor:
    """Row-major E-pixel indices of the core: the (2 core) x (2 core) pixels of E centred on the
    scatterer, where the peak of a selection's image lies (their pair images, ``core_images``,
    settle near-ties at the peak without delay-and-sum)."""
    iz, ix = scatterer_pixel
    iz, ix = iz - rows.start, ix - cols.start
    h, w = shape
    zr = torch.arange(max(0, iz - core), min(h, iz + core))
    xr = torch.arange(max(0, ix - core), min(w, ix + core))
    return (zr[:, None] * w + xr[None, :]).reshape(-1)
