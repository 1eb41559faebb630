"""Peak certificates of the fast path: envelopes of a selection's I/Q channels and the bounds
of ``|I|`` on the grid blocks outside E (tier 1) or outside the band (tier 2).

For transmit n and receive element e the I/Q channel of a selection is
``X_ne(t) = m_e sum_j m_j A_nej(t)`` (A: the pair I/Q signals, ``pair_channels``). Linear
interpolation and unit phase rotations cannot exceed the larger neighbouring sample, so on a
block Q of pixels ``|I(p)| <= sum_{n,e} max_{t in [lo, hi]_neQ} |X_ne(t)|``, where ``[lo, hi]``
spans the samples the block's pixels read. The maxima come from aligned segments of
``segment`` samples: ``[lo, hi]`` lies inside segments ``lo // segment .. hi // segment``, and
the envelope of every run of 1 .. ``max_run`` consecutive segments is formed once per batch
(:meth:`Certificates.envelopes`), so one sparse product sums the right run for every (block,
transmit, element).

:class:`Certificates` is a part of :class:`~arraysel.physics.psf.basis.PairBasis`.
"""
from __future__ import annotations

import warnings

import numpy as np
import torch


def sparse_csr(crow, col, val, size):
    """A CSR tensor (checked), without torch's beta warning for sparse CSR."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        return torch.sparse_csr_tensor(crow, col, val, size=size, check_invariants=True)


class Certificates:
    """Block bounds of :class:`~arraysel.physics.psf.basis.PairBasis` (see the module)."""

    #: samples per aligned envelope segment of the certificates
    segment = 4

    def _build_certificates(self, X: np.ndarray, lo: torch.Tensor, hi: torch.Tensor):
        model = self.model
        ne = model.n_elements
        T = self.window_samples
        # A[j, (n, e, r, a)] = I/Q sample t = a segment + r of (rx e, tx j): the channel of receive e on
        # transmit n is m_e sum_j m_j A[j, (n, e, :, :)]; samples are stored segment-offset major
        # so that the envelopes reduce over contiguous slabs (:meth:`envelopes`)
        ntx = X.shape[0]

        def part(k):  # X's real (0) or imaginary (1) part as (j, (n, e, r, a))
            A = torch.from_numpy(X[:, :, :, k, :]).permute(3, 0, 1, 2)  # (j, n, e, T)
            return A.reshape(ne, ntx, ne, T // self.segment, self.segment).transpose(-1, -2).reshape(ne, -1)

        self.pair_channels = torch.cat([part(0), part(1)], dim=1).to(model.device, model.dtype)
        off = self.window_offset[:, None, None, :]
        read = hi >= lo
        lo = torch.where(read, lo - off, torch.full_like(lo, T))
        hi = torch.where(read, (hi - off).clamp(max=T - 1), torch.full_like(hi, -1))
        outside1, outside2 = self._outside_blocks()
        has_all = hi >= lo
        runs = torch.where(has_all, hi // self.segment - lo // self.segment + 1, torch.zeros_like(lo))
        #: longest run of consecutive segments a block reads
        self.max_run = max(1, int(runs.max()))
        self.block_envelopes_e = self._block_matrix(lo, hi, outside1)
        self.block_envelopes_band = self._block_matrix(lo, hi, outside2) if self.strips else \
            sparse_csr(torch.zeros(1, dtype=torch.long), torch.zeros(0, dtype=torch.long),
                 torch.zeros(0, dtype=model.dtype), (0, self.block_envelopes_e.shape[1])).to(model.device)

    def _outside_blocks(self):
        """(nbz, nbx) bool masks of the blocks not inside E (tier 1) and not inside the band (tier 2)."""
        s = self.model.setup
        b = self.model.block
        bz = torch.arange(-(-s.n_z // b))
        bx = torch.arange(-(-s.n_x // b))
        in_rows = (bz * b >= self.rows.start) & ((bz + 1) * b <= self.rows.stop)
        in_cols = (bx * b >= self.cols.start) & ((bx + 1) * b <= self.cols.stop)
        outside1 = ~(in_rows[:, None] & in_cols[None, :])
        outside2 = ~(in_rows[:, None] & torch.ones(bx.numel(), dtype=torch.bool)[None, :])
        return outside1, outside2

    def _block_matrix(self, lo, hi, outside):
        """Sparse (nQ, ntx*Ne*M*nS) matrix summing, per block, the envelope of the run of
        segments that holds the block's samples (layout of :meth:`envelopes`)."""
        model = self.model
        ntx, _, _, ne = lo.shape
        M, nS, sg = self.max_run, self.window_samples // self.segment, self.segment
        qz, qx = torch.nonzero(outside, as_tuple=True)
        nq = qz.numel()
        lo_q = lo[:, qz, qx]
        hi_q = hi[:, qz, qx]
        has = hi_q >= lo_q
        first = (lo_q // sg).clamp(0, nS - 1)
        run = (hi_q // sg - lo_q // sg).clamp(0, M - 1)
        n_ar = torch.arange(ntx)[:, None, None]
        e_ar = torch.arange(ne)[None, None, :]
        col = ((n_ar * ne + e_ar) * M + run) * nS + first
        q_ar = torch.arange(nq)[None, :, None].expand_as(col)
        rows_i = q_ar[has]
        cols_i = col[has]
        width = ntx * ne * M * nS
        order = torch.argsort(rows_i * width + cols_i)
        rows_i, cols_i = rows_i[order], cols_i[order]
        crow = torch.zeros(nq + 1, dtype=torch.long)
        crow[1:] = torch.cumsum(torch.bincount(rows_i, minlength=nq), 0)
        vals = torch.full((rows_i.numel(),), 1.0 + 1e-4, dtype=model.dtype)  # rounding safety margin
        return sparse_csr(crow, cols_i, vals, (nq, width)).to(model.device)

    #: fewest (transmit, element) channels per step of :meth:`envelopes`
    env_group = 8
    #: bytes of one step's channel products in :meth:`envelopes` (kept in cache): 8 channels a
    #: step for a batch of 128 masks, every channel at once for one mask (a gradient step),
    #: where a step's fixed cost would otherwise dominate
    env_step_bytes = 1 << 20

    def envelopes(self, w: torch.Tensor) -> torch.Tensor:
        """Segment envelopes (ntx * Ne * M * nS, B) of the channels of selections w.

        Entry (n, e, m, a): ``max |X_ne(t)|`` over segments ``a .. a + m`` (``segment`` samples
        each; zeros past the end). The channel sums are formed :attr:`env_group` channels at a
        time and reduced to segment maxima at once, so they never reach main memory; then
        M - 1 running maxima on the segment array (``segment`` times smaller than the channels).
        """
        ne = self.model.n_elements
        ntx = len(self.model.transmits)
        B = w.shape[0]
        T = self.window_samples
        nS = T // self.segment
        nch = ntx * ne
        half = self.pair_channels.shape[1] // 2
        a_re, a_im = self.pair_channels[:, :half].T, self.pair_channels[:, half:].T
        wt = w.T.contiguous()
        seg = w.new_empty(nch, nS, B)
        group = max(self.env_group, self.env_step_bytes // (2 * T * B * w.element_size()))
        for g0 in range(0, nch, group):
            g1 = min(nch, g0 + group)
            yr = a_re[g0 * T: g1 * T] @ wt
            yi = a_im[g0 * T: g1 * T] @ wt
            sq = torch.addcmul(yi.square_(), yr, yr)
            torch.amax(sq.view(g1 - g0, self.segment, nS, B), dim=1, out=seg[g0:g1])
        seg.sqrt_()
        seg.view(ntx, ne, nS, B).mul_(w.abs().T[None, :, None, :])
        env = seg.new_empty(nch, self.max_run, nS, B)
        env[:, 0] = seg
        for m in range(1, self.max_run):
            env[:, m, nS - m:] = env[:, m - 1, nS - m:]
            torch.maximum(env[:, m - 1, : nS - m], seg[:, m:], out=env[:, m, : nS - m])
        return env.view(-1, B)

    def bound(self, w: torch.Tensor, tier: int = 1, per_block: bool = False, env=None) -> torch.Tensor:
        """(B,) upper bound of |I| on the blocks outside E (tier 1) or outside the band (tier 2);
        with ``per_block`` the (nQ, B) bounds of every block. ``env``: :meth:`envelopes` of w."""
        S = self.block_envelopes_e if tier == 1 else self.block_envelopes_band
        B = w.shape[0]
        if S.shape[0] == 0:
            return torch.zeros((0, B) if per_block else B, dtype=w.dtype, device=w.device)
        if env is None:
            env = self.envelopes(w)
        bounds = torch.sparse.mm(S, env)  # (nQ, B)
        return bounds if per_block else bounds.amax(dim=0)
