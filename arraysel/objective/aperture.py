"""Separate transmit and receive apertures (``docs/apertures.md``): the scene's ``[aperture]``
section chooses what a selection is.

* ``mode = "shared"`` (default): one mask transmits and receives (the scene's objective itself;
  this module is not involved);
* ``mode = "full-tx"``: every element transmits, the selection of ``k`` elements receives. The
  selector sees the probe's ``Ne`` elements and ``k``, so every selector works unchanged; the
  mask is the receive aperture;
* ``mode = "separate"``: two selections, ``k_tx`` transmit and ``k_rx`` receive elements. The
  selector sees a **virtual problem of 2 Ne units**: units ``0 .. Ne - 1`` are the transmit
  elements, units ``Ne .. 2 Ne - 1`` the receive elements (unit ``Ne + e`` is element ``e``
  receiving), ``k = k_tx + k_rx``, and the quota (exactly ``k_tx`` of the first half and ``k_rx``
  of the second) as channel groups with a count each
  (:func:`~arraysel.constraints.aperture_constraints`), which every built-in selector honours
  by construction. Its layout (:attr:`ApertureObjective.element_grid`,
  :attr:`~ApertureObjective.element_positions`) places the receive aperture beside the transmit
  aperture: a matrix probe's receive rows below its transmit rows (grid ``(2 ny, nx)``), a 1-D
  probe's receive elements after its transmit elements along x.

:class:`ApertureObjective` wraps the scene's objective (1-D, 3-D or sector) and scores a mask as
its transmit and receive weights through the objective's ``receive=`` keyword (the 1-D exact
path, the 3-D fast and exact paths, the sector's beam pattern).
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np
import torch

from arraysel.constraints import aperture_constraints
from arraysel.errors import NumericalError, ParameterError, SelectionError
from arraysel.objective.contract import WorkerFactory, hessian_by_rows
from arraysel.objective.losses import training_loss

__all__ = ["APERTURE_MODES", "ApertureObjective", "ApertureObjectiveFactory", "split_apertures"]

_log = logging.getLogger(__name__)

#: the values of the scene key ``aperture.mode``
APERTURE_MODES = ("shared", "full-tx", "separate", "per-transmit")


def split_events(elements, n_probe: int, n_events: int) -> tuple[list[list[int]], list[int]]:
    """The transmit elements of each transmit event and the receive elements of a
    ``per-transmit`` selection ``elements`` (units: block ``n`` of ``n_probe`` units is event
    ``n``'s transmit aperture, the last block the receive aperture)."""
    n, sel = int(n_probe), sorted(int(e) for e in elements)
    events = [[e - b * n for e in sel if b * n <= e < (b + 1) * n] for b in range(int(n_events))]
    return events, [e - int(n_events) * n for e in sel if e >= int(n_events) * n]


def split_apertures(elements, n_probe: int, mode: str, n_events: int = 1) -> tuple[list[int], list[int]]:
    """The transmit and receive elements of a selection ``elements`` (indices of the selector's
    problem) under ``mode``: ``shared`` both the selection, ``full-tx`` every element and the
    selection, ``separate`` the units below ``n_probe`` and those above less ``n_probe``,
    ``per-transmit`` the elements that transmit in any of the ``n_events`` events
    (:func:`split_events` gives each event's) and the receive block's."""
    sel = sorted(int(e) for e in elements)
    if mode == "shared":
        return sel, sel
    if mode == "full-tx":
        return list(range(int(n_probe))), sel
    if mode == "separate":
        return [e for e in sel if e < n_probe], [e - n_probe for e in sel if e >= n_probe]
    if mode == "per-transmit":
        events, rx = split_events(sel, n_probe, n_events)
        return sorted(set().union(*events)), rx
    raise ParameterError(f"aperture.mode = {mode!r}; allowed: {', '.join(APERTURE_MODES)}")


class ApertureObjective:
    """The scene objective ``inner`` seen through the aperture ``mode`` (module docstring).

    Parameters
    ----------
    inner : the scene's objective (its ``evaluate``, ``mask_loss`` and ``psf_terms`` take
        ``receive=`` weights)
    mode : ``"full-tx"``, ``"separate"`` or ``"per-transmit"`` (a matrix-probe scene scored on
        planes: one transmit aperture per transmit event and one receive aperture)
    k_tx, k_rx : the transmit (of each event) and receive counts (each in ``[1, Ne]``)

    Attributes it does not define are ``inner``'s (the scene, the settings, the counters).
    """

    def __init__(self, inner, mode: str, k_tx: int | None = None, k_rx: int | None = None):
        if mode not in APERTURE_MODES[1:]:
            raise ParameterError(f"aperture.mode = {mode!r}; ApertureObjective takes 'full-tx', 'separate' or "
                                 f"'per-transmit' (allowed in a scene: {', '.join(APERTURE_MODES)})")
        self._inner = inner
        self.aperture_mode = mode
        self.n_probe = n = int(inner.n_elements)
        #: transmit events with an aperture of their own (``per-transmit``; else 1)
        self.n_events = 1
        if mode == "per-transmit":
            if getattr(inner, "image_kind", None) != "planes" or hasattr(inner, "beam_metrics"):
                raise ParameterError("aperture.mode = 'per-transmit' applies to matrix-probe scenes imaged on planes "
                                     "(such as matrix-1024); allowed on this scene: shared, full-tx, separate")
            from arraysel.objective.imagers import transmit_events

            self.n_events = transmit_events(inner.imagers)
        if mode == "full-tx":
            self.n_elements, self.k = n, int(inner.k)
            self.constraints = getattr(inner, "constraints", None)
            self.k_tx, self.k_rx = n, int(inner.k)
        else:
            self.k_tx = int(inner.k if k_tx is None else k_tx)
            self.k_rx = int(inner.k if k_rx is None else k_rx)
            #: the quota and the scene's constraints, met by each aperture
            self.constraints = aperture_constraints(n, self.k_tx, self.k_rx, getattr(inner, "constraints", None),
                                                    n_events=self.n_events)
            self.n_elements, self.k = (self.n_events + 1) * n, self.n_events * self.k_tx + self.k_rx
        if hasattr(inner, "beam_metrics"):  # a sector scene: its exact per-beam scoring, both apertures
            self.beam_metrics = self._beam_metrics
        psfs = getattr(inner, "psfs", None)
        if psfs:  # a 1-D scene: the pair basis is symmetric in transmit and receive
            per = sum(p.exact_seconds_per_mask() for p in psfs)
            _log.warning("aperture.mode = %r on a 1-D scene: the PSF pair basis holds only the shared aperture, "
                         "so every mask is scored on the exact path: about %.3g s a mask (estimated)", mode, per)

    def __getattr__(self, name):
        if name.startswith("__") or name == "_inner":
            raise AttributeError(name)
        return getattr(self._inner, name)

    @property
    def inner(self):
        """The scene's objective (shared-aperture physics)."""
        return self._inner

    # -- layout of the selector's problem ------------------------------------------------------
    @property
    def element_grid(self):
        grid = getattr(self._inner, "element_grid", None)
        if grid is None or self.aperture_mode == "full-tx":
            return grid
        return ((self.n_events + 1) * int(grid[0]), int(grid[1]))

    @property
    def element_positions(self):
        pos = getattr(self._inner, "element_positions", None)
        if pos is None or self.aperture_mode == "full-tx":
            return pos
        pos = np.asarray(pos, dtype=np.float64)
        axis = 1 if getattr(self._inner, "element_grid", None) is not None else 0
        span = float(np.ptp(pos[:, axis]))
        steps = np.diff(np.unique(np.round(pos[:, axis], 12)))
        gap = float(steps.min()) if steps.size else 1e-3
        blocks = [pos.copy() for _ in range(self.n_events + 1)]
        for b, block in enumerate(blocks):
            block[:, axis] += b * (span + gap)
        return np.concatenate(blocks)

    # -- masks -> transmit and receive weights ---------------------------------------------------
    def _tensor(self, masks) -> torch.Tensor:
        m = masks if isinstance(masks, torch.Tensor) else torch.as_tensor(np.asarray(masks, dtype=np.float64))
        if m.dim() == 1:
            m = m[None]
        if m.dim() != 2 or m.shape[1] != self.n_elements:
            raise SelectionError(f"masks must have shape (B, {self.n_elements}), got {tuple(m.shape)}")
        return m

    def apertures(self, masks) -> tuple[torch.Tensor, torch.Tensor]:
        """``(transmit, receive)`` weights ``(B, Ne)`` each of masks ``(B, n_elements)``
        (``per-transmit``: transmit ``(B, n_events, Ne)``, one aperture per event); a selection
        without transmit (of an event) or without receive elements is refused."""
        m = self._tensor(masks)
        n, e = self.n_probe, self.n_events
        if self.aperture_mode == "full-tx":
            return torch.ones_like(m), m
        tx, rx = m[:, :e * n], m[:, e * n:]
        for name, w in (("transmit", tx.reshape(-1, n)), ("receive", rx)):
            empty = torch.nonzero(w.detach().sum(1) == 0).flatten().tolist()
            if empty:
                where = f"batch position(s) {empty}" if e == 1 or name == "receive" else \
                    f"(batch position, transmit event) {[divmod(i, e) for i in empty]}"
                raise SelectionError(f"empty {name} aperture (no {name} element) at {where}")
        return (tx if e == 1 else tx.reshape(-1, e, n)), rx

    # -- the objective contract ---------------------------------------------------------------
    def evaluate(self, masks, **kwargs) -> dict:
        tx, rx = self.apertures(masks)
        return self._inner.evaluate(tx, receive=rx, **kwargs)

    def evaluate_indices(self, selections) -> dict:
        from arraysel.selection import masks_from_indices

        return self.evaluate(masks_from_indices(selections, self.n_elements, self.k))

    def evaluate_moves(self, mask, out, into) -> dict:
        from arraysel.objective.neighbours import check_moves, move_masks

        m, a, b = check_moves(mask, out, into)
        return self.evaluate(move_masks(m, a, b))

    def evaluate_swaps(self, mask, out, into) -> dict:
        return self.evaluate_moves(mask, np.asarray(out)[:, None], np.asarray(into)[:, None])

    def neighbourhood(self):
        """Neighbours scored as their masks (:meth:`evaluate_moves`): the inner objective's own
        neighbourhood is of one shared aperture and must not be reached through the forwarding."""
        from arraysel.objective.contract import MovesNeighbourhood

        return MovesNeighbourhood(self.evaluate_moves, self.prepare_neighbourhoods)

    def loss_model(self):
        """The :class:`~arraysel.objective.contract.LossModel` of this objective's
        :meth:`mask_loss` (the selector's units), not of the inner objective's."""
        from arraysel.objective.contract import AutogradLossModel

        return AutogradLossModel(self.mask_loss, self._inner.dtype, self._inner.device, hessian=self.mask_hessian)

    def prepare_neighbourhoods(self) -> bool:
        """Nothing to form: a neighbour is scored as its masks (the inner objective's shared
        neighbourhood structures do not apply to two apertures)."""
        return True

    def mask_loss(self, weights):
        w = weights if weights.dim() == 2 else weights[None]
        tx, rx = self.apertures(w)
        return self._inner.mask_loss(tx, receive=rx)

    def mask_hessian(self, mask):
        return hessian_by_rows(self.mask_loss, mask, dtype=self._inner.dtype, device=self._inner.device)

    def selection_loss(self, P: torch.Tensor, P_soft: torch.Tensor, step: int = 0):
        """Training loss of a ``(n_elements, k)`` selection matrix: the PSF terms of its row sums
        (clamped to [0, 1]) as transmit and receive weights, ``L_ent`` and ``L_row`` on ``P_soft``."""
        inner = self._inner
        if P.dim() != 2 or P.shape[0] != self.n_elements:
            raise SelectionError(f"P must have shape ({self.n_elements}, k), got {tuple(P.shape)}")
        tx, rx = self.apertures(P.sum(1).clamp(0, 1)[None])
        psf = inner._psf_loss(tx, receive=rx)[1]
        total, terms = training_loss({k: v.sum() for k, v in psf.items()}, inner.weights, P_soft=P_soft)
        if not bool(torch.isfinite(total.detach())):
            raise NumericalError("selection_loss is not finite (NaN/Inf)")
        inner.evaluations += 1
        if P.requires_grad:
            inner.gradient_steps += 1
        return total, terms

    def _beam_metrics(self, masks, points=None) -> dict:
        """A sector scene's exact per-beam metrics of the masks' transmit and receive apertures."""
        tx, rx = self.apertures(masks)
        return self._inner.beam_metrics(tx, points, receive=rx)

    def fresh_random_masks(self, n: int | None = None, seed: int = 0) -> np.ndarray:
        """Fresh random selections of the selector's problem (``separate``, ``per-transmit``:
        uniformly random feasible ones; ``full-tx``: the scene's)."""
        if self.aperture_mode == "full-tx":
            return self._inner.fresh_random_masks(n, seed)
        n = self._inner.fresh_random if n is None else int(n)
        return self.constraints.random_masks(np.random.default_rng(seed), n)

    def split(self, elements) -> tuple[list[int], list[int]]:
        """The transmit and receive elements of a selection (:func:`split_apertures`)."""
        return split_apertures(elements, self.n_probe, self.aperture_mode, self.n_events)

    def worker_factory(self):
        f = self._inner.worker_factory()
        return None if f is None else ApertureObjectiveFactory(f, self.aperture_mode, self.k_tx, self.k_rx)

    def reset_counters(self):
        self._inner.reset_counters()


@dataclasses.dataclass(frozen=True)
class ApertureObjectiveFactory(WorkerFactory):
    """Builds :class:`ApertureObjective` on a worker from the inner objective's factory."""

    inner: object
    mode: str
    k_tx: int
    k_rx: int

    def __hash__(self):
        return hash(self.key())

    def __call__(self):
        return ApertureObjective(self.inner(), self.mode, self.k_tx, self.k_rx)
