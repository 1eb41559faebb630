"""The objective contract: what a selector, an experiment and an executor may rely on.

:class:`ObjectiveContract` is a :class:`typing.Protocol` (structural: an objective does not
inherit from it). :class:`arraysel.objective.psf_objective.Objective` and
:class:`arraysel.objective.toy.ToyObjective` follow it; so can a user's own objective.

Capability: an objective that can be rebuilt in another process has a ``worker_factory()``
method returning a picklable zero-argument callable that builds an equal objective (a
:class:`WorkerFactory`), or ``None`` when it cannot. Executors and isolated runs use it
(:func:`arraysel.run.workers.objective_factory_for`); they never look at the objective's class.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from typing import Any, Callable, Protocol, runtime_checkable

__all__ = ["ObjectiveContract", "Rebuildable", "WorkerFactory", "dtype_name"]


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
