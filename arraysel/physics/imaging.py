"""Imagers: element weights in, named complex images with their pixel positions out.

An :class:`Imager` turns a batch of element weights ``(B, Ne)`` (the same weights are the transmit
apodization and the receive channel weights) into a :class:`PlaneSet`: one or more named complex
images ``(B, H, W)`` with the position in metres of every pixel. It is the one seam between the
physics and the objective (:class:`~arraysel.objective.psf_objective.Objective`): the objective
scores plane sets and never asks which physics made them.

* :class:`KernelImager` (a 1-D probe, one field point): one plane, the point's PSF kernel (the
  ``window`` x ``window`` cut centred on its peak, unit L2 norm; :class:`~arraysel.physics.psf.PSFModel`:
  the certified fast path, the exact path where it does not settle). Its pixels lie on a regular
  grid of pitch ``pitch``; their positions are given relative to the window's centre pixel (the
  window moves with each selection's peak and the metrics measure distances from the peak).
* :class:`VolumeImager` (a matrix probe): the three planes of the 3-D PSF through the scatterer
  (``"xy"`` the C-plane, ``"xz"``, ``"yz"``; :class:`~arraysel.physics.volume.MatrixPSF` or its fast
  path), at their positions in the volume.
* :class:`PatternImager` (a sector scene's search): one plane, the two-way power beam pattern over
  the shifts of the steered sector (:class:`~arraysel.physics.beampattern.BeamPattern`), real, at
  its ``(du, dv, 0)`` positions in the u-v frame (:attr:`Imager.frame` ``"uv"``).

The full array's plane set (the reference of the metrics) comes from the same imager
(:meth:`Imager.reference`). A scene with several field points has one imager per point.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

__all__ = ["PlaneSet", "Imager", "KernelImager", "VolumeImager", "PatternImager", "KERNEL_PLANE", "PATTERN_PLANE"]

#: the name of a kernel imager's one plane
KERNEL_PLANE = "kernel"
#: the name of a pattern imager's one plane
PATTERN_PLANE = "pattern"


@dataclass(frozen=True)
class PlaneSet:
    """Named complex images of a batch of element weights, with their pixel positions.

    Attributes
    ----------
    images : ``{name: complex Tensor (B, H, W)}``, every plane with the same batch size ``B``
    coords : ``{name: float64 array (H, W, 3)}``, the (x, y, z) position in metres of each pixel
    pitch : ``(row pitch, column pitch)`` in metres when the set is one plane on a regular pixel
        grid (its metrics then use the pixel-grid formulas), else None
    """

    images: dict
    coords: dict
    pitch: tuple | None = None

    @property
    def names(self) -> tuple[str, ...]:
        """The plane names, in order."""
        return tuple(self.images)

    @property
    def batch(self) -> int:
        """The batch size ``B``."""
        return int(next(iter(self.images.values())).shape[0])

    @property
    def kernel(self) -> Tensor:
        """The one plane of a one-plane set ``(B, H, W)``."""
        if len(self.images) != 1:
            raise ValueError(f"the plane set has {len(self.images)} planes {list(self.images)}, not one kernel")
        return next(iter(self.images.values()))

    def with_images(self, images: dict) -> "PlaneSet":
        """The same planes' positions with other images (same names and windows)."""
        return PlaneSet(dict(images), self.coords, self.pitch)

    def map(self, fn) -> "PlaneSet":
        """``fn`` applied to every image (``lambda x: x.cpu()``, a slice, a dtype)."""
        return self.with_images({k: fn(v) for k, v in self.images.items()})

    @staticmethod
    def cat(sets: list["PlaneSet"]) -> "PlaneSet":
        """The plane sets of consecutive batches as one."""
        first = sets[0]
        return first.with_images({k: torch.cat([s.images[k] for s in sets]) for k in first.names})


def kernel_coords(window: int, pitch: float) -> np.ndarray:
    """``(window, window, 3)`` positions (x, 0, z) in metres of a kernel window's pixels relative to its
    centre pixel ``(window // 2, window // 2)``; rows run along z, columns along x."""
    off = (np.arange(window) - window // 2) * float(pitch)
    z, x = np.meshgrid(off, off, indexing="ij")
    return np.stack([x, np.zeros_like(x), z], axis=-1)


class Imager:
    """The interface of an imager (module docstring); subclasses fill it.

    Attributes: ``n_elements``; ``plane_names`` (the names of its planes, in order); ``pitch``
    (``(row, column)`` pitch in metres of a one-plane regular grid, else None); ``frame`` (``"xyz"``:
    pixel positions in metres; ``"uv"``: shifts of direction sines); ``model`` (the physics model
    behind it); ``setup`` (its setup); ``exact`` (True when it images on the exact path only);
    ``exact_reason`` (why, else None); ``moves_from_selection`` (True when :meth:`image_moves`
    images a selection's neighbours from the selection's own images, cheaper than imaging their masks);
    ``point`` (the field point it images, in metres: ``(x, z)`` of a 1-D point, ``(x, y, z)`` of a
    3-D one; None for a beam pattern); ``psf_model`` (the 1-D point's
    :class:`~arraysel.physics.psf.PSFModel` whose pair basis gives the loss's quadratic model,
    else None).
    """

    n_elements: int
    plane_names: tuple = ()
    pitch: tuple | None = None
    frame: str = "xyz"
    exact: bool = False
    exact_reason: str | None = None
    moves_from_selection: bool = False
    point: tuple | None = None
    psf_model = None

    def wrap(self, images) -> PlaneSet:
        """A :class:`PlaneSet` of this imager's planes from ``images`` (``{name: (B, H, W)}``, or the
        one plane's tensor)."""
        if isinstance(images, Tensor):
            images = {self.plane_names[0]: images}
        return PlaneSet(dict(images), self.coords, self.pitch)

    def image(self, weights: Tensor, receive: Tensor | None = None) -> PlaneSet:
        """The plane set of weights ``(B, Ne)``, differentiable in them; with ``receive`` (separate
        receive channel weights ``(B, Ne)``), ``weights`` is the transmit apodization."""
        raise NotImplementedError

    def image_masks(self, masks: Tensor, receive: Tensor | None = None) -> tuple[PlaneSet, Tensor]:
        """The plane set of masks ``(B, Ne)`` (``receive``: as :meth:`image`) without gradient and
        whether each fell back from the imager's fast path to its exact path (bool ``(B,)``)."""
        with torch.no_grad():
            ps = self.image(masks, receive)
        return ps, torch.zeros(masks.shape[0], dtype=torch.bool)

    def image_moves(self, mask: Tensor, out, into, bases=None) -> tuple[PlaneSet, Tensor]:
        """:meth:`image_masks` of the neighbours of the selection ``mask`` (Ne,) that switch the
        elements ``out[b]`` off and ``into[b]`` on (int ``(B, m)``, ``-1`` pads); ``bases``: the
        selection bases the caller keeps for this imager, where its physics uses them."""
        return self.image_masks(moved_masks(mask, out, into))

    def reference(self) -> PlaneSet:
        """The full array's plane set (batch 1, no gradient), computed once."""
        ref = getattr(self, "_reference", None)
        if ref is None:
            with torch.no_grad():
                ones = torch.ones(1, self.n_elements, dtype=self.dtype, device=self.device)
                ref = self._reference = self.image(ones)
        return ref

    def masks_per_batch(self) -> int:
        """The most masks one call images at once (a memory or efficiency bound)."""
        raise NotImplementedError

    def layout(self) -> tuple:
        """``(grid, positions)``: the element grid ``(ny, nx)`` of a 2-D array on a full grid (else
        None) and the element centres ``(Ne, 3)`` as (x, y, z) in metres."""
        raise NotImplementedError

    def prepare_moves(self) -> bool:
        """Form now what :meth:`image_moves` shares between selections; True when it is all formed."""
        return True


def moved_masks(mask: Tensor, out, into) -> Tensor:
    """The masks ``(B, Ne)`` of the moves ``out[b]`` off, ``into[b]`` on (int ``(B, m)``, ``-1`` pads)
    of the selection ``mask`` (Ne,)."""
    a = torch.as_tensor(np.asarray(out, dtype=np.int64)).reshape(len(out), -1)
    b = torch.as_tensor(np.asarray(into, dtype=np.int64)).reshape(len(into), -1)
    w = mask.reshape(1, -1).repeat(a.shape[0], 1)
    for idx, val in ((a, 0), (b, 1)):
        r, c = torch.nonzero(idx >= 0, as_tuple=True)
        w[r.to(w.device), idx[r, c].to(w.device)] = val
    return w


class KernelImager(Imager):
    """The imager of one field point of a 1-D probe: its PSF kernel as one plane (module docstring).

    Parameters: ``model``, the point's :class:`~arraysel.physics.psf.PSFModel`; ``exact_reason``, why
    it has no fast path (None when it has one).
    """

    def __init__(self, model, exact_reason: str | None = None):
        self.model = self.psf_model = model
        self.exact_reason = exact_reason
        self.setup = model.setup
        self.n_elements = model.n_elements
        self.dtype, self.device = model.dtype, model.device
        p = float(model.setup.pitch)
        self.pitch = (p, p)
        self.plane_names = (KERNEL_PLANE,)
        self.coords = {KERNEL_PLANE: kernel_coords(model.setup.window, p)}
        self.exact = model.basis is None
        self.moves_from_selection = True
        self.point = tuple(float(v) for v in model.setup.scatterer_position)

    def image(self, weights: Tensor, receive: Tensor | None = None) -> PlaneSet:
        return self.wrap(self.model.kernels(weights, receive=receive))

    def layout(self):
        xe, ze, _, _ = self.setup.probe.element_positions()
        return None, np.stack([xe, np.zeros_like(xe), ze], axis=1)

    def image_masks(self, masks: Tensor, receive: Tensor | None = None) -> tuple[PlaneSet, Tensor]:
        k, fell_back = self.model.kernels(masks, return_info=True, receive=receive)
        return self.wrap(k), fell_back

    def image_moves(self, mask: Tensor, out, into, bases=None) -> tuple[PlaneSet, Tensor]:
        k, fell_back = self.model.swap_kernels(mask, out, into, return_info=True, bases=bases)
        return self.wrap(k), fell_back

    def reference(self) -> PlaneSet:
        # the model keeps the full array's kernel (PSFModel.reference_kernel)
        return self.wrap(self.model.reference_kernel()[None])

    def masks_per_batch(self) -> int:
        return self.model.masks_per_batch()

    def prepare_moves(self) -> bool:
        basis = self.model.basis
        return True if basis is None else basis.fill_pair_rows()


class VolumeImager(Imager):
    """The imager of a matrix probe: the planes of its 3-D PSF (module docstring).

    Parameters: ``model``, a :class:`~arraysel.physics.volume.MatrixPSF` or its fast path
    :class:`~arraysel.physics.volume.fast.MatrixFastPSF`; ``exact_reason``, None on the fast path,
    else why the exact path is used; ``batch``, the most masks per call (the objective's ``chunk``
    sets the batch).
    """

    def __init__(self, model, exact_reason: str | None = None, batch: int = 1 << 30):
        self.model = model
        self.setup = model.setup
        self.n_elements = model.n_elements
        self.dtype, self.device = model.dtype, torch.device(model.device)
        self.coords = {k: v.cpu().numpy() for k, v in model.coords.items()}
        self.plane_names = tuple(self.coords)
        self.exact_reason = exact_reason
        self.exact = exact_reason is not None
        self.batch = int(batch)
        self.point = tuple(float(v) for v in self.setup.scatterer)

    def image(self, weights: Tensor, receive: Tensor | None = None) -> PlaneSet:
        return self.wrap(self.model.planes(weights) if receive is None else self.model.planes(weights, receive=receive))

    def layout(self):
        probe = self.setup.probe
        return probe.layout_grid, probe.element_positions()

    def masks_per_batch(self) -> int:
        return self.batch


class PatternImager(Imager):
    """The imager of a sector scene's search: its two-way power beam pattern as one plane (module
    docstring).

    Parameters: ``pattern``, the :class:`~arraysel.physics.beampattern.BeamPattern` over the sector;
    ``setup``, the scene's :class:`~arraysel.physics.volume.sector.SectorSetup` (its probe).
    """

    frame = "uv"

    def __init__(self, pattern, setup):
        self.model = self.pattern = pattern
        self.setup = setup
        self.n_elements = int(pattern.n_elements)
        self.dtype, self.device = pattern.dtype, pattern.device
        self.plane_names = (PATTERN_PLANE,)
        self.coords = {PATTERN_PLANE: pattern.coords.cpu().numpy()}

    def image(self, weights: Tensor, receive: Tensor | None = None) -> PlaneSet:
        return self.wrap(self.pattern.pattern(weights, receive))

    def layout(self):
        probe = self.setup.probe
        return probe.layout_grid, probe.element_positions()

    def masks_per_batch(self) -> int:
        return 1 << 30
