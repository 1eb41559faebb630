"""Hot blocks: grid blocks that the selections of a search leave loose again and again, settled
from their pair matrices instead of a delay-and-sum of each selection's channels.

The refinement (:meth:`arraysel.physics.psf.refinement.Refinement.refine`) settles a selection
whose peak the block bounds alone do not certify on each block whose bound reaches the peak.
Without strips such a block is delay-and-summed from the selection's own channels. On a
convex probe, many selections of a search leave the same few blocks loose: its lateral lobes
at the scatterer's depth, just beside E.

A block left loose :attr:`HotBlocks.after` times becomes hot. Its symmetric pair matrix
``G = (D + D^T) / 2`` (Ne x Ne x 2 Npix float64; ``D[j, e]`` the delay-and-sum on the block of
the I/Q signal element ``e`` receives when ``j`` transmits) is formed once from the stored pair
channels (:func:`~arraysel.physics.pairkernels.block_pair_matrix`), so that a selection's image
on the block is ``I(w) = w^T G w``.

A selection ``w = s + d`` near a reference selection ``s`` then costs ``|d|^2`` rows of ``G``:
``I(s) + 2 d^T (G s) + d^T G d`` (:func:`~arraysel.physics.pairkernels.moved_block_values`).
The reference is the selection whose neighbourhood is being scored, when the certificates hold
one (:meth:`~arraysel.physics.psf.certificate.Certificates.held_selection`); ``G s`` and
``s^T G s`` are carried from one reference to the next by the elements that changed.

Inputs (constructor): the model (``n_elements``, ``transmits``, ``device``), the certificates
(``pair_channels``, ``window_samples``, ``segment``, ``held_selection``) and ``plans``, the
refinement's block DAS plans
(:meth:`~arraysel.physics.psf.refinement.Refinement._plans_for_blocks`). Results are exact to
float64 rounding, covered by an allowance; a decision keeps the delay-and-sum's ``1e-4``
margin.
"""
from __future__ import annotations

import numpy as np
import torch

from arraysel.selection import flagged_elements

__all__ = ["HotBlocks"]


class HotBlocks:
    """The hot blocks of one pair basis (shared by its truncated views): their pair matrices,
    how often each block was loose, and the reference selection's state (see the module)."""

    #: times a block is left loose before its pair matrix is formed and kept (forming it costs
    #: about as much as 400 block delay-and-sums of one selection: docs/performance.md)
    after = 64

    #: memory (bytes) of the pair matrices kept (one block: Ne^2 x 2 block^2 float64, 16.8 MB
    #: for 128 elements and 8 x 8 blocks; a block that does not fit stays beamformed), at most
    #: the memory cap ``ARRAYSEL_MEMORY_GIB``
    max_bytes = 256 * 2 ** 20

    #: the reference selection is kept while the selections settled differ from it by at most
    #: this many elements (median), and carried to a new one that differs by at most this many
    #: by updating each block's state
    moved_most = 16

    #: updates of a block's state at the reference before it is formed afresh
    refresh = 64

    def __init__(self, model, certificates, plans):
        self.model = model
        self.certificates = certificates
        self.plans = plans
        self.matrices: dict = {}  # (qz, qx) -> (G, largest |G| entry)
        self.seen: dict = {}  # (qz, qx) -> times it was loose
        self.ref: np.ndarray | None = None  # the reference selection (Ne,) float64
        self.states: dict = {}  # (qz, qx) -> (G ref, ref^T G ref, updates since formed)
        self.settled = 0  #: selections that reached a hot block

    def clear(self) -> None:
        """Forget every matrix, count and state (as a new basis starts)."""
        self.matrices.clear()
        self.seen.clear()
        self.states.clear()
        self.ref = None

    def settle(self, w: torch.Tensor, loose: dict, blocks: torch.Tensor, threshold: torch.Tensor) -> list:
        """Settle the hot blocks among ``loose`` (selection -> its loose rows of ``blocks``, the
        tier's (qz, qx) blocks) for the selections ``w`` and their ``threshold`` (the peak less
        its error bound), counting each block's loose occurrences (and making it hot at
        :attr:`after`). ``loose`` is updated in place: a selection that reaches its threshold on
        a hot block leaves it (unsettled), the others keep only their other blocks. Returns the
        selections whose loose blocks were all hot and stayed below their thresholds (none for
        selections or a model off the CPU)."""
        from arraysel.physics.pairkernels import moved_block_values  # compiled code: loaded on use

        if not loose or w.device.type != "cpu" or self.model.device.type != "cpu":
            return []
        by_block: dict = {}  # (qz, qx) -> [(selection, row in blocks)]
        for i, left in loose.items():
            for q in left.tolist():
                key = (int(blocks[q][0]), int(blocks[q][1]))
                self.seen[key] = self.seen.get(key, 0) + 1
                by_block.setdefault(key, []).append((i, q))
        hot = {}
        for key in by_block:
            if key in self.matrices or self.seen[key] >= self.after:
                got = self._matrix(key)
                if got is not None:
                    hot[key] = got
        if not hot:
            return []
        rows = sorted({i for key in hot for i, _ in by_block[key]})
        at = {i: r for r, i in enumerate(rows)}
        W = w[torch.tensor(rows, dtype=torch.long, device=w.device)].detach().cpu().double().numpy()
        ref = self._reference(W)
        d = W - ref[None]
        moved = d != 0
        idx = flagged_elements(moved, max(1, int(moved.sum(1).max())))
        val = np.where(idx >= 0, np.take_along_axis(d, np.maximum(idx, 0), axis=1), 0.0)
        # float64 rounding of sums of at most 4 Ne^2 terms, each at most (|w|_1 + |s|_1)^2 max|G|
        ne = W.shape[1]
        room = 4 * ne * ne * (np.finfo(np.float64).eps / 2) * (np.abs(W).sum(1) + np.abs(ref).sum()) ** 2
        thr = threshold.detach().cpu().double().numpy()
        failed, done = set(), {}
        for key, (G, gmax) in hot.items():
            g, base = self._state(key, G, ref)
            sel = [i for i, _ in by_block[key]]
            r = np.array([at[i] for i in sel], dtype=np.int64)
            v = moved_block_values(G, g, base, idx[r], val[r])
            n = v.shape[1] // 2
            peak = np.sqrt((v[:, :n] ** 2 + v[:, n:] ** 2).max(1)) + room[r] * gmax
            for (i, q), bad in zip(by_block[key], (peak * (1 + 1e-4) >= thr[sel]).tolist()):
                if bad:
                    failed.add(i)
                done.setdefault(i, set()).add(q)
        self.settled += len(rows)
        settled = []
        for i in list(loose):
            if i in failed:
                del loose[i]
            elif i in done:
                keep = [q for q in loose[i].tolist() if q not in done[i]]
                if keep:
                    loose[i] = torch.tensor(keep, dtype=torch.long)
                else:
                    del loose[i]
                    settled.append(i)
        return settled

    def _reference(self, W: np.ndarray) -> np.ndarray:
        """The reference selection (Ne,) float64 for the selections ``W`` (R, Ne): the one whose
        neighbourhood is being scored when the certificates hold one, else the current
        reference while the selections stay near it, else the first of ``W``. A new reference
        within :attr:`moved_most` elements of the old one updates each block's state; a farther
        one drops them (formed again on use)."""
        from arraysel.physics.pairkernels import moved_block_values

        old = self.ref
        held = self.certificates.held_selection()
        if held is not None:
            new = held.astype(np.float64)
        elif old is not None and float(np.median((W != old[None]).sum(1))) <= self.moved_most:
            new = old
        else:
            new = W[0].copy()
        if old is not None and np.array_equal(new, old):
            return old
        step = np.flatnonzero(new - old) if old is not None else None
        if step is None or step.size > self.moved_most:
            self.states.clear()
        else:
            d = (new - old)[step]
            for key, (g, base, updates) in list(self.states.items()):
                if updates >= self.refresh:
                    del self.states[key]
                    continue
                G = self.matrices[key][0]
                base = moved_block_values(G, g, base, step[None], d[None])[0]
                self.states[key] = (g + np.tensordot(G[:, step], d, axes=([1], [0])), base, updates + 1)
        self.ref = new
        return new

    def _state(self, key: tuple, G: np.ndarray, ref: np.ndarray):
        """``(G ref, ref^T G ref)`` of block ``key`` at the reference ``ref``, kept until it moves."""
        got = self.states.get(key)
        if got is None:
            g = np.tensordot(G, ref, axes=([1], [0]))
            got = self.states[key] = (g, ref @ g, 0)
        return got[0], got[1]

    def _matrix(self, key: tuple):
        """``(G, largest |G| entry)`` of the block ``key`` = (qz, qx), formed on first use and kept;
        None when it does not fit :attr:`max_bytes` or the channels are not on the CPU."""
        got = self.matrices.get(key)
        if got is not None:
            return got
        from arraysel.physics.pairkernels import block_pair_matrix

        cert, model = self.certificates, self.model
        ne = model.n_elements
        if cert.pair_channels.device.type != "cpu":
            return None
        from arraysel.physics.psf.settings import memory_limit_bytes

        i0, wt, rot = self.plans([key])[0]
        need = ne * ne * 2 * i0.shape[1] * 8
        if sum(G.nbytes for G, _ in self.matrices.values()) + need > min(self.max_bytes, memory_limit_bytes()):
            return None
        y = cert.pair_channels.numpy().reshape(ne, ne, 2, len(model.transmits), cert.window_samples)
        G = block_pair_matrix(y, i0.contiguous().numpy(), wt.contiguous().numpy(),
                              torch.view_as_real(rot.contiguous()).numpy(), cert.segment)
        n = G.shape[2] // 2
        self.matrices[key] = (G, float(np.sqrt(G[:, :, :n] ** 2 + G[:, :, n:] ** 2).max()))
        return self.matrices[key]
