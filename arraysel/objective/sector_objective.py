"""Sector scenes (``docs/sector.md``): search on the two-way beam pattern over the steered sector,
score on the points' PSFs, per beam.

A sector scene is scored by the one :class:`~arraysel.objective.psf_objective.Objective` over its
imager (:func:`~arraysel.objective.imagers.scene_imagers`): a
:class:`~arraysel.physics.imaging.PatternImager`, the cheap, differentiable beam pattern
(:class:`~arraysel.physics.beampattern.BeamPattern` over the sector), whose plane set is scored by
:meth:`~arraysel.objective.beam_objective.BeamPatternScorer.search_terms` under the Table-1 names:

* ``L_SLR_q``: ``10^(PSL/20)``, the worst beam's peak side lobe, as an amplitude ratio;
* ``L_SLR_i``: ``10^(ISLR/10)``, the sector's mean integrated side-lobe ratio;
* ``L_contrast``: the mean side-lobe power over the mean main-lobe power (each beam's view
  weighted by the share of the sector's beams that see it);
* ``L_PSF``: the scale-invariant MSE of the amplitude pattern against the full array's (its main
  lobe's width and shape); ``L_SLR`` and ``Mean`` as in Table 1.

The pattern's ``PSL_dB``, ``ISLR_dB`` and -6 dB widths in u and v go into each row as
``bp_PSL_dB``, ``bp_ISLR_dB``, ``bp_width_u_6dB``, ``bp_width_v_6dB`` (:data:`SEARCH_COLUMNS`).

Its points are read the way a designer reads them by the objective's per-beam view
(``Objective.beams``, :class:`~arraysel.objective.sector_beams.SectorBeams`: one imager per point,
the point's PSF on its surface over the sector, exact or fast, scored per beam by
:meth:`~arraysel.objective.sector_beams.SectorBeams.beam_metrics`; its names are re-exported here).

:func:`SectorObjective` builds that objective and checks that the scene is a sector scene;
:class:`SectorObjectiveFactory` is the worker recipe of the same name. Both stay for code written
against them; new code calls :func:`arraysel.objective.build.build_objective`.
"""
from __future__ import annotations

import torch

from arraysel.errors import ParameterError
from arraysel.objective.beam_objective import SEARCH_COLUMNS
from arraysel.objective.imagers import DEFAULT_CHUNK_PATTERN
from arraysel.objective.psf_objective import Objective, SceneObjectiveFactory
from arraysel.objective.sector_beams import (BEAM_COLUMNS, SECTOR_FAST_VERSION, SectorBeams, SectorPointImager,
                                             point_label, sector_fast_state)
from arraysel.scenes.schema import Scene, load_scene

__all__ = ["SectorObjective", "SectorObjectiveFactory", "SectorBeams", "SectorPointImager", "BEAM_COLUMNS",
           "SEARCH_COLUMNS", "SECTOR_FAST_VERSION", "point_label", "sector_fast_state"]


def SectorObjective(scene: Scene | str = "matrix-1024-sector", device="cpu", dtype=torch.float32,
                    chunk: int = DEFAULT_CHUNK_PATTERN, fast: bool = True) -> Objective:
    """The :class:`~arraysel.objective.psf_objective.Objective` of a sector scene (a scene with a
    ``[sector]`` section, or its name/path; module docstring). ``chunk``: masks per batch of
    ``evaluate`` and of the points' fast path (their exact path runs one selection at a time);
    ``fast`` False: the points' exact path only."""
    sc = load_scene(scene) if not isinstance(scene, Scene) else scene
    if not sc.is_sector:
        raise ParameterError(f"scene {sc.name!r} has no [sector] section: it is not a sector scene")
    return Objective(sc, device=device, dtype=dtype, chunk=chunk, fast=fast)


class SectorObjectiveFactory(SceneObjectiveFactory):
    """The worker recipe of a sector scene's objective (fields as
    :class:`~arraysel.objective.psf_objective.SceneObjectiveFactory`, which it is)."""

    def __hash__(self):
        return hash(self.key())
