"""The PSF's configuration: :class:`PSFSetup` and the grid conventions.

The image grid has ``n_x`` x ``n_z`` pixels of side ``pitch`` (default ``(c / fs) / 4``):
column ``i`` lies at ``x_i = (i - n_x // 2 + x_offset) pitch``, row ``i`` at
``z_i = (i + z_offset) pitch`` (offsets in whole pixels). The scatterer defaults to the pixel
(column ``n_x // 2``, row ``n_z // 2``). ``repr(setup)`` is part of the fast-path cache key, so
it must not change for an unchanged scene.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np

from arraysel.errors import ParameterError, check_number
from arraysel.physics.probes import Acquisition, Probe, check_sampling
from arraysel.physics.simus import SimOptions


@dataclass(frozen=True, repr=False)
class PSFSetup:
    """Everything the PSF of a selection depends on (a scene's physics part).

    probe, acq: transducer and acquisition (fs, c, attenuation, pulse cycles).
    tilts: plane-wave tilts (radians); TX delays are the full array's.
    n_x, n_z: image grid size; pixel: grid pitch (m, default (c/fs)/4);
        ``x_i = (i - n_x//2 + x_offset) pixel``, ``z_i = (i + z_offset) pixel``
        (offsets in whole pixels; ``x_offset`` is left out of the repr when 0,
        so that the cache keys of unshifted grids do not change).
    scatterer: (x, z) in metres (default: the pixel (x = x_offset pixel,
        z = (n_z//2 + z_offset) pixel), i.e. column n_x//2, row n_z//2).
    window: PSF window side (pixels).
    fnumber: receive f-number (0 = full aperture).
    iq_bandwidth: bandwidth (%) of the I/Q low-pass (default: the probe's).
    options: simulator accuracy settings.
    """

    probe: Probe
    acq: Acquisition
    tilts: tuple = tuple(np.deg2rad(np.linspace(-10, 10, 7)))
    n_x: int = 400
    n_z: int = 400
    pixel: float | None = None
    z_offset: int = 0
    scatterer: tuple | None = None
    reflectivity: float = 1.0
    window: int = 128
    fnumber: float = 0.0
    iq_bandwidth: float | None = None
    options: SimOptions = field(default_factory=SimOptions)
    x_offset: int = 0

    def __repr__(self) -> str:
        parts = [f"{f.name}={getattr(self, f.name)!r}" for f in fields(self)
                 if not (f.name == "x_offset" and self.x_offset == 0)]
        return f"{type(self).__qualname__}({', '.join(parts)})"

    def __post_init__(self):
        check_sampling(self.probe, self.acq)
        check_number("x_offset", self.x_offset, lo=-10 ** 6, hi=10 ** 6, integer=True)
        check_number("n_x", self.n_x, lo=2, hi=8192, integer=True)
        check_number("n_z", self.n_z, lo=2, hi=8192, integer=True)
        check_number("window", self.window, lo=2, hi=min(self.n_x, self.n_z), integer=True)
        if self.pixel is not None:
            check_number("pixel", self.pixel, lo=0, lo_open=True, hi=1.0)
        if len(self.tilts) < 1:
            raise ParameterError("tilts: at least one transmit is needed")
        for t in self.tilts:
            check_number("tilt (rad)", t, lo=-math.pi / 2, hi=math.pi / 2, lo_open=True, hi_open=True)
        check_number("fnumber", self.fnumber, lo=0.0, hi=100.0)
        check_number("reflectivity", self.reflectivity, lo=0.0, lo_open=True)
        xs, zs = self.scatterer_position
        if zs <= 0:
            raise ParameterError(f"scatterer depth z = {zs!r} m must be > 0 (in front of the array)")

    @property
    def pitch(self) -> float:
        return self.pixel if self.pixel is not None else self.acq.c / self.acq.fs / 4

    @property
    def x(self) -> np.ndarray:
        return (np.arange(self.n_x) - self.n_x // 2 + self.x_offset) * self.pitch

    @property
    def z(self) -> np.ndarray:
        return (np.arange(self.n_z) + self.z_offset) * self.pitch

    @property
    def scatterer_position(self) -> tuple[float, float]:
        if self.scatterer is not None:
            return float(self.scatterer[0]), float(self.scatterer[1])
        return float(self.x_offset * self.pitch), float((self.n_z // 2 + self.z_offset) * self.pitch)

    @property
    def scatterer_pixel(self) -> tuple[int, int]:
        """(row, column) of the grid pixel nearest the scatterer (may lie outside the grid)."""
        xs, zs = self.scatterer_position
        return int(round(zs / self.pitch - self.z_offset)), int(round(xs / self.pitch - self.x_offset)) + self.n_x // 2

    @property
    def wavelength(self) -> float:
        return self.acq.c / self.probe.fc
