"""The PyMUST oracle pipeline of the paper scene (docs/paper-scene.md), used only by tests and benchmarks.

PyMUST (LGPL) is called, never copied: this module builds the reference
point-spread function of an element selection with PyMUST's public functions
(``getparam``, ``txdelay``, ``simus``, ``rf2iq``, ``dasmtx``), exactly as
docs/paper-scene.md describes the paper scene.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np


def _pymust():
    import logging
    import pymust

    logging.getLogger().setLevel(logging.ERROR)
    return pymust


@dataclass
class PyMUSTScene:
    probe: str = "P4-2v"
    fc: float = 3.5e6
    c: float = 1540.0
    n_tx: int = 7
    max_tilt_deg: float = 10.0
    n_grid: int = 400
    window: int = 128
    _das_cache: dict = field(default_factory=dict, repr=False)

    def param(self):
        pm = _pymust()
        param = pm.getparam(self.probe)
        param.fc = self.fc
        param.fs = 4 * self.fc
        param.c = self.c
        return param

    @property
    def pixel(self) -> float:
        return (self.c / (4 * self.fc)) / 4

    def grid(self):
        p = self.pixel
        n = self.n_grid
        x = (np.arange(n) - n // 2) * p
        z = np.arange(n) * p
        return x, z

    def scatterer(self):
        return 0.0, (self.n_grid // 2) * self.pixel

    def tilts(self):
        return np.deg2rad(np.linspace(-self.max_tilt_deg, self.max_tilt_deg, self.n_tx))

    def rf(self, mask: np.ndarray, tilt: float):
        """RF (n_t, Ne) of one plane-wave transmit for a 0/1 (or weight) mask."""
        param = self.param()
        delays = _pymust().txdelay(param, float(tilt))
        return transmit_rf(param, delays, self.scatterer(), 1.0, mask), delays, param

    def image(self, mask: np.ndarray, cache_das: bool = True) -> np.ndarray:
        """Coherently compounded complex image on the (n_grid, n_grid) grid, [iz, ix]."""
        X, Z = np.meshgrid(*self.grid())
        return compound_images(self.param(), self.tilts(), X, Z, self.scatterer(), 1.0, np.asarray(mask)[None],
                               self._das_cache if cache_das else None)[0]

    def kernel(self, mask: np.ndarray) -> np.ndarray:
        return window_kernel(self.image(mask), self.window)


def window_kernel(image: np.ndarray, w: int) -> np.ndarray:
    """The paper scene's kernel: 128x128 window centred (64, 64) on the peak of |image|, clipped, L2-normalised."""
    iz, ix = np.unravel_index(np.argmax(np.abs(image)), image.shape)
    nz, nx = image.shape
    z0 = min(max(iz - w // 2, 0), nz - w)
    x0 = min(max(ix - w // 2, 0), nx - w)
    k = image[z0:z0 + w, x0:x0 + w]
    return k / np.linalg.norm(k)


def si_mse(k: np.ndarray, ref: np.ndarray) -> float:
    a = np.vdot(k, ref) / np.vdot(k, k)
    return float(np.linalg.norm(a * k - ref) ** 2 / np.linalg.norm(ref) ** 2)


def setup_param(setup):
    """PyMUST's ``param`` for an arraysel 1-D PSF setup (``PSFSetup``): the probe's geometry
    field by field (so any catalogue or custom probe, linear or convex), the acquisition's
    sampling rate, speed of sound, attenuation and transmit cycles, the receive f-number."""
    pm = _pymust()
    probe, acq = setup.probe, setup.acq
    param = pm.getparam("P4-2v")
    param.fc, param.pitch, param.width = probe.fc, probe.pitch, probe.width
    param.kerf = probe.pitch - probe.width
    param.Nelements, param.bandwidth = probe.n_elements, probe.bandwidth
    param.radius, param.height, param.focus = probe.radius, probe.height, probe.elevation_focus
    if probe.baffle != "soft":
        param.baffle = probe.baffle
    param.fs, param.c = acq.fs, acq.c
    param.attenuation, param.TXnow = acq.attenuation, acq.tx_cycles
    param.fnumber = setup.fnumber
    return param


def transmit_rf(param, delays, point, reflectivity: float, mask: np.ndarray, receive=None) -> np.ndarray:
    """RF (n_t, Ne) of one transmit (``delays``) by the active elements of ``mask`` (their TX
    apodization), received by them (the other channels zero), from one point scatterer; with
    ``receive`` (Ne,), the channels are weighted by it instead (separate receive aperture)."""
    pm = _pymust()
    w = np.asarray(mask, dtype=np.float32).reshape(1, -1)
    param.TXapodization = w.copy()
    try:
        RF, _ = pm.simus(np.array([point[0]]), np.array([point[1]]), np.array([reflectivity]), delays, param)
    finally:
        del param.TXapodization
    rx = mask if receive is None else receive
    return RF * np.asarray(rx, dtype=RF.dtype).reshape(1, -1)


def compound_images(param, tilts, X, Z, point, reflectivity: float, masks: np.ndarray,
                    das_cache: dict | None = None, receive: np.ndarray | None = None) -> np.ndarray:
    """The coherently compounded complex images (B, *X.shape) of 0/1 ``masks`` (B, Ne): per
    plane-wave ``tilt``, ``txdelay``, ``simus`` (:func:`transmit_rf`), ``rf2iq`` and the
    ``dasmtx`` product on the pixels ``X``, ``Z``; ``das_cache`` keeps the DAS matrices.
    ``receive`` (B, Ne): separate receive weights (``masks`` then transmit alone)."""
    pm = _pymust()
    total = np.zeros((len(masks),) + X.shape, dtype=np.complex128)
    rxs = [None] * len(masks) if receive is None else list(receive)
    for tilt in tilts:
        delays = pm.txdelay(param, float(tilt))
        iqs = [pm.rf2iq(transmit_rf(param, delays, point, reflectivity, m, r), param) for m, r in zip(masks, rxs)]
        n = max(iq.shape[0] for iq in iqs)
        iqs = [np.pad(iq, ((0, n - iq.shape[0]), (0, 0))) for iq in iqs]
        key = (float(tilt), iqs[0].shape)
        M = None if das_cache is None else das_cache.get(key)
        if M is None:
            M = pm.dasmtx(iqs[0], X, Z, delays, param).tocsr()
            if das_cache is not None:
                das_cache[key] = M
        for i, iq in enumerate(iqs):
            total[i] += (M @ iq.flatten(order="F")).reshape(X.shape, order="F")
    return total


def setup_kernels(setup, masks: np.ndarray, receive: np.ndarray | None = None) -> list[np.ndarray]:
    """The kernels of 0/1 ``masks`` (B, Ne) on an arraysel 1-D setup's scene, through
    PyMUST (:func:`compound_images` on the setup's own grid), for scenes unlike the paper's:
    another probe, a convex one, attenuation, a longer pulse, an f-number, a point off the axis,
    other transmits. ``receive`` (B, Ne): separate receive weights, ``masks`` transmit."""
    X, Z = np.meshgrid(np.asarray(setup.x, dtype=float), np.asarray(setup.z, dtype=float))
    images = compound_images(setup_param(setup), setup.tilts, X, Z, setup.scatterer_position, setup.reflectivity,
                             masks, receive=receive)
    return [window_kernel(img, setup.window) for img in images]


if __name__ == "__main__":
    s = PyMUSTScene()
    full = np.ones(64)
    uni = np.zeros(64); uni[::2] = 1
    t = time.perf_counter(); kf = s.kernel(full); t1 = time.perf_counter() - t
    t = time.perf_counter(); ku = s.kernel(uni); t2 = time.perf_counter() - t
    print("first (builds DAS)", t1, "cached", t2)
    print("L_PSF uniform", si_mse(ku, kf))
    RF, _, _ = s.rf(full, 0.0)
    print("RF shape", RF.shape)
