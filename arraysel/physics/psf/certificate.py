"""Peak certificates of the fast path: envelopes of a selection's I/Q channels and the bounds
of ``|I|`` on the grid blocks outside E (tier 1) or outside the band (tier 2).

For transmit n and receive element e the I/Q channel of a selection is
``X_ne(t) = m_e sum_j m_j A_nej(t)`` (A: the pair I/Q signals, ``pair_channels``, stored
receive-element major: an element whose weight is zero has no channel to form). Linear
interpolation and unit phase rotations cannot exceed the larger neighbouring sample, so on a
block Q of pixels ``|I(p)| <= sum_{n,e} max_{t in [lo, hi]_neQ} |X_ne(t)|``, where ``[lo, hi]``
spans the samples the block's pixels read. The maxima come from aligned segments of
``segment`` samples: ``[lo, hi]`` lies inside segments ``lo // segment .. hi // segment``, and
the envelope of every run of 1 .. ``max_run`` consecutive segments is formed once per batch
(:meth:`Certificates.envelopes`: a few selections in a loop sum each channel compiled from the
rows of A they use), so a block's bound sums one entry per (transmit, element): the right run
(:meth:`Certificates.bound`: compiled on the CPU, a sparse product elsewhere).

:class:`Certificates` is a part of :class:`~arraysel.physics.psf.basis.PairBasis`
(``basis.certificates``): it owns the pair I/Q signals on their windows, the block matrices and
the caches of the bounds, and reads only the model's public interface (its constructor's
arguments); the basis, its refinement and its stored state read the channels and bounds from it.
"""
from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np
import torch

from arraysel.physics import compiled
from arraysel.selection import flagged_elements


def largest_bound(bounds: torch.Tensor) -> torch.Tensor:
    """(B,) largest of per-block bounds (nQ, B) (:meth:`Certificates.bound`); zero without blocks."""
    return bounds.amax(dim=0) if bounds.shape[0] else bounds.new_zeros(bounds.shape[1])


def sparse_csr(crow, col, val, size):
    """A CSR tensor (checked), without torch's beta warning for sparse CSR."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        return torch.sparse_csr_tensor(crow, col, val, size=size, check_invariants=True)


def block_matrix(lo: torch.Tensor, hi: torch.Tensor, outside: torch.Tensor, max_run: int, window_samples: int,
                 segment: int, margin: float, dtype: torch.dtype, device) -> torch.Tensor:
    """Sparse (nQ, ntx*Ne*M*nS) matrix summing, per block of ``outside`` (nbz, nbx) bool, the
    envelope of the run of segments that holds the block's samples ``lo``, ``hi`` (ntx, nbz, nbx,
    Ne; local to the channel windows) (layout of :meth:`Certificates.envelopes`; ``M`` =
    ``max_run``, ``nS`` segments of ``segment`` samples), its entries ``margin``
    (:attr:`Certificates.bound_margin`)."""
    ntx, _, _, ne = lo.shape
    M, nS, sg = max_run, window_samples // segment, segment
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
    vals = torch.full((rows_i.numel(),), margin, dtype=dtype)
    return sparse_csr(crow, cols_i, vals, (nq, width)).to(device)


def compiled_envelopes(w: torch.Tensor) -> bool:
    """Whether :meth:`Certificates.envelopes` reduces the receive products to segment peaks and
    runs compiled (:func:`_envelopes_compiled`): on the CPU without gradient, for a batch of at
    least :data:`~arraysel.physics.compiled.MIN_BATCH` selections in float32 (the same values)."""
    return w.device.type == "cpu" and not w.requires_grad and w.shape[0] >= compiled.MIN_BATCH and \
        w.dtype == torch.float32


def _envelopes_compiled(cert: "Certificates", w: torch.Tensor, env: torch.Tensor) -> torch.Tensor:
    """:meth:`Certificates.envelopes` of ``w`` into ``env`` (nch, M, nS, B), returned as (nch M
    nS, B): each receive product read once
    (:func:`~arraysel.physics.peakkernels.product_peaks_into`) and one pass over the envelopes
    (:func:`~arraysel.physics.peakkernels.segment_runs`), where torch's square, maximum, root,
    product, transpose and running maxima take a dozen."""
    from arraysel.physics.peakkernels import product_peaks_into, segment_runs

    B = w.shape[0]
    env[:, 0].zero_()
    wn, en = np.ascontiguousarray(w.numpy()), env.numpy()
    every = np.arange(B)
    for e0, _, s, y in cert._receive_products(w):
        product_peaks_into(y.numpy(), every if s is None else s.numpy(), e0, wn, en)
    segment_runs(en)
    return env.view(-1, B)


class RawChannels(NamedTuple):
    """One selection's I/Q channels as the product with ``pair_channels`` leaves them (CPU, no
    gradient): ``y`` (Ne, 2, ntx, T) [re, im] with each channel's samples in segment-offset-major
    order (``segment`` samples a segment: sample ``a segment + r`` at ``r nS + a``; 1: time
    order), not yet weighted by the receive element's weight ``we`` (Ne,). The channels of the
    receive elements whose weight is zero are not formed (their values are undefined; nothing
    reads them). The compiled delay-and-sum reads them as they are
    (``pairkernels.das_stacked_raw``): forming the complex, time-ordered, weighted channels of
    :meth:`~arraysel.physics.psf.basis.PairBasis.channels` costs as much as the product."""

    y: np.ndarray
    we: np.ndarray
    segment: int


class Certificates:
    """The peak certificates of a :class:`~arraysel.physics.psf.basis.PairBasis` (see the module):
    ``basis.certificates``.

    Inputs (constructor): ``model`` (reads ``n_elements``, ``transmits``, ``dtype``,
    ``device``) and the stored tensors it owns: ``pair_channels`` (Ne, Ne 2 ntx T) the windowed
    pair I/Q signals, ``window_offset`` (ntx, Ne) the first record sample of each channel's
    window, ``window_samples`` (T) its length, ``max_run`` the longest run of segments a block
    reads, ``block_envelopes_e`` / ``block_envelopes_band`` the sparse block matrices of the two
    tiers, and ``segment``. :meth:`build` forms them from the pair I/Q signals and the sample
    ranges of the blocks (the layout's ``outside1``, ``outside2`` and ``strips``). It owns its
    caches too: the blocks' envelope entries per tier (:meth:`_bound_index`), the channel sums of
    the last neighbourhood's selection (:meth:`swap_envelopes`) and the counts of small batches
    (:meth:`_warm`). Nothing else of the basis is read.
    """

    #: samples per aligned envelope segment of the certificates
    segment = 4

    def __init__(self, model, pair_channels: torch.Tensor, window_offset: torch.Tensor, window_samples: int,
                 max_run: int, block_envelopes_e: torch.Tensor, block_envelopes_band: torch.Tensor,
                 segment: int | None = None):
        self.model = model
        self.pair_channels = pair_channels
        self.window_offset = window_offset
        self.window_samples = int(window_samples)
        #: longest run of consecutive segments a block reads
        self.max_run = int(max_run)
        self.block_envelopes_e = block_envelopes_e
        self.block_envelopes_band = block_envelopes_band
        if segment is not None:
            self.segment = int(segment)
        self._block_index: dict = {}  # per tier, the blocks' envelope entries (:meth:`_bound_index`)
        # (selection key, its channel sums, corrections since summed afresh) of :meth:`swap_envelopes`
        self._swap_sums = None
        self.corrected = 0  #: selections whose raw channels :meth:`moved_channels` corrected
        self._small_calls: dict = {}  # per compiled pass, the small batches seen (:meth:`_warm`)

    def view(self) -> "Certificates":
        """These certificates for another view of the same basis (a truncated one): the same
        tensors and block entries, its own counts of small batches and neighbourhood sums."""
        import copy

        out = copy.copy(self)
        out._swap_sums, out._small_calls = None, {}
        return out

    @classmethod
    def build(cls, model, layout, X: np.ndarray, lo: torch.Tensor, hi: torch.Tensor, window_offset: torch.Tensor,
              window_samples: int) -> "Certificates":
        """The certificates of the pair I/Q signals ``X`` (ntx, Ne, T, 2, Ne) on the channel
        windows (``window_offset``, ``window_samples``) for blocks reading the samples ``lo``,
        ``hi`` (ntx, nbz, nbx, Ne) (:meth:`~arraysel.physics.psf.build.BasisBuilder.sample_ranges`)
        outside E and outside the band (``layout.outside1``, ``layout.outside2``; the band's
        matrix is empty without ``layout.strips``)."""
        ne = model.n_elements
        T = int(window_samples)
        sg = cls.segment
        # A[j, (e, c, n, r, a)] = part c (0: re, 1: im) of sample t = a segment + r of (rx e, tx j)
        # on transmit n: the channels of receive e on every transmit are m_e sum_j m_j A[j, (e, ...)],
        # one contiguous block of columns (:meth:`_receive_products`); samples are stored
        # segment-offset major so that the envelopes reduce over contiguous slabs (:meth:`envelopes`)
        A = torch.from_numpy(X).unflatten(2, (T // sg, sg))  # (n, e, a, r, c, j)
        pair_channels = A.permute(5, 1, 4, 0, 3, 2).reshape(ne, -1).to(model.device, model.dtype)
        off = window_offset[:, None, None, :]
        read = hi >= lo
        lo = torch.where(read, lo - off, torch.full_like(lo, T))
        hi = torch.where(read, (hi - off).clamp(max=T - 1), torch.full_like(hi, -1))
        has_all = hi >= lo
        runs = torch.where(has_all, hi // sg - lo // sg + 1, torch.zeros_like(lo))
        self = cls(model, pair_channels, window_offset, T, max(1, int(runs.max())), None, None)
        tier = dict(max_run=self.max_run, window_samples=T, segment=self.segment, margin=self.bound_margin,
                    dtype=model.dtype, device=model.device)
        self.block_envelopes_e = block_matrix(lo, hi, layout.outside1, **tier)
        self.block_envelopes_band = block_matrix(lo, hi, layout.outside2, **tier) if layout.strips else \
            sparse_csr(torch.zeros(1, dtype=torch.long), torch.zeros(0, dtype=torch.long),
                 torch.zeros(0, dtype=model.dtype), (0, self.block_envelopes_e.shape[1])).to(model.device)
        return self

    #: rounding safety margin of the block bounds: the block matrices' entries, and the factor
    #: of the compiled sums (:meth:`bound`)
    bound_margin = 1.0 + 1e-4

    #: bytes of one product in :meth:`_receive_products` (kept in cache)
    receive_step_bytes = 2 << 20
    #: fewest selections whose products :meth:`_receive_products` forms for each receive element's
    #: own selections: fewer selections are bound by reading ``pair_channels``, not by the
    #: arithmetic, so one product serves them all and only the elements none of them uses are
    #: skipped (measurements: ``docs/performance.md``, "Tuning constants")
    receive_subset_min = 32

    def _receive_products(self, w: torch.Tensor, subsets: bool | None = None):
        """Yield ``(e0, e1, s, y)`` covering every receive element that some selection of ``w``
        (B, Ne) uses: ``s`` the selections (a LongTensor of rows of ``w``; None: all of them)
        whose products were formed for the receive elements ``e0 .. e1 - 1``, and ``y``
        (len(s), e1 - e0, 2, ntx, T) the products ``sum_j w[s, j] A[j, e, c, n, :]`` (samples in
        stored order, not yet weighted by the receive weight).

        A receive element with zero weight has a zero channel, so with ``subsets`` (default: a
        batch of at least :attr:`receive_subset_min` selections) the products of the selections
        that use each receive element are formed: for selections of k of Ne elements, k / Ne of
        the whole product ``w @ pair_channels``. Otherwise every selection's products are formed
        on the receive elements any of them uses.
        Consecutive receive elements with the same selections share one product (a single mask:
        its runs of active elements; soft weights: all elements), cut to
        :attr:`receive_step_bytes` of output so that it stays in cache."""
        ne = self.model.n_elements
        ntx = len(self.model.transmits)
        T = self.window_samples
        cols = 2 * ntx * T
        B = w.shape[0]
        on = (w != 0).T  # (Ne, B)
        if not (B >= self.receive_subset_min if subsets is None else subsets):
            on = on.any(1, keepdim=True)
        cut = (torch.nonzero((on[1:] != on[:-1]).any(1)).flatten() + 1).tolist()
        for e0, e1 in zip([0] + cut, cut + [ne]):
            s = torch.nonzero(on[e0]).flatten()
            if not s.numel():
                continue
            whole = s.numel() == on.shape[1]
            ws = w if whole else w[s]
            n = ws.shape[0]
            step = max(1, self.receive_step_bytes // (cols * n * w.element_size()))
            for a in range(e0, e1, step):
                b = min(e1, a + step)
                y = ws @ self.pair_channels[:, a * cols:b * cols]
                yield a, b, (None if whole else s), y.view(n, b - a, 2, ntx, T)

    def envelopes(self, w: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
        """Segment envelopes (ntx * Ne * M * nS, B) of the channels of selections w (no gradient),
        written into the first entries of ``out`` (a contiguous 1-D tensor of w's dtype and
        device, at least :meth:`envelope_size` long) when it is given.

        Entry (n, e, m, a): ``max |X_ne(t)|`` over segments ``a .. a + m`` (``segment`` samples
        each; zeros past the end). The channel sums of the receive elements a selection uses are
        formed a few receive elements at a time (:meth:`_receive_products`) and reduced to
        segment maxima at once, so they never reach main memory (or, for a few selections in a
        loop, each channel compiled from the rows it uses: :meth:`_channels_from_rows`); then
        M - 1 running maxima on the segment array (``segment`` times smaller than the channels).
        """
        ne = self.model.n_elements
        ntx = len(self.model.transmits)
        B = w.shape[0]
        sg = self.segment
        nS = self.window_samples // sg
        nch = ntx * ne
        if out is None:
            env = w.new_empty(nch, self.max_run, nS, B)
        else:
            env = out[:self.envelope_size(B)].view(nch, self.max_run, nS, B)
        seg = env[:, 0]
        if self._channels_from_rows(w):
            from arraysel.physics.peakkernels import channel_peaks_into

            seg.zero_()
            channel_peaks_into(self.pair_channels.numpy(), np.ascontiguousarray(w.numpy()), env.numpy())
        elif compiled_envelopes(w):
            return _envelopes_compiled(self, w, env)
        else:
            peaks = w.new_zeros(B, ne, ntx, nS)
            for e0, e1, s, y in self._receive_products(w):
                sq = y[:, :, 1].square_().addcmul_(y[:, :, 0], y[:, :, 0])  # |X|^2 (n, g, ntx, T), in y
                peak = sq.unflatten(-1, (sg, nS)).amax(3)  # (n, g, ntx, nS)
                if s is None:
                    peaks[:, e0:e1] = peak
                else:
                    peaks[s, e0:e1] = peak
            peaks.sqrt_().mul_(w.abs()[:, :, None, None])
            seg.view(ntx, ne, nS, B).copy_(peaks.permute(2, 1, 3, 0))
        return self._segment_runs(env)

    def envelope_size(self, B: int) -> int:
        """Entries of the envelopes of ``B`` selections (:meth:`envelopes`)."""
        nS = self.window_samples // self.segment
        return len(self.model.transmits) * self.model.n_elements * self.max_run * nS * B

    def _segment_runs(self, env: torch.Tensor) -> torch.Tensor:
        """Fill runs 2 .. ``max_run`` of envelopes ``env`` (nch, M, nS, B) whose first run (the
        segment peaks) is set: M - 1 running maxima; returns them as (nch * M * nS, B)."""
        nS, B = env.shape[2], env.shape[3]
        seg = env[:, 0]
        for m in range(1, self.max_run):
            env[:, m, nS - m:] = env[:, m - 1, nS - m:]
            torch.maximum(env[:, m - 1, : nS - m], seg[:, m:], out=env[:, m, : nS - m])
        return env.view(-1, B)

    def swaps_compiled(self, mask: torch.Tensor) -> bool:
        """Whether :meth:`swap_envelopes` serves the neighbours of ``mask``: on the CPU, without
        gradient, for a 0/1 selection."""
        return mask.device.type == "cpu" and not mask.requires_grad and bool(((mask == 0) | (mask == 1)).all())

    def swap_envelopes(self, mask: torch.Tensor, out: torch.Tensor, into: torch.Tensor) -> torch.Tensor:
        """:meth:`envelopes` of the neighbours of the 0/1 selection ``mask`` (Ne,) that switch the
        elements ``out[b]`` off and ``into[b]`` on (int (B,): one-swap neighbours, or (B, m): m
        elements each, ``-1`` for none), the same values to rounding, for less work: the selection's channel sums
        over every receive element are formed once (``Y[e] = sum_{j in mask} A_je``, float64), and
        a neighbour's channel on each receive element it uses is ``Y[e] - sum A_out,e + sum
        A_into,e``, 2 m + 1 rows read where summing it afresh reads k
        (:func:`~arraysel.physics.peakkernels.swap_peaks_into`). CPU, no gradient
        (:meth:`swaps_compiled`)."""
        from arraysel.physics.peakkernels import swap_peaks_into

        ne = self.model.n_elements
        ntx = len(self.model.transmits)
        B = int(out.shape[0])
        nS = self.window_samples // self.segment
        on = (mask.detach().cpu() != 0).numpy()
        A = self.pair_channels.numpy()
        # the selection's channel sums, kept for the next batch of the same neighbourhood
        key = on.tobytes()
        held = self._swap_sums
        if held is None or held[0] != key:
            held = self._swap_sums = self._channel_sums(A, on, key, held)
        env = torch.empty(ntx * ne, self.max_run, nS, B, dtype=self.pair_channels.dtype)
        env[:, 0].zero_()  # the channels a neighbour does not use; the longer runs come from the first
        swap_peaks_into(A, held[1], on, out.cpu().numpy(), into.cpu().numpy(), env.numpy())
        return self._segment_runs(env)

    #: most elements switched (off and on together) from the held selection for which
    #: :meth:`swap_envelopes` corrects its channel sums instead of summing the new selection's
    #: afresh (a search's next selection is one swap or a segment shift away), and the most
    #: corrections in a row before a fresh sum (float64 roundings of the corrections stay below
    #: 1e-14 relative, far inside the float32 envelopes' resolution)
    swap_sums_moved_max = 12
    swap_sums_refresh = 32

    def _channel_sums(self, A: np.ndarray, on: np.ndarray, key: bytes, held) -> tuple:
        """``(key, Y, corrections)`` for the 0/1 selection ``on`` (Ne,) bool: its channel sums over
        every receive element, ``Y[e] = sum_{j in on} A_je`` (Ne, 2 ntx T) float64. Corrected from
        the ``held`` ones (``Y - sum A_out + sum A_into``: the rows of the elements switched,
        where a fresh sum reads the k rows of the selection) when at most
        :attr:`swap_sums_moved_max` elements differ and fewer than :attr:`swap_sums_refresh`
        corrections were made in a row; summed afresh otherwise."""
        from arraysel.physics.peakkernels import row_sums

        ne = self.model.n_elements
        if held is not None and held[2] < self.swap_sums_refresh:
            base = np.frombuffer(held[0], dtype=bool)
            if base.shape == on.shape:
                outs, ins = np.flatnonzero(base & ~on), np.flatnonzero(on & ~base)
                moved = len(outs) + len(ins)
                if moved <= self.swap_sums_moved_max and moved + 2 < int(on.sum()):
                    y = held[1].copy()
                    if len(ins):
                        y += row_sums(A, ins).reshape(ne, -1)
                    if len(outs):
                        y -= row_sums(A, outs).reshape(ne, -1)
                    return key, y, held[2] + 1
        return key, row_sums(A, np.flatnonzero(on)).reshape(ne, -1), 0

    #: most elements switched each way for which :meth:`swap_channels` corrects the held sums
    #: (:meth:`swap_moves`)
    swap_channels_most = 8

    def swap_moves(self, w: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``(out, into, on)`` of the 0/1 selections ``w`` (B, Ne) relative to the selection whose
        channel sums :meth:`swap_envelopes` holds (the one whose neighbourhood is being scored):
        the elements each switches off and on ((B, m) int64, ``-1`` for none) and the receive
        elements each uses ((B, Ne) bool), for :meth:`swap_channels`. None (form the channels
        afresh) when no sums are held, ``w`` is not 0/1 on the CPU without gradient, or a
        selection is more than :attr:`swap_channels_most` elements away each way, or so far that
        correcting a channel (``2 m + 1`` rows) reads as many rows as summing it (the k it uses)."""
        base = self.held_selection()
        if base is None or w.device.type != "cpu" or w.requires_grad or not w.shape[0]:
            return None
        wn = w.detach().numpy()
        on = wn != 0
        if not np.array_equal(wn[on], np.ones(int(on.sum()), dtype=wn.dtype)):
            return None  # soft weights
        if base.shape[0] != on.shape[1]:
            return None
        outs, ins = base[None] & ~on, on & ~base[None]
        m = int(max(outs.sum(1).max(), ins.sum(1).max()))
        if m > self.swap_channels_most or 2 * m + 1 >= int(on.sum(1).min()):
            return None
        return flagged_elements(outs, max(m, 1)), flagged_elements(ins, max(m, 1)), on

    def held_selection(self) -> np.ndarray | None:
        """The 0/1 selection (Ne,) bool whose channel sums :meth:`swap_envelopes` holds (the one
        whose neighbourhood is being scored), or None."""
        held = self._swap_sums
        if held is None:
            return None
        base = np.frombuffer(held[0], dtype=bool)
        return base if base.shape[0] == self.model.n_elements else None

    def moved_channels(self, w: torch.Tensor, index: list):
        """None, or a generator of ``(i, RawChannels)`` for the selections ``w[i]``, ``i`` in
        ``index``, when :meth:`swap_moves` describes them all: the raw channels (as the
        refinement's product forms them) corrected from the held sums, one selection at a time so
        that they are still in cache when delay-and-summed. Counts them in ``corrected``."""
        moves = self.swap_moves(w[torch.tensor(index, dtype=torch.long, device=w.device)]) if index else None
        if moves is None:
            return None

        def each():
            we = moves[2].astype(self.pair_channels.numpy().dtype)
            for k, i in enumerate(index):
                y = self.swap_channels(*(v[k:k + 1] for v in moves))
                self.corrected += 1
                yield i, RawChannels(y[0], we[k], self.segment)

        return each()

    def swap_channels(self, out: np.ndarray, into: np.ndarray, on: np.ndarray) -> np.ndarray:
        """The receive products (B, Ne, 2, ntx, T) of the selections :meth:`swap_moves` describes,
        as :meth:`_receive_products` forms them (stored sample order, not weighted by the receive
        weight), on the receive elements each uses only (the others undefined): the held channel
        sums corrected by the rows of the elements switched (``2 m + 1`` rows read a channel where
        the product reads every row of ``pair_channels``)."""
        from arraysel.physics.peakkernels import swap_channels

        y = swap_channels(self.pair_channels.numpy(), self._swap_sums[1], out, into, on)
        return y.reshape(on.shape[0], self.model.n_elements, 2, len(self.model.transmits), self.window_samples)

    def _channels_from_rows(self, w: torch.Tensor) -> bool:
        """Whether :meth:`envelopes` sums each channel of ``w`` compiled from the rows of
        ``pair_channels`` its selection uses (:func:`~arraysel.physics.peakkernels.channel_peaks_into`)
        instead of forming the receive products: on the CPU without gradient, for a batch
        smaller than :data:`~arraysel.physics.compiled.MIN_BATCH` after
        :attr:`compiled_bound_warm` of them (a loop of gradient steps; a cold single-mask run
        loads no compiled code), when those rows (``sum_b nnz_b^2`` blocks, k^2 for a mask of k
        elements) are fewer than the product ``w @ pair_channels`` reads (Ne blocks per receive
        element any selection uses). Both are bound by those reads: one mask of 32 of 64
        elements reads a quarter of the channels instead of half."""
        if w.device.type != "cpu" or w.requires_grad or w.shape[0] >= compiled.MIN_BATCH:
            return False
        if not self._warm("envelopes"):
            return False
        on = w != 0
        return int(on.sum(1).square().sum()) < self.model.n_elements * int(on.any(0).sum())

    def _warm(self, what: str) -> bool:
        """Count a batch smaller than :data:`~arraysel.physics.compiled.MIN_BATCH` for the
        compiled pass ``what``; True from the call after :attr:`compiled_bound_warm` of them."""
        counts = self._small_calls
        counts[what] = counts.get(what, 0) + 1
        return counts[what] > self.compiled_bound_warm

    def _bound_index(self, tier: int) -> np.ndarray:
        """(ntx * Ne, nQ) int32: for each channel and block of ``tier``, the row of the channel's
        (max_run * nS) envelope entries the block reads (-1: none), from the block matrix."""
        index = self._block_index.get(tier)
        if index is None:
            S = self.block_envelopes_e if tier == 1 else self.block_envelopes_band
            nch = len(self.model.transmits) * self.model.n_elements
            per = S.shape[1] // nch
            crow, col = S.crow_indices().cpu(), S.col_indices().cpu()
            q = torch.repeat_interleave(torch.arange(S.shape[0]), crow[1:] - crow[:-1])
            index = torch.full((nch, S.shape[0]), -1, dtype=torch.int32)
            index[col // per, q] = (col % per).to(torch.int32)
            index = self._block_index[tier] = index.numpy()
        return index

    #: a batch smaller than :data:`arraysel.physics.compiled.MIN_BATCH` takes torch's
    #: operations for the first calls only (a cold single-mask run loads no compiled code): from
    #: the call after this many such batches on (a loop of gradient steps), counted per pass
    #: (:meth:`_warm`), its block bounds are summed compiled too (faster than the sparse product
    #: for one mask) and its envelopes summed from the rows it uses (:meth:`_channels_from_rows`)
    compiled_bound_warm = 4

    def bound(self, w: torch.Tensor, tier: int = 1, per_block: bool = False, env=None) -> torch.Tensor:
        """(B,) upper bound of |I| on the blocks outside E (tier 1) or outside the band (tier 2);
        with ``per_block`` the (nQ, B) bounds of every block. ``env``: :meth:`envelopes` of w.

        On the CPU, for at least :data:`~arraysel.physics.compiled.MIN_BATCH` selections (or
        after :attr:`compiled_bound_warm` smaller calls), the sums run compiled,
        channel by channel over the channels of the receive elements the selections use,
        float32 partial sums totalled in float64
        (:func:`~arraysel.physics.pairkernels.block_bound_sums`:
        the sparse product read the envelopes block by block, out of cache); elsewhere they are
        the sparse product with the block matrix."""
        S = self.block_envelopes_e if tier == 1 else self.block_envelopes_band
        B = w.shape[0]
        if S.shape[0] == 0:
            return torch.zeros((0, B) if per_block else B, dtype=w.dtype, device=w.device)
        if env is None:
            env = self.envelopes(w)
        if env.device.type == "cpu" and not env.requires_grad and (
                B >= compiled.MIN_BATCH or self._warm("bound")):
            from arraysel.physics.pairkernels import block_bound_sums

            ntx, ne = len(self.model.transmits), self.model.n_elements
            used = (w.detach() != 0).any(0).cpu()
            chans = torch.nonzero(used[None, :].expand(ntx, ne).reshape(-1)).flatten()
            sums = block_bound_sums(env.view(ntx * ne, -1, B).numpy(), self._bound_index(tier), chans.numpy())
            bounds = (torch.from_numpy(sums) * self.bound_margin).to(env.dtype)
        else:
            bounds = torch.sparse.mm(S, env)  # (nQ, B)
        return bounds if per_block else largest_bound(bounds)
