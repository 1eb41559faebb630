"""The objective of a 3-D scene, under its former names.

A 3-D scene (a ``[volume]`` section, ``docs/matrix.md``) is scored by the one
:class:`~arraysel.objective.psf_objective.Objective` over its imager
(:class:`~arraysel.physics.imaging.VolumeImager`, the three planes of the 3-D PSF through the
scatterer; :func:`~arraysel.objective.imagers.matrix_model` gives its fast path or the exact path).
:func:`MatrixObjective` builds that objective and checks that the scene is 3-D;
:class:`MatrixObjectiveFactory` is the worker recipe of the same name. Both stay for code written
against them; new code calls :func:`arraysel.objective.build.build_objective`.
"""
from __future__ import annotations

import torch

from arraysel.errors import ParameterError
from arraysel.objective.imagers import DEFAULT_CHUNK_3D, FAST_VERSION, MAX_REPLICAS, matrix_model
from arraysel.objective.psf_objective import Objective, SceneObjectiveFactory
from arraysel.scenes.schema import Scene, load_scene

__all__ = ["MatrixObjective", "MatrixObjectiveFactory", "matrix_model", "FAST_VERSION", "MAX_REPLICAS",
           "DEFAULT_CHUNK_3D"]


def MatrixObjective(scene: Scene | str = "matrix-1024", device="cpu", dtype=torch.float32,
                    chunk: int = DEFAULT_CHUNK_3D, fast: bool = True) -> Objective:
    """The :class:`~arraysel.objective.psf_objective.Objective` of a 3-D scene (a scene with a
    ``[volume]`` section or its name/path); ``fast`` False: the exact path only."""
    sc = load_scene(scene) if not isinstance(scene, Scene) else scene
    if not sc.is_volume:
        raise ParameterError(f"scene {sc.name!r} has no [volume] section: use Objective for it")
    return Objective(sc, device=device, dtype=dtype, chunk=chunk, fast=fast)


class MatrixObjectiveFactory(SceneObjectiveFactory):
    """The worker recipe of a 3-D scene's objective (fields as
    :class:`~arraysel.objective.psf_objective.SceneObjectiveFactory`, which it is)."""

    def __hash__(self):
        return hash(self.key())
