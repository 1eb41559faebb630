"""A scene's imagers (:mod:`arraysel.physics.imaging`): the one place that tells a 1-D scene from a
3-D one and from a sector scene.

:func:`scene_imagers` gives a 1-D scene one :class:`~arraysel.physics.imaging.KernelImager` per
field point (each on its :class:`~arraysel.physics.psf.PSFModel`), a 3-D scene (a ``[volume]``
section) one :class:`~arraysel.physics.imaging.VolumeImager` on the planes model of
:func:`matrix_model` (the fast 3-D path, loaded from the cache (``arraysel cache``) or built and
checked against the exact path, else the exact path) and a sector scene (a ``[sector]`` section)
one :class:`~arraysel.physics.imaging.PatternImager`, its two-way beam pattern over the sector. The
:class:`~arraysel.objective.psf_objective.Objective` scores whatever plane sets they give.

What differs between the kinds besides their planes is here too: the time and memory notice of
the exact path (:func:`exact_notice`, :func:`estimate_seconds`), the neighbourhood that scores
all swaps of a selection of a 3-D scene from its own planes (:func:`neighbourhood_for`) and the
per-beam view of a sector scene's points (:func:`scene_beams`: one imager per point, on its
surface, :class:`~arraysel.objective.sector_beams.SectorBeams`).
"""
from __future__ import annotations

import hashlib
import logging

import numpy as np
import torch

from arraysel.objective.tensors import check_masks
from arraysel.physics.imaging import Imager, KernelImager, PatternImager, VolumeImager

__all__ = ["scene_imagers", "transmit_events", "scene_points", "scene_beams", "matrix_model", "exact_notice",
           "estimate_seconds", "neighbourhood_for", "default_chunk", "check_masks", "FAST_VERSION", "DEFAULT_CHUNK", "DEFAULT_CHUNK_3D",
           "DEFAULT_CHUNK_PATTERN"]

_log = logging.getLogger(__name__)

#: the version of the cached fast-path tensors of a 3-D scene (bumped when their meaning changes)
FAST_VERSION = 3
#: the most interpolation harmonics (``FastSettings.replicas``) the 3-D fast path's build tries
MAX_REPLICAS = 2
#: most masks per batch of ``Objective.evaluate`` on a 1-D scene; each model takes at most its
#: :meth:`~arraysel.physics.psf.operator.PSFModel.masks_per_batch` at once (a memory budget:
#: the paper scene 256, the 128-element built-in scenes about 200). Against 128 on the paper
#: scene: 1.85 against 2.18 ms a mask (six rounds of 3000 masks alternated in one process; the
#: image product on E runs 10 % faster on the larger batch) and 10.9-11.0 against 11.4-11.5 s
#: for 5000 masks whole-process, for a resident peak 0.2 GiB higher (1.40 against 1.18 GB).
#: The scores do not depend on it (the same CSV to the last digit).
DEFAULT_CHUNK = 256
#: masks per batch on a 3-D scene: the fast path's matrix product is most efficient from about
#: 128 masks (``benchmarks/bench_matrix_fast.py``)
DEFAULT_CHUNK_3D = 128
#: masks per batch on a sector scene (its beam pattern; its points' per-beam images on their fast path)
DEFAULT_CHUNK_PATTERN = 64
#: estimated seconds a mask of a sector scene's beam pattern
_PATTERN_SECONDS = 0.005


def scene_imagers(scene, settings, dtype=torch.float32, device="cpu", fast: bool = True) -> list[Imager]:
    """The imagers of ``scene`` (module docstring), read with its ``settings``
    (``Scene.objective_settings()``); ``fast`` False: the exact paths only (a sector scene: its
    points' per-beam images, :func:`scene_beams`)."""
    if scene.is_sector:
        from arraysel.physics.beampattern import BeamPattern

        setup = scene.sector_setup()
        pattern = BeamPattern.from_probe(setup.probe, scene.acquisition(),
                                         sector_deg=scene.sector_geometry()["half_angles"],
                                         n_freq=int(scene.value("sector", "n_freq")), dtype=dtype, device=device)
        return [PatternImager(pattern, setup)]
    if scene.is_volume:
        model, why = matrix_model(scene.matrix_setup(), settings.k, dtype, device, bool(fast) and settings.fast)
        return [VolumeImager(model, why)]
    from arraysel.physics.psf import PSFModel

    psfs = [PSFModel(s, dtype=dtype, device=device, fast=fast, margin=settings.fast_margin,
                     block=settings.fast_block) for s in scene.psf_setups()]
    if len(psfs) > 1:  # the points share the memory cap: each keeps its share of DAS plans
        for p in psfs:
            p.plan_cache_elements = max(1, p.plan_cache_limit() // len(psfs))
        for p in psfs:
            p.other_bytes = sum(q.plan_cache_bytes() + q.model_bytes() for q in psfs if q is not p)
    why = "disabled (fast=False)" if not fast else "unavailable (its precomputation is over its cap)"
    return [KernelImager(p, exact_reason=why if p.basis is None else None) for p in psfs]


def scene_points(scene) -> list:
    """The field points of ``scene``: ``(x, z)`` in metres (1-D, one per imager), the scatterer's
    ``(x, y, z)`` (3-D), a sector scene's points ``(x, y, z)`` (one per beam, :func:`scene_beams`)."""
    if scene.is_sector:
        return list(scene.sector_setup().points)
    return [scene.matrix_setup().scatterer] if scene.is_volume else scene.points()


def scene_beams(objective):
    """The per-beam view of a sector scene's objective
    (:class:`~arraysel.objective.sector_beams.SectorBeams`: its points' images on their surfaces,
    one imager per point, and their per-beam metrics), None for any other scene (a 1-D scene's is
    :class:`~arraysel.objective.beams1d.PSFBeams`, made on demand)."""
    if not objective.scene.is_sector:
        return None
    from arraysel.objective.sector_beams import SectorBeams

    return SectorBeams(objective)


def default_chunk(imagers: list[Imager]) -> int:
    """Masks per batch of ``Objective.evaluate`` when none is given."""
    if any(isinstance(im, PatternImager) for im in imagers):
        return DEFAULT_CHUNK_PATTERN
    return DEFAULT_CHUNK_3D if any(isinstance(im, VolumeImager) for im in imagers) else DEFAULT_CHUNK


def _fmt_seconds(sec: float) -> str:
    if sec < 1:
        return f"{sec * 1e3:.0f} ms"
    if sec < 120:
        return f"{sec:.1f} s"
    if sec < 7200:
        return f"{sec / 60:.1f} min"
    return f"{sec / 3600:.1f} h"


def estimate_seconds(imagers: list[Imager], n_masks: int, chunk: int) -> float:
    """Estimated wall time (s) of imaging ``n_masks`` masks on every imager: a 1-D point on its exact
    path by :meth:`~arraysel.physics.psf.PSFModel.exact_seconds_per_mask` (its fast path counts as
    free, milliseconds a mask), a 3-D scene about 10 ms a mask on its fast path, 1 s on its exact path, a sector scene's beam
    pattern 5 ms."""
    total = 0.0
    for im in imagers:
        if isinstance(im, PatternImager):
            total += n_masks * _PATTERN_SECONDS
        elif isinstance(im, VolumeImager):
            total += n_masks * (1.0 if im.exact else 0.01)
        elif im.exact:
            p = im.model
            total += n_masks * p.exact_seconds_per_mask(min(chunk, p.masks_per_batch(), max(1, n_masks)))
            if p._ref is None:  # the full array's reference kernel comes first, once
                total += p.exact_seconds_per_mask(1)
    return total


def exact_notice(name: str, imagers: list[Imager], chunk: int, n_masks: int | None = None) -> str:
    """One line saying that (and why) the scene ``name`` runs on an exact path, with its time (and for
    a 1-D scene its memory); or that every imager has its fast path."""
    if any(isinstance(im, PatternImager) for im in imagers):
        return f"scene {name!r}: search on the sector's two-way beam pattern"
    if any(isinstance(im, VolumeImager) for im in imagers):
        im = imagers[0]
        if not im.exact:
            return f"scene {name!r}: fast 3-D PSF path"
        return f"scene {name!r}: 3-D PSF fast path {im.exact_reason}; using the exact path (about 1 s per mask)"
    slow = [i for i, im in enumerate(imagers) if im.exact]
    if not slow:
        return f"scene {name!r}: fast PSF path on every field point"
    why = imagers[slow[0]].exact_reason
    where = "" if len(imagers) == 1 else f" for {len(slow)} of {len(imagers)} field points"
    per = sum(imagers[i].model.exact_seconds_per_mask() for i in slow)
    mem = max(p.exact_bytes(p.masks_per_batch()) for p in (imagers[i].model for i in slow))
    text = (f"scene {name!r}: PSF fast path {why}{where}; using the exact path: about "
            f"{_fmt_seconds(per)} per mask (estimated), memory up to {mem / 2 ** 30:.1f} GiB "
            f"(cap {imagers[slow[0]].model.memory_limit / 2 ** 30:.1f} GiB, ARRAYSEL_MEMORY_GIB)")
    if n_masks is not None:
        text += f"; {n_masks} mask(s): about {_fmt_seconds(estimate_seconds(imagers, n_masks, chunk))}"
    return text


def neighbourhood_for(objective):
    """The :class:`~arraysel.objective.matrix_neighbours.MatrixNeighbourhood` that scores all swaps
    of a selection of a 3-D scene from its planes, on the fast path on the CPU; None otherwise (the
    neighbours are then imaged by their imagers' ``image_moves``)."""
    ims = objective.imagers
    if len(ims) != 1 or not isinstance(ims[0], VolumeImager) or ims[0].exact or objective.device.type != "cpu":
        return None
    from arraysel.objective.matrix_neighbours import MatrixNeighbourhood

    return MatrixNeighbourhood(objective)


def _setup_key(setup) -> tuple:
    """A cache key of a :class:`~arraysel.physics.volume.MatrixPSFSetup` (its delays by digest)."""
    d = np.ascontiguousarray(setup.delays, dtype=np.float64)
    fields = (setup.probe, setup.acq, setup.scatterer, setup.half_x, setup.half_y, setup.half_z, setup.pixel,
              setup.planes, setup.reflectivity, setup.iq_bandwidth, setup.options)
    return (repr(fields), d.shape, hashlib.sha256(d.tobytes()).hexdigest())


def matrix_model(setup, k: int, dtype=torch.float32, device="cpu", fast: bool = True):
    """The planes model of ``setup``: ``(model, why)``. ``model`` is the fast path (from the
    on-disk cache, or built and checked against the exact path on the full array and two random
    selections of ``k`` elements, then cached) or, when ``fast`` is
    False or the fast path is refused, the exact :class:`~arraysel.physics.volume.MatrixPSF`;
    ``why`` is None, or the reason the exact path is used."""
    from arraysel import __version__
    from arraysel.io import cache
    from arraysel.physics.volume import MatrixPSF
    from arraysel.physics.volume.fast import FastPathUnavailable, FastSettings, MatrixFastPSF

    if not fast:
        return MatrixPSF(setup, dtype=dtype, device=device), "disabled (volume.fast = false)"
    base = FastSettings()
    refused: list[str] = []
    checks = check_masks(setup.probe.n_elements, k)

    def build() -> dict:
        # the fewest interpolation harmonics whose check is within a hundredth of the tolerance (a
        # sparse selection of a small array averages their error out less), else within it
        exact = MatrixPSF(setup, dtype=torch.float64)
        fallback = None
        for replicas in range(0, MAX_REPLICAS + 1):
            try:
                fast_model = MatrixFastPSF(exact, FastSettings(replicas=replicas), dtype=torch.float64,
                                           check_masks=checks)
            except FastPathUnavailable as exc:
                refused.append(str(exc))
                continue
            if fast_model.check["max_relative_error"] <= base.check_tol / 100:
                return fast_model.state()
            fallback = fallback or fast_model
        if fallback is not None:
            return fallback.state()
        return {"refused": torch.tensor(1)}

    def check(state: dict) -> None:
        if "refused" not in state:
            MatrixFastPSF.from_state(setup, state, base)

    key = (__version__, FAST_VERSION, _setup_key(setup), k, repr(base))
    state = cache.load_or_build("psf3-fast", key, build, what="the 3-D fast path", check=check)
    if "refused" in state:
        why = refused[0] if refused else "refused when it was built (its check against the exact path failed)"
        return MatrixPSF(setup, dtype=dtype, device=device), f"unavailable: {why}"
    return MatrixFastPSF.from_state(setup, state, base, dtype=dtype, device=device), None


def transmit_events(imagers) -> int:
    """The transmit events a selection may give apertures of their own (``aperture.mode =
    "per-transmit"``): those of a matrix scene imaged on planes, else 0."""
    from arraysel.physics.imaging import VolumeImager

    first = imagers[0] if imagers else None
    return int(first.setup.delays.shape[0]) if isinstance(first, VolumeImager) else 0
