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
needed. It scores

* a *block* of swaps (one outgoing element ``a`` against many incoming ones, up to
  :data:`BLOCK_ROWS` such ``a`` at a time: what a search asks for when the neighbourhood says it
  prefers blocks, :meth:`block`) by one batched matrix product per chunk of pixels: the cross terms
  ``C_ae`` of the block's ``a`` against every element, read while in cache by a compiled pass
  (:func:`~arraysel.objective.column_kernels.block_power`) that writes each swap's ``|img|^2`` and
  its sums against the reference, all the metrics need;
* any other move (a few swaps of scattered elements, moves of several elements) from its own
  rows: ``img' = img + sum_e d_e S_e + sum_{j in p} (d @ B)_j (d @ Z)_j``, which reads the ``2 m``
  rows of ``B`` and ``Z`` a move of ``m`` elements changes (where a mask scored on its own reads
  all ``k`` of them).

``S`` is linear in the selection (``S_e(w) = sum_f w_f C_ef``, ``C_ee = 2 D_e``), so when the
selection moves by a few elements the ``S_e`` held are carried over by the cross terms of the
elements moved (:meth:`select`), formed afresh every :data:`REFRESH_AFTER` moves against rounding.

The neighbours' planes then go through the objective's metrics (:meth:`MatrixObjective._metrics`),
the same function :meth:`MatrixObjective.evaluate` scores masks with.
"""
from __future__ import annotations

import numpy as np
import torch

from arraysel.errors import SelectionError

__all__ = ["MatrixNeighbourhood", "BLOCK_ROWS", "PIXEL_CHUNK", "DENSE_SHARE", "MOVE_BATCH", "CARRY_MAX", "REFRESH_AFTER",
           "check_selection"]

#: most outgoing elements a pass of the block path takes: each pass reads the right factors of
#: every element once (0.87 GB in float32 on matrix-1024), and holds ``|img|^2`` of its swaps
#: (16 x 768 neighbours: 226 MB in float32)
BLOCK_ROWS = 16
#: pixels per batched product of the block path (its cross terms are read while in cache)
PIXEL_CHUNK = 64
#: an outgoing element's swaps go by the block path when they fill at least this share of its row
#: of Ne images (on matrix-1024 a neighbour of a block costs about a fifteenth of a mask scored by
#: ``evaluate``); the other moves are formed from their own rows
DENSE_SHARE = 1 / 16
#: moves formed from their own rows per batch (each reads the rows of the elements it changes)
MOVE_BATCH = 64
#: most elements a selection may differ from the held one by for its ``S_e`` to be carried over
CARRY_MAX = 16
#: carried selections after which the held ``S_e`` are formed afresh (float32 rounding)
REFRESH_AFTER = 32


class MatrixNeighbourhood:
    """Exact neighbourhood scoring of a :class:`~arraysel.objective.matrix_objective.MatrixObjective`
    whose planes come from the fast path (module docstring). ``objective.model`` must be a
    :class:`~arraysel.physics.volume.fast.MatrixFastPSF`."""

    def __init__(self, objective):
        model = objective.model
        self.objective = objective
        self.model = model
        self.n_elements = ne = model.n_elements
        self.cols = model._B.shape[1] // 2
        self.cdtype = model.cdtype
        #: (pixels, width, column offset) per pixel group, in the fast path's column order
        self.groups = list(model._groups)
        self.n_pixels = sum(n for n, _, _ in self.groups)
        self.unsort = model._unsort
        # (Ne, cols): no copy of a receive matrix held in the evaluation's precision
        self._B = torch.view_as_complex(model.receive_matrix().reshape(ne, self.cols, 2))
        self._Z = None          # (Ne, cols) transmit rows C_e Psi
        self._D = None          # (Ne, P) sum_j B_ej Z_ej, group order
        self._right = None      # per group (n, 4 w, Ne) real: [Re Z | Re B | Im Z | Im B] by column
        self._key = None        # the selection whose image and S_e are held
        self._img = None
        self._S = None
        self._have = None
        self._U = None          # S_e + D_e as columns, per selection (block path)
        self._mask = None       # the held selection
        self._pending = None    # the rows (d @ B, d @ Z) of a carried move not yet added to _U
        self._carried = 0       # selections whose S_e were carried over since they were formed
        self._metrics = None
        self._buffers: dict[str, np.ndarray] = {}   # kept between blocks (:meth:`_scratch`)

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
            self._Z = self.model.transmit_sums(self.model.element_coefficients())
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
            rdt = self.model.dtype
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
        self._key = self._img = self._S = self._have = self._U = self._mask = self._pending = None
        self._carried = 0

    def select(self, mask: np.ndarray) -> None:
        """Hold the image of the 0/1 selection ``mask`` (Ne,) (kept while it stays the same). When it
        differs from the held one by a few elements (at most :data:`CARRY_MAX`), its ``gamma``,
        ``z`` and image are carried over from the held ones by the rows of the elements moved,
        and the ``S_e`` of every element too when held (module docstring); else they are formed
        afresh (every :data:`REFRESH_AFTER` carried selections too, against rounding)."""
        mask = np.asarray(mask, dtype=bool)
        key = mask.tobytes()
        if key == self._key:
            return
        changed = None if self._mask is None else np.flatnonzero(mask != self._mask)
        if changed is not None and changed.size <= CARRY_MAX and self._carried < REFRESH_AFTER:
            self._carry(changed, np.where(mask[changed], 1.0, -1.0))
        else:
            m = self.model
            w = torch.as_tensor(mask, dtype=m.dtype, device=m.device)[None]
            rx = torch.view_as_real(self._B).reshape(self.n_elements, -1)   # (Ne, 2 cols) real, no copy
            gamma = torch.view_as_complex((w @ rx).reshape(1, -1, 2))[0]
            self._gamma, self._z = gamma, m.transmit_sums(m.transmit_coefficients(w))[0]
            self._img = self._segsum(self._gamma * self._z)
            self._U = self._pending = None
            self._carried = 0
        self._S = None      # formed when first needed (:meth:`_single`)
        self._have = torch.zeros(self.n_elements, dtype=torch.bool)
        self._key, self._mask = key, mask.copy()

    def _carry(self, changed: np.ndarray, signs: np.ndarray) -> None:
        """Carry the held selection to the one that switched ``changed`` by ``signs`` (+1 on, -1
        off), by the move's rows ``dB = d @ B``, ``dZ = d @ Z``: ``gamma += dB``, ``z += dZ``, the
        image by :meth:`move_images`' formula, and the held ``S_e + D_e`` of every element
        (:meth:`_pairs_part`) by ``S_e += sum_f d_f C_ef``, the cross terms of the move's rows
        against every element; those rows are kept until the columns are next needed
        (:meth:`_settle`): a block formed then takes them in its own product."""
        Bc, Zc = self._rows(torch.as_tensor(changed, dtype=torch.long))
        d = torch.as_tensor(signs, dtype=self.cdtype)[None]
        rows = (d @ Bc, d @ Zc)
        self._img = self._img + self._segsum(rows[0] * (rows[1] + self._z) + self._gamma * rows[1])[0]
        self._gamma = self._gamma + rows[0][0]
        self._z = self._z + rows[1][0]
        if self._U is not None:
            if self._pending is not None:     # C is linear in the rows: moves carried add up
                rows = (rows[0] + self._pending[0], rows[1] + self._pending[1])
            self._pending = rows
        self._carried += 1

    def _settle(self) -> None:
        """Add the carried move's cross terms to the held columns (a block's product adds them
        itself, :meth:`swap_power`)."""
        if self._pending is None:
            return
        X = self._cross(*self._pending)[:, :, 0]
        self._pending = None
        ur, ui = self._U
        ur.add_(X[:, 0])
        ui.add_(X[:, 1])

    def _single(self, elements: torch.Tensor) -> torch.Tensor:
        """``S_e`` (E, P) of ``elements`` for the held selection (formed when first needed, or read
        from the columns :meth:`_pairs_part` holds)."""
        need = torch.unique(elements[~self._have[elements]])
        if self._S is None:
            self._S = torch.empty(self.n_elements, self.n_pixels, dtype=self.cdtype)
        for i in range(0, need.numel(), 64):
            e = need[i:i + 64]
            if self._U is not None:
                ur, ui = self._pairs_part()
                self._S[e] = torch.complex(ur[:, e], ui[:, e]).T - self.diagonal().index_select(0, e)
            else:
                Be, Ze = self._rows(e)
                self._S[e] = self._segsum(Be * self._z + self._gamma * Ze)
            self._have[e] = True
        return self._S.index_select(0, elements)

    # ---------------------------------------------------------------- images, as columns
    def _pairs_part(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``S_e + D_e`` of every element as columns (P, Ne), real and imaginary (per selection)."""
        if self._U is None:
            u = torch.view_as_real(self._single(torch.arange(self.n_elements)) + self.diagonal())
            u = u.permute(2, 1, 0).contiguous()                                 # (2, P, Ne)
            self._U = (u[0], u[1])
        self._settle()
        return self._U

    def _cross(self, Ba: torch.Tensor, Za: torch.Tensor) -> torch.Tensor:
        """The cross terms ``C_ae(p) = sum_{j in p} (B_aj Z_ej + Z_aj B_ej)`` of the rows ``(B_a,
        Z_a)`` (each ``(A, cols)``) against every element as real ``(P, 2, A, Ne)`` (real and
        imaginary parts, the fast path's pixel order; ``C_aa = 2 D_a``): one batched product per
        pixel group."""
        A = Ba.shape[0]
        X = torch.empty(self.n_pixels, 2 * A, self.n_elements, dtype=self.model.dtype)
        p0 = 0
        for (n, _, _), r, left in zip(self.groups, self.rights(), self._lefts(Ba, Za)):
            torch.bmm(left, r, out=X[p0:p0 + n])
            p0 += n
        return X.reshape(self.n_pixels, 2, A, self.n_elements)

    def swap_power(self, outs: torch.Tensor, ai: np.ndarray, ei: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """``(k2, sums)`` of the swaps ``outs[ai[i]]`` off and ``ei[i]`` on: ``|img|^2`` (M, P) (the
        fast path's pixel order) and float64 ``(<k, k>, Re <k, r>, Im <k, r>)`` (M, 3) against the
        reference (:func:`~arraysel.objective.column_kernels.block_power`). One batched product
        per chunk of :data:`PIXEL_CHUNK` pixels gives the cross terms of ``outs`` (and of a carried
        move's rows, added to the held columns) against every element, and the compiled pass reads
        the swaps' images from it while it is in cache."""
        from arraysel.objective.column_kernels import block_power

        Ba, Za = self._rows(outs)
        Sa = self._segsum(Ba * self._z + self._gamma * Za)               # S_a from the rows
        v = (self._img[None] - Sa + self.diagonal().index_select(0, outs)).T   # (P, A)
        vr, vi = v.real.contiguous().numpy(), v.imag.contiguous().numpy()
        if self._U is None:
            self._pairs_part()
        pend, self._pending = self._pending, None
        if pend is not None:     # the carried move's rows in the same product, added to the columns
            Ba, Za = torch.cat([pend[0], Ba]), torch.cat([pend[1], Za])
        first = 0 if pend is None else 1
        ur, ui = self._U
        cm = self.metrics()
        rr, ri = cm.ref_r.numpy(), cm.ref_i.numpy()
        A, ne = outs.shape[0], self.n_elements
        rows = np.full((A, ne), -1, dtype=np.int64)           # the row of k2 of each swap asked for
        rows[ai, ei] = np.arange(ai.size)
        k2 = self._scratch("k2", (ai.size, self.n_pixels), vr.dtype)
        acc = np.zeros((3, A, ne))
        chunk = PIXEL_CHUNK
        tile = self._scratch("tile", (chunk, ne), vr.dtype)
        out = torch.from_numpy(self._scratch("X", (chunk, 2 * Ba.shape[0], ne), vr.dtype))
        p0 = 0
        for (n, w, o), r, left in zip(self.groups, self.rights(), self._lefts(Ba, Za)):
            for c0 in range(0, n, chunk):
                c1 = min(n, c0 + chunk)
                X = torch.bmm(left[c0:c1], r[c0:c1], out=out[:c1 - c0]).reshape(c1 - c0, 2, -1, ne)
                if first:
                    ur[p0 + c0:p0 + c1].add_(X[:, 0, 0])
                    ui[p0 + c0:p0 + c1].add_(X[:, 1, 0])
                sl = slice(p0 + c0, p0 + c1)
                block_power(X.numpy(), first, ur[sl].numpy(), ui[sl].numpy(), vr[sl], vi[sl], rr[sl], ri[sl],
                            rows, p0 + c0, k2, acc, tile)
            p0 += n
        sums = np.ascontiguousarray(acc[:, ai, ei].T)
        return torch.from_numpy(k2), torch.from_numpy(sums)

    def _scratch(self, name: str, shape: tuple, dtype) -> np.ndarray:
        """A buffer ``shape`` of ``dtype`` kept between blocks (its contents are not), so that a
        block's ``|img|^2`` (226 MB for 16 outgoing elements on matrix-1024) is not allocated and
        faulted in afresh each time."""
        size = int(np.prod(shape))
        buf = self._buffers.get(name)
        if buf is None or buf.dtype != dtype or buf.size < size:
            buf = self._buffers[name] = np.empty(size, dtype=dtype)
        return buf[:size].reshape(shape)

    def _lefts(self, Ba: torch.Tensor, Za: torch.Tensor):
        """Per pixel group, the left factor ``(n, 2 A, 4 w)`` (real) of the cross terms of the rows
        ``(B_a, Z_a)`` (each ``(A, cols)``): ``[re rows; im rows] x [re | im]`` against
        :meth:`rights`."""
        A = Ba.shape[0]
        rdt = self.model.dtype
        for n, w, o in self.groups:
            L = torch.view_as_real(torch.cat([Ba[:, o:o + n * w].reshape(A, n, w),
                                              Za[:, o:o + n * w].reshape(A, n, w)], 2)).permute(1, 0, 2, 3)
            left = torch.empty(n, 2, A, 4 * w, dtype=rdt)
            left[:, 0, :, :2 * w] = L[..., 0]
            left[:, 0, :, 2 * w:] = -L[..., 1]
            left[:, 1, :, :2 * w] = L[..., 1]
            left[:, 1, :, 2 * w:] = L[..., 0]
            yield left.reshape(n, 2 * A, 4 * w)

    def move_images(self, out: torch.Tensor, into: torch.Tensor) -> torch.Tensor:
        """The images ``(M, P)`` (complex, the fast path's pixel order) of the moves that switch
        ``out[i]`` off and ``into[i]`` on (``(M, m)`` long, ``-1`` pads), each from the rows of
        the elements it changes, ``dB = d @ B`` and ``dZ = d @ Z``: the image of ``gamma + dB``
        and ``z + dZ`` is ``img + sum_{j in p} (dB_j (z_j + dZ_j) + gamma_j dZ_j)``, one pass over
        the rows."""
        dB = dZ = None
        for idx, sign in ((out, -1.0), (into, 1.0)):
            for j in range(idx.shape[1]):
                e = idx[:, j]
                ok = e >= 0
                if not bool(ok.any()):
                    continue
                if bool(ok.all()):          # every move switches a j-th element: rows gathered as they are
                    Be, Ze = self._rows(e)
                else:
                    Be, Ze = self._rows(torch.where(ok, e, 0))
                    keep = ok.to(Be.real.dtype)[:, None]
                    Be, Ze = Be * keep, Ze * keep
                if dB is None:
                    dB, dZ = (Be, Ze) if sign > 0 else (Be.neg_(), Ze.neg_())
                else:
                    dB.add_(Be, alpha=sign)
                    dZ.add_(Ze, alpha=sign)
        cross = (dZ + self._z).mul_(dB).addcmul_(dZ, self._gamma[None].expand_as(dZ))
        return self._segsum(cross).add_(self._img[None])

    def block(self):
        """The requests this neighbourhood scores fastest (:class:`~arraysel.objective.contract.SwapBlock`):
        swaps grouped by outgoing element, each with every incoming element, one outgoing element a
        call. Blocks of four score more neighbours a second on a loaded machine (one product reads
        the right factors once for them all), but a descent moves only after a block: ``ils`` on
        matrix-1024 in 10 minutes ended at a median Mean of 0.0156 with blocks of one against 0.053
        with blocks of four (``benchmarks/results/compare-matrix-1024-10min``, ``-blocks4``)."""
        from arraysel.objective.contract import SwapBlock

        return SwapBlock(outgoing=1)

    def dense(self, out: np.ndarray) -> np.ndarray:
        """For each swap with the outgoing elements ``out``: whether it goes by the block path (its
        outgoing element's swaps fill at least :data:`DENSE_SHARE` of a row of Ne images)."""
        _, inv, counts = np.unique(out, return_inverse=True, return_counts=True)
        return (counts >= DENSE_SHARE * self.n_elements)[inv]

    def move_columns(self, out: np.ndarray, into: np.ndarray):
        """Yield ``(positions, {name: float64 (n,)})``: the metrics of the moves ``(out[i], into[i])``
        (``(B, m)``, ``-1`` pads) of the held selection at ``positions`` of the request. The swaps
        whose outgoing element has many (:meth:`dense`) go by blocks of outgoing elements against
        every element (:meth:`swap_power`); the other moves are formed from their own rows."""
        block = np.zeros(out.shape[0], dtype=bool)
        single = out.shape[1] == 1 or bool((out[:, 1:] < 0).all())
        if single and out.shape[0] and (out[:, 0] >= 0).all():
            block = self.dense(out[:, 0])
        if block.any():
            pos = np.flatnonzero(block)
            for p, res in self.swap_columns(out[pos, 0], into[pos, 0]):
                yield pos[p], res
        rest = np.flatnonzero(~block)
        cm = self.metrics()
        for s in range(0, rest.size, MOVE_BATCH):
            pos = rest[s:s + MOVE_BATCH]
            img = self.move_images(torch.as_tensor(out[pos]), torch.as_tensor(into[pos])).T
            yield pos, cm(img.real.contiguous(), img.imag.contiguous())

    def swap_columns(self, out: np.ndarray, into: np.ndarray):
        """Yield ``(positions, {name: float64 (n,)})``: the metrics of the swaps ``(out[i], into[i])``
        of the held selection at ``positions`` of the request, a block of :data:`BLOCK_ROWS`
        outgoing elements against every element at a time."""
        order = np.argsort(out, kind="stable")
        a_sorted = out[order]
        starts = np.flatnonzero(np.r_[True, a_sorted[1:] != a_sorted[:-1]])
        ends = np.r_[starts[1:], a_sorted.size]
        cm = self.metrics()
        for g in range(0, starts.size, BLOCK_ROWS):
            s0, s1 = starts[g:g + BLOCK_ROWS], ends[g:g + BLOCK_ROWS]
            pos = order[s0[0]:s1[-1]]
            rows, ins = np.repeat(np.arange(s0.size), s1 - s0), into[pos]
            _, keep, inv = np.unique(rows * self.n_elements + ins, return_index=True, return_inverse=True)
            k2, sums = self.swap_power(torch.as_tensor(a_sorted[s0], dtype=torch.long), rows[keep], ins[keep])
            res = cm.from_power(k2, sums[:, 0], sums[:, 1], sums[:, 2])
            yield pos, {k: v[inv] for k, v in res.items()}      # a swap asked for twice, scored once

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
        """``{name: float64 (total,)}`` of the metrics ``pieces`` yields as ``(positions, {name: values})``."""
        out: dict[str, np.ndarray] = {}
        for pos, res in pieces:
            for k, v in res.items():
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
