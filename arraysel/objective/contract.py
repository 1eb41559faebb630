"""The objective contract: what a selector, an experiment and an executor may rely on.

:class:`ObjectiveContract` is a :class:`typing.Protocol` (structural: an objective does not
inherit from it). :class:`arraysel.objective.psf_objective.Objective` and
:class:`arraysel.objective.toy.ToyObjective` follow it; so can a user's own objective.

Capability: an objective that can be rebuilt in another process has a ``worker_factory()``
method returning a picklable zero-argument callable that builds an equal objective (a
:class:`WorkerFactory`), or ``None`` when it cannot. Executors and isolated runs use it
(:func:`arraysel.run.workers.objective_factory_for`); they never look at the objective's class.

Capability: an objective may score the one-swap neighbours of a selection in one call
(:class:`ScoresSwaps`): ``evaluate_swaps(mask, out, into)`` returns what ``evaluate`` returns for
the masks ``mask`` with element ``out[i]`` switched off and ``into[i]`` switched on, the same
values as scoring those masks independently, exploiting what they share.
:func:`arraysel.objective.neighbours.evaluate_swaps` calls it, and scores the masks with
``evaluate`` for an objective without it. More generally (:class:`ScoresMoves`),
``evaluate_moves(mask, out, into)`` scores neighbours that switch up to ``m`` elements each
(``out``, ``into`` of shape ``(B, m)``, padded with ``-1``;
:func:`arraysel.objective.neighbours.evaluate_moves`).

Capability: an objective may give the *neighbourhood* of its selections (:class:`Neighbourhood`):
``objective.neighbourhood()`` returns an object that scores a selection's neighbours (the
selection with a few elements switched off and as many on) in one call, exploiting what they
share, or ``None`` when it has no such scoring (its neighbours are then scored as masks). A
search asks for it once, through :func:`arraysel.objective.neighbours.neighbourhood_of`, which also
reads an objective written
before this method existed (its ``evaluate_moves`` / ``evaluate_swaps`` /
``prepare_neighbourhoods`` methods, :class:`ScoresSwaps`, :class:`ScoresMoves`).

Capability: an objective may give a *model of its loss* (:class:`LossModel`):
``objective.loss_model()`` returns an object with the gradient and the Hessian of ``mask_loss`` at
a selection, or ``None`` when its loss has none. A search asks for it once, through
:func:`loss_model_of`; an objective without the method gets one formed by autograd from its
``mask_loss`` (its own ``mask_hessian`` where it has one, :class:`HasHessian`).

Capability: an objective may say how its elements are laid out (:class:`HasLayout`):
``element_grid`` is ``(ny, nx)`` for a matrix array (element index ``iy * nx + ix``) or ``None`` for a
1-D array, and ``element_positions`` the element centres, a numpy ``(Ne, 3)`` array of (x, y, z) in
metres. Selectors read them through :func:`element_layout`, which treats an objective without them
as a 1-D array.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from arraysel.errors import ParameterError, check_number

__all__ = ["ObjectiveContract", "Rebuildable", "HasLayout", "ScoresSwaps", "ScoresMoves", "HasHessian", "WorkerFactory",
           "Neighbourhood", "SwapBlock", "LossModel", "MovesNeighbourhood", "AutogradLossModel", "loss_model_of", "ObjectiveInfo", "objective_info", "worker_factory_of", "missing_members",
           "dtype_name", "hessian_by_rows",
           "check_element_grid", "element_layout"]


@runtime_checkable
class ObjectiveContract(Protocol):
    """Counters, sizes and the evaluation a selector needs (``docs/selectors.md``)."""

    n_elements: int
    k: int
    evaluations: int
    gradient_steps: int
    seconds: float

    def evaluate(self, masks) -> dict:
        """Metrics of hard masks ``(B, Ne)``: ``{name: float64 array (B,)}``, no gradient."""

    def mask_loss(self, weights) -> tuple[Any, dict]:
        """Differentiable loss of soft weights ``(B, Ne)``: ``(total (B,), terms)``."""

    def selection_loss(self, P, P_soft, step: int) -> tuple[Any, dict]:
        """Differentiable loss of a selection matrix ``(Ne, k)``: ``(scalar total, terms)``."""


@runtime_checkable
class Rebuildable(Protocol):
    """An objective that can be sent to worker processes as a recipe."""

    def worker_factory(self) -> Callable[[], Any] | None:
        ...


@runtime_checkable
class ScoresSwaps(Protocol):
    """An objective that scores a selection's one-swap neighbours in one call (optional capability).

    ``evaluate_swaps(mask, out, into)``: ``mask`` a boolean ``(Ne,)`` selection, ``out`` and
    ``into`` int arrays ``(B,)`` with ``mask[out]`` all True and ``mask[into]`` all False; returns
    ``{name: float64 array (B,)}`` equal to ``evaluate`` of the ``B`` neighbour masks, and counts
    ``B`` evaluations."""

    def evaluate_swaps(self, mask, out, into) -> dict:
        ...


@runtime_checkable
class ScoresMoves(Protocol):
    """An objective that scores a selection's neighbours of m-element moves in one call (optional
    capability).

    ``evaluate_moves(mask, out, into)``: ``mask`` a boolean ``(Ne,)`` selection, ``out`` and
    ``into`` int arrays ``(B, m)`` with ``mask[out]`` all True, ``mask[into]`` all False and no
    element twice in a row, a row of fewer elements padded with ``-1`` (as many in ``out[i]`` as
    in ``into[i]``); returns ``{name: float64 array (B,)}`` equal to ``evaluate`` of the ``B``
    masks with ``out[i]`` switched off and ``into[i]`` on, and counts ``B`` evaluations."""

    def evaluate_moves(self, mask, out, into) -> dict:
        ...


@runtime_checkable
class HasHessian(Protocol):
    """An objective that gives the gradient and the Hessian of its ``mask_loss`` at a selection
    (optional capability: the quadratic model by which swap descents rank swaps,
    ``model = quadratic``).

    ``mask_hessian(mask)``: ``mask`` a boolean or 0/1 ``(Ne,)`` selection; returns ``(g, H)``,
    float64 arrays ``(Ne,)`` and ``(Ne, Ne)``, and counts ``Ne`` evaluations. An objective without
    it gets the same from :func:`hessian_by_rows` on its ``mask_loss``."""

    def mask_hessian(self, mask) -> tuple[np.ndarray, np.ndarray]:
        ...


def hessian_by_rows(mask_loss, mask, dtype=None, device="cpu") -> tuple[np.ndarray, np.ndarray]:
    """The gradient ``(Ne,)`` and the Hessian ``(Ne, Ne)`` (float64) of any differentiable
    ``mask_loss`` (weights ``(B, Ne)`` to ``(total (B,), terms)``) at ``mask``: the loss of ``Ne``
    copies of ``mask`` in one call, differentiated once, then row ``i``'s gradient element ``i``
    differentiated again (row ``i`` of the Hessian). ``mask_loss`` sees, and counts, ``Ne`` weight
    vectors."""
    import torch

    m = np.asarray(mask, dtype=np.float64).reshape(-1)
    n = m.size
    w = torch.tensor(np.repeat(m[None], n, axis=0), dtype=dtype or torch.float32,
                     device=device).requires_grad_(True)
    total, _terms = mask_loss(w)
    (grads,) = torch.autograd.grad(total.sum(), w, create_graph=True)
    (H,) = torch.autograd.grad(torch.diagonal(grads).sum(), w)
    return grads.detach()[0].double().cpu().numpy(), H.detach().double().cpu().numpy()


@runtime_checkable
class Neighbourhood(Protocol):
    """Scores the neighbours of a selection in one call (the capability ``objective.neighbourhood()``
    gives; :func:`~arraysel.objective.neighbours.neighbourhood_of`).

    ``evaluate(mask, out, into)``: ``mask`` a boolean ``(Ne,)`` selection, ``out`` and ``into`` int
    arrays ``(B, m)`` (or ``(B,)`` for one-swaps) with ``mask[out]`` all True, ``mask[into]`` all
    False, rows padded with ``-1`` (as for :class:`ScoresMoves`); returns ``{name: float64 (B,)}``
    equal, to rounding, to the objective's ``evaluate`` of the ``B`` neighbour masks, and counts
    ``B`` evaluations on the objective. ``prepare()`` does the one-off work the scoring shares
    between selections (the runners call it before a run's budget starts). ``block()`` says how a
    search should ask for one-swaps to score them fastest: a :class:`SwapBlock` (a few outgoing
    elements a call, each with all its incoming ones), or None (any set of swaps is as cheap a
    neighbour; :func:`~arraysel.objective.neighbours.neighbourhood_of` gives an object without
    this method one that answers None)."""

    def evaluate(self, mask, out, into) -> dict:
        ...

    def prepare(self) -> None:
        ...

    def block(self) -> "SwapBlock | None":
        ...


@dataclasses.dataclass(frozen=True)
class SwapBlock:
    """The one-swap requests a :class:`Neighbourhood` scores fastest: ``outgoing`` outgoing elements
    a call, each swapped with every incoming element a search allows it (a matrix scene's
    neighbourhood forms such a block by batched products; a neighbour of it costs a fraction of one
    asked alone)."""

    outgoing: int

    def __post_init__(self):
        if int(self.outgoing) < 1:
            raise ParameterError(f"SwapBlock.outgoing must be at least 1, got {self.outgoing}")


@runtime_checkable
class LossModel(Protocol):
    """The local model of an objective's ``mask_loss`` at a selection (the capability
    ``objective.loss_model()`` gives; :func:`loss_model_of`): by it a descent orders its moves.

    ``gradient(mask)``: the gradient ``(Ne,)`` float64 of ``mask_loss`` at the weights ``mask``
    (``(Ne,)``, 0/1 or soft), one evaluation and one gradient step; ``model(mask)``: ``(g, H)``,
    the gradient and the Hessian ``(Ne, Ne)`` float64 at a 0/1 selection, ``Ne`` evaluations.
    Either raises :class:`~arraysel.errors.NumericalError` where the loss is not finite."""

    def gradient(self, mask) -> np.ndarray:
        ...

    def model(self, mask) -> tuple[np.ndarray, np.ndarray]:
        ...


class MovesNeighbourhood:
    """A :class:`Neighbourhood` made of an objective's methods: ``evaluate_moves(mask, out, into)``
    (``(B, m)`` moves) and, optionally, ``prepare()``; ``block`` the :class:`SwapBlock` it prefers
    (None: none)."""

    def __init__(self, evaluate_moves: Callable, prepare: Callable | None = None, block: "SwapBlock | None" = None):
        self._evaluate_moves = evaluate_moves
        self._prepare = prepare
        self._block = block

    def block(self) -> "SwapBlock | None":
        return self._block

    def evaluate(self, mask, out, into) -> dict:
        return self._evaluate_moves(mask, out, into)

    def prepare(self) -> None:
        if self._prepare is not None:
            self._prepare()


class AutogradLossModel:
    """A :class:`LossModel` by autograd of a ``mask_loss`` (weights ``(B, Ne)`` to ``(total (B,),
    terms)``): the gradient by one backward pass; the Hessian by ``hessian`` (an objective's own
    ``mask_hessian(mask) -> (g, H)``) when given, else :func:`hessian_by_rows`."""

    def __init__(self, mask_loss: Callable, dtype=None, device="cpu", hessian: Callable | None = None):
        self.mask_loss, self.dtype, self.device, self.hessian = mask_loss, dtype, device, hessian

    def gradient(self, mask) -> np.ndarray:
        import torch

        w = torch.tensor(np.asarray(mask, dtype=np.float64).reshape(1, -1), dtype=self.dtype or torch.float32,
                         device=self.device).requires_grad_(True)
        total, _terms = self.mask_loss(w)
        (g,) = torch.autograd.grad(total.sum(), w)
        return g.detach()[0].double().cpu().numpy()

    def model(self, mask) -> tuple[np.ndarray, np.ndarray]:
        if self.hessian is not None:
            return self.hessian(mask)
        return hessian_by_rows(self.mask_loss, mask, self.dtype, self.device)


def loss_model_of(objective) -> LossModel | None:
    """The :class:`LossModel` of ``objective``: its ``loss_model()``; for an objective without that
    method, :class:`AutogradLossModel` of its ``mask_loss`` (with its ``mask_hessian`` where it has
    one), or ``None`` without a ``mask_loss``. The one place the optional methods are looked up."""
    own = getattr(objective, "loss_model", None)
    if callable(own):
        return own()
    loss = getattr(objective, "mask_loss", None)
    if not callable(loss):
        return None
    hessian = getattr(objective, "mask_hessian", None)
    return AutogradLossModel(loss, getattr(objective, "dtype", None), getattr(objective, "device", "cpu"),
                             hessian if callable(hessian) else None)


@runtime_checkable
class HasLayout(Protocol):
    """An objective that says how its elements are laid out (optional capability)."""

    #: ``(ny, nx)`` for a matrix array (element index ``iy * nx + ix``), ``None`` for a 1-D array
    element_grid: tuple[int, int] | None
    #: element centres, numpy ``(Ne, 3)``: (x, y, z) in metres, in element-index order
    element_positions: Any


#: what an objective scores a selection's image as: a 2-D kernel per field point (``kernel``: the
#: 1-D objective, the toy), a 3-D PSF's planes (``planes``: a matrix scene) or a sector's beam
#: pattern (``beams``)
KINDS = ("kernel", "planes", "beams")


@dataclasses.dataclass(frozen=True)
class ObjectiveInfo:
    """What an objective says about itself beyond the contract's required members, read once by
    :func:`objective_info`; an objective that does not say a thing gets the default here."""

    #: one of :data:`KINDS`: ``beams`` for an objective with ``beam_metrics``, ``planes`` for one
    #: whose ``image_kind`` is ``planes`` (a 3-D scene), else ``kernel``
    kind: str = "kernel"
    #: its :class:`~arraysel.scenes.scene.Scene` (``scene``), None without one (the toy objective)
    scene: Any = None
    #: ``device`` and ``dtype`` (None: not said)
    device: Any = None
    dtype: Any = None
    #: masks per batch of ``evaluate`` (``chunk``; None: not said)
    chunk: int | None = None
    #: extra result keys of ``evaluate`` a run's row keeps (``breakdown_names``)
    breakdown_names: tuple[str, ...] = ()
    #: the metrics' radii and scales of a ``kernel`` objective (``metric_kw``; None: not said)
    metric_kw: dict | None = None
    #: the element pitch in metres (``setup.pitch``; None: not said)
    pitch: float | None = None
    #: separate transmit and receive apertures (``aperture_mode``: ``full-tx``, ``separate``, ``per-transmit``;
    #: None: one shared aperture, :mod:`arraysel.objective.aperture`)
    aperture_mode: str | None = None
    #: transmit events with an aperture of their own (``aperture_mode`` ``per-transmit``), else 1
    aperture_events: int = 1
    #: the scene's objective under a wrapper of one (an aperture objective's ``inner``), else the
    #: objective itself
    scene_objective: Any = None

    @property
    def scene_name(self) -> str | None:
        return None if self.scene is None else getattr(self.scene, "name", None)


def objective_info(objective) -> ObjectiveInfo:
    """The :class:`ObjectiveInfo` of ``objective`` (the one place its optional attributes are
    read; selectors and runners ask here)."""
    kind = "beams" if hasattr(objective, "beam_metrics") else \
        "planes" if getattr(objective, "image_kind", None) == "planes" else "kernel"
    chunk = getattr(objective, "chunk", None)
    kw = getattr(objective, "metric_kw", None)
    return ObjectiveInfo(kind=kind, scene=getattr(objective, "scene", None), device=getattr(objective, "device", None),
                         dtype=getattr(objective, "dtype", None), chunk=None if chunk is None else int(chunk),
                         breakdown_names=tuple(getattr(objective, "breakdown_names", ()) or ()),
                         metric_kw=None if kw is None else dict(kw),
                         pitch=getattr(getattr(objective, "setup", None), "pitch", None),
                         aperture_mode=getattr(objective, "aperture_mode", None),
                         aperture_events=int(getattr(objective, "n_events", 1) or 1),
                         scene_objective=getattr(objective, "inner", objective))


def worker_factory_of(objective) -> Callable[[], Any] | None:
    """``objective.worker_factory()`` (:class:`Rebuildable`), or None for an objective without it."""
    make = getattr(objective, "worker_factory", None)
    return make() if callable(make) else None


def missing_members(objective, names=("n_elements", "k", "evaluate")) -> list[str]:
    """The members of the contract among ``names`` that ``objective`` lacks."""
    return [name for name in names if not hasattr(objective, name)]


def check_element_grid(grid, n_elements: int | None = None) -> tuple[int, int]:
    """``grid`` as ``(ny, nx)`` of positive ints; with ``n_elements``, ``ny * nx`` must equal it
    (:class:`~arraysel.errors.ParameterError` naming the key otherwise)."""
    try:
        ny, nx = grid
    except (TypeError, ValueError):
        raise ParameterError(f"element_grid must be (ny, nx), got {grid!r}") from None
    ny = int(check_number("element_grid[0] (ny)", ny, lo=1, integer=True))
    nx = int(check_number("element_grid[1] (nx)", nx, lo=1, integer=True))
    if n_elements is not None and ny * nx != int(n_elements):
        raise ParameterError(f"element_grid = ({ny}, {nx}) holds {ny * nx} elements, but n_elements = {n_elements}")
    return ny, nx


def element_layout(objective) -> tuple[tuple[int, int] | None, np.ndarray | None]:
    """``(element_grid, element_positions)`` of an objective, validated; ``(None, None)`` when it
    does not declare them (a 1-D array). The grid must hold ``n_elements`` elements and the
    positions be ``(Ne, 3)`` and finite."""
    n = int(objective.n_elements)
    grid = getattr(objective, "element_grid", None)
    grid = None if grid is None else check_element_grid(grid, n)
    pos = getattr(objective, "element_positions", None)
    if pos is not None:
        pos = np.asarray(pos, dtype=np.float64)
        if pos.shape != (n, 3) or not np.isfinite(pos).all():
            raise ParameterError(f"element_positions must be a finite ({n}, 3) array of (x, y, z) in metres, "
                                 f"got shape {pos.shape}")
    return grid, pos


def dtype_name(dtype) -> str:
    """``torch.float32`` -> ``"float32"`` (a picklable, readable dtype)."""
    text = str(dtype)
    return text[len("torch."):] if text.startswith("torch.") else text


class WorkerFactory:
    """Base of the picklable objective recipes (frozen dataclasses): a stable :meth:`key` that names
    the objective in worker-side caches."""

    def key(self) -> str:
        fields = dataclasses.asdict(self)  # type: ignore[arg-type]
        text = json.dumps({"type": type(self).__name__, **fields}, sort_keys=True, default=str)
        return hashlib.sha1(text.encode()).hexdigest()[:16]
