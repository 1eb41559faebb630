"""The neighbours of a selection on a 3-D scene, scored from the selection's own image.

The fast path (:class:`~arraysel.physics.volume.fast.MatrixFastPSF`) forms the image of pixel
``p`` as a sum over its columns ``j``:

    img(p) = sum_{j in p} gamma_j(w) z_j(w),   gamma(w) = w @ B,   z(w) = w @ Z,

with ``B`` the receive matrix and ``Z = C Psi`` the transmit rows of the elements (``Z_e = C_e Psi``),
so the image is bilinear in the element weights ``w``, the same mask on transmit and receive. A
move ``w' = w + d`` (``d = +1`` on the elements switched on, ``-1`` on those switched off) changes it
by

    img'(p) = img(p) + sum_e d_e S_e(p) + sum_{j in p} (d @ B)_j (d @ Z)_j,
    S_e(p) = sum_{j in p} (B_ej z_j + gamma_j Z_ej)

(``S_e``: the receive-side and transmit-side single-element images of the selection). For a swap
(``a`` off, ``b`` on) the last term is ``D_a + D_b - X_ab`` with ``D_e = sum_j B_ej Z_ej`` and the
cross term ``X_ab = sum_j (B_aj Z_bj + Z_aj B_bj)``. Nothing is approximated: these are the fast
path's own planes, to rounding.

:class:`MatrixNeighbourhood` keeps ``Z``, ``D`` and, per selection, its image and the ``S_e`` it has
needed; it scores

a dense set of swaps (many ``b`` for each ``a``, a whole neighbourhood) by one batched matrix
product per pixel group for a block of ``a``: ``X`` of the block against every element. Sparser
requests, and moves of several elements, are scored as masks (one by one, a move's image is no
cheaper to form than a mask's in a batch: it reads whole rows of ``B`` and ``Z``).

The neighbours' planes then go through the objective's metrics (:meth:`MatrixObjective._metrics`),
the same function :meth:`MatrixObjective.evaluate` scores masks with.
"""
from __future__ import annotations

import numpy as np
import torch

from arraysel.errors import SelectionError

__all__ = ["MatrixNeighbourhood", "BLOCK_ROWS", "DENSE_SHARE", "check_selection"]

#: outgoing elements per batched product of the dense path (its output: rows x Ne images)
BLOCK_ROWS = 4
#: the neighbourhood path is taken when the requested swaps fill at least this share of the
#: (distinct outgoing elements) x Ne block it computes (on matrix-1024 a neighbour of a block costs
#: about a sixteenth of a mask scored by ``evaluate``; sparser requests are scored as masks)
DENSE_SHARE = 1 / 16


class MatrixNeighbourhood:
    """Exact neighbourhood scoring of a :class:`~arraysel.objective.matrix_objective.MatrixObjective`
    whose planes come from the fast path (module docstring). ``objective.model`` must be a
    :class:`~arraysel.physics.volume.fast.MatrixFastPSF`."""

    def __init__(self, objective):
        model = objective.model
        self.objective = objective
        self.model = model
        self.n_elements = ne = model.n_elements
        self.cols = model._Psi.shape[1]
        self.cdtype = model.cdtype
        #: (pixels, width, column offset) per pixel group, in the fast path's column order
        self.groups = list(model._groups)
        self.n_pixels = sum(n for n, _, _ in self.groups)
        self.unsort = model._unsort
        self._B = torch.view_as_complex(model._B.reshape(ne, self.cols, 2))   # (Ne, cols), no copy
        self._Z = None          # (Ne, cols) transmit rows C_e Psi
        self._D = None          # (Ne, P) sum_j B_ej Z_ej, group order
        self._right = None      # per group (n, 4 w, Ne) real: [Re Z | Re B | Im Z | Im B] by column
        self._key = None        # the selection whose image and S_e are held
        self._img = None
        self._S = None
        self._have = None
        self._U = None          # S_e + D_e as columns, per selection (dense path)
        self._metrics = None

    # ---------------------------------------------------------------- shared tensors
    def _segsum(self, x: torch.Tensor) -> torch.Tensor:
        """Per-pixel sums ``(..., P)`` (group order) of per-column values ``(..., cols)``."""
        lead = x.shape[:-1]
        parts = [x[..., o:o + n * w].reshape(*lead, n, w).sum(-1) for n, w, o in self.groups]
        return torch.cat(parts, dim=-1)

    def _rows(self, elements: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The receive and transmit rows ``(B_e, Z_e)`` of ``elements``, each ``(E, cols)``."""
        return self._B.index_select(0, elements), self.transmit_rows().index_select(0, elements)

    def transmit_rows(self) -> torch.Tensor:
        """``Z = C Psi`` (Ne, cols): the transmit rows of the elements (formed once)."""
        if self._Z is None:
            m = self.model
            c = m._C.permute(1, 0, 2).reshape(self.n_elements, -1)            # (Ne, n_tx r)
            self._Z = c @ m._Psi
        return self._Z

    def diagonal(self) -> torch.Tensor:
        """``D_e(p) = sum_j B_ej Z_ej`` (Ne, P), group order (formed once)."""
        if self._D is None:
            Z = self.transmit_rows()
            self._D = torch.cat([self._segsum(self._B[i:i + 64] * Z[i:i + 64])
                                 for i in range(0, self.n_elements, 64)])
        return self._D

    def rights(self) -> list[torch.Tensor]:
        """Per pixel group, the right factor ``(n, 4 w, Ne)`` (real) of the cross terms."""
        if self._right is None:
            Z = self.transmit_rows()
            rdt = self.model._B.dtype
            out = []
            for n, w, o in self.groups:
                r = torch.empty(n, 4 * w, self.n_elements, dtype=rdt)
                zr = torch.view_as_real(Z[:, o:o + n * w]).reshape(-1, n, w, 2)
                br = torch.view_as_real(self._B[:, o:o + n * w]).reshape(-1, n, w, 2)
                for k, src in enumerate((zr[..., 0], br[..., 0], zr[..., 1], br[..., 1])):
                    r[:, k * w:(k + 1) * w] = src.permute(1, 2, 0)
                out.append(r)
            self._right = out
        return self._right

    # ---------------------------------------------------------------- the selection
    def forget(self) -> None:
        """Drop the held selection (the next one is formed afresh)."""
        self._key = self._img = self._S = self._have = self._U = None

    def select(self, mask: np.ndarray) -> None:
        """Hold the image of the 0/1 selection ``mask`` (Ne,) (kept while it stays the same)."""
        key = mask.tobytes()
        if key == self._key:
            return
        m = self.model
        w = torch.as_tensor(mask, dtype=m.dtype, device=m.device)[None]
        gamma = torch.view_as_complex((w @ m._B).reshape(1, -1, 2))[0]
        c = torch.einsum("be,ner->bnr", w.to(self.cdtype), m._C).reshape(1, -1)
        z = (c @ m._Psi)[0]
        self._gamma, self._z = gamma, z
        self._img = self._segsum(gamma * z)
        self._S = torch.zeros(self.n_elements, self.n_pixels, dtype=self.cdtype)
        self._have = torch.zeros(self.n_elements, dtype=torch.bool)
        self._U = None
        self._key = key

    def _single(self, elements: torch.Tensor) -> torch.Tensor:
        """``S_e`` (E, P) of ``elements`` for the held selection (formed when first needed)."""
        need = torch.unique(elements[~self._have[elements]])
        for i in range(0, need.numel(), 64):
            e = need[i:i + 64]
            Be, Ze = self._rows(e)
            self._S[e] = self._segsum(Be * self._z + self._gamma * Ze)
            self._have[e] = True
        return self._S.index_select(0, elements)

    # ---------------------------------------------------------------- images, as columns
    def _pairs_part(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``S_e + D_e`` of every element as columns (P, Ne), real and imaginary (per selection)."""
        if self._U is None:
            u = (self._single(torch.arange(self.n_elements)) + self.diagonal()).T
            self._U = (u.real.contiguous(), u.imag.contiguous())
        return self._U

    def swap_block(self, outs: torch.Tensor) -> torch.Tensor:
        """The images of the swaps ``outs[i]`` off and every element on (the columns of active
        elements are meaningless) as real ``(P, 2, A, Ne)``: real and imaginary parts, rows in
        the fast path's pixel order; one batched product per pixel group."""
        A = outs.numel()
        Ba, Za = self._rows(outs)
        rights = self.rights()
        rdt = self.model._B.dtype
        X = torch.empty(self.n_pixels, 2 * A, self.n_elements, dtype=rdt)
        p0 = 0
        for (n, w, o), r in zip(self.groups, rights):
            L = torch.view_as_real(torch.cat([Ba[:, o:o + n * w].reshape(A, n, w),
                                              Za[:, o:o + n * w].reshape(A, n, w)], 2)).permute(1, 0, 2, 3)
            left = torch.empty(n, 2, A, 4 * w, dtype=rdt)   # [re rows; im rows] x [re | im] of (B_a, Z_a)
            left[:, 0, :, :2 * w] = L[..., 0]
            left[:, 0, :, 2 * w:] = -L[..., 1]
            left[:, 1, :, :2 * w] = L[..., 1]
            left[:, 1, :, 2 * w:] = L[..., 0]
            torch.bmm(left.reshape(n, 2 * A, 4 * w), r, out=X[p0:p0 + n])
            p0 += n
        X = X.reshape(self.n_pixels, 2, A, self.n_elements).neg_()
        v = (self._img[None] - self._single(outs) + self.diagonal().index_select(0, outs)).T   # (P, A)
        ur, ui = self._pairs_part()
        X[:, 0].add_(ur[:, None]).add_(v.real[:, :, None])
        X[:, 1].add_(ui[:, None]).add_(v.imag[:, :, None])
        return X

    def dense(self, out: np.ndarray) -> bool:
        """Whether swaps with the outgoing elements ``out`` are cheaper here than as masks: at
        least :data:`DENSE_SHARE` of the block (distinct outgoing elements x Ne) they need."""
        return out.size >= DENSE_SHARE * np.unique(out).size * self.n_elements

    def swap_columns(self, out: np.ndarray, into: np.ndarray):
        """Yield ``(positions, re, im, cols)``: the images of the swaps ``(out[i], into[i])`` of
        the held selection at ``positions`` of the request as the columns ``cols`` of ``(P, M)``
        real and imaginary parts, a block of outgoing elements against every element at a time."""
        order = np.argsort(out, kind="stable")
        a_sorted = out[order]
        starts = np.flatnonzero(np.r_[True, a_sorted[1:] != a_sorted[:-1]])
        ends = np.r_[starts[1:], a_sorted.size]
        ne = self.n_elements
        for g in range(0, starts.size, BLOCK_ROWS):
            s0, s1 = starts[g:g + BLOCK_ROWS], ends[g:g + BLOCK_ROWS]
            X = self.swap_block(torch.as_tensor(a_sorted[s0], dtype=torch.long))
            A = s0.size
            pos = np.concatenate([order[s:e] for s, e in zip(s0, s1)])
            rows = np.concatenate([np.full(e - s, i) for i, (s, e) in enumerate(zip(s0, s1))])
            idx = torch.as_tensor(rows * ne + into[pos])
            re = X[:, 0].reshape(self.n_pixels, A * ne)
            im = X[:, 1].reshape(self.n_pixels, A * ne)
            yield pos, re, im, idx

    def metrics(self):
        """The :class:`~arraysel.objective.columns3d.ColumnMetrics` of the objective (formed once)."""
        if self._metrics is None:
            from arraysel.objective.columns3d import ColumnMetrics

            obj = self.objective
            ref = {k: v.detach().cpu() for k, v in obj.reference_planes().items()}
            self._metrics = ColumnMetrics(obj.coords, ref, torch.argsort(self.unsort.cpu()),
                                          dtype=self.model.dtype, **obj.metric_kw)
        return self._metrics

    def score(self, pieces, total: int) -> dict[str, np.ndarray]:
        """``{name: float64 (total,)}`` of the columns ``pieces`` yields as ``(positions, re, im, cols)``."""
        cm = self.metrics()
        out: dict[str, np.ndarray] = {}
        for pos, re, im, cols in pieces:
            for k, v in cm(re, im, cols).items():
                if k not in out:
                    out[k] = np.empty(total, dtype=np.float64)
                out[k][pos] = v
        return out


def check_selection(mask: np.ndarray, n_elements: int) -> None:
    """SelectionError when ``mask`` is not one non-empty selection of the scene's elements."""
    if mask.size != n_elements:
        raise SelectionError(f"mask must have shape ({n_elements},), got ({mask.size},)")
    if not mask.any():
        raise SelectionError("empty selection (no active element): mask")
