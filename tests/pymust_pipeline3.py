"""The PyMUST oracle of the 3-D PSF on three planes (used only by tests and benchmarks).

PyMUST (LGPL) is called, never copied: the compound image of an element selection on given
3-D points is built with PyMUST's public 3-D functions (``simus3``, ``rf2iq``, ``dasmtx3``; the
delays come from ``txdelay3`` or are given), as ``arraysel.physics.volume`` models it: every
transmit uses the full array's delays; an inactive element gets zero transmit apodization and its
received channel is zeroed (PyMUST 0.1.9's 3-D functions fail on NaN delays, its own convention
for an inactive element); RF -> I/Q -> DAS (linear interpolation, f-number 0, t0 = 0); the
images of the transmits are summed coherently.
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


def must_param(probe, acq):
    """A PyMUST ``Param`` for a :class:`~arraysel.physics.probes.MatrixProbe` and an acquisition."""
    pm = _pymust()
    p = pm.utils.Param()
    for k, v in probe.to_must_dict().items():
        setattr(p, k, v)
    p.c = acq.c
    p.fs = acq.fs
    p.attenuation = acq.attenuation
    p.TXnow = acq.tx_cycles
    return p


@dataclass
class PyMUSTScene3:
    """probe, acq: arraysel objects (only their numbers reach PyMUST); delays (n_tx, Ne) s;
    scatterer (x, y, z) m; coords {plane: (H, W, 3) m} where the image is sampled."""

    probe: object
    acq: object
    delays: np.ndarray
    scatterer: tuple
    coords: dict
    _das: dict = field(default_factory=dict, repr=False)
    das_seconds: float = 0.0

    def iq(self, mask: np.ndarray, tx: int, receive: np.ndarray | None = None) -> np.ndarray:
        """I/Q (n_t, Ne) of transmit ``tx`` for a 0/1 (or weight) mask; ``receive``: separate
        receive channel weights (``mask`` then the transmit apodization alone)."""
        pm = _pymust()
        param = must_param(self.probe, self.acq)
        mask = np.asarray(mask, dtype=np.float64).reshape(-1)
        param.TXapodization = mask.reshape(1, -1).copy()
        x, y, z = (np.array([v]) for v in self.scatterer)
        RF, _ = pm.simus3(x, y, z, np.array([1.0]), np.asarray(self.delays[tx]).reshape(1, -1), param)
        rx = mask if receive is None else np.asarray(receive, dtype=np.float64).reshape(-1)
        RF = RF * rx.reshape(1, -1)
        return pm.rf2iq(RF, param)

    def das(self, shape, tx: int, plane: str):
        key = (tx, plane, tuple(shape))
        if key not in self._das:
            pm = _pymust()
            t = time.perf_counter()
            param = must_param(self.probe, self.acq)
            c = np.asarray(self.coords[plane], dtype=np.float64)
            X, Y, Z = (np.ascontiguousarray(c[..., i])[..., None] for i in range(3))
            M = pm.dasmtx3(1j * np.array(shape), X, Y, Z, np.asarray(self.delays[tx]).reshape(1, -1), param)
            self._das[key] = M.tocsr()
            self.das_seconds += time.perf_counter() - t
        return self._das[key]

    def planes(self, mask: np.ndarray, receive: np.ndarray | None = None) -> dict:
        """The compound image on each plane: {name: complex (H, W)}; ``receive`` as in :meth:`iq`;
        ``mask`` (n_tx, Ne): a transmit apodization per transmit event."""
        out = {k: np.zeros(np.asarray(v).shape[:2], dtype=np.complex128) for k, v in self.coords.items()}
        events = np.ndim(mask) == 2     # one transmit apodization per transmit event
        for tx in range(len(self.delays)):
            IQ = self.iq(mask[tx] if events else mask, tx, receive)
            flat = IQ.flatten(order="F")
            for name in out:
                M = self.das(IQ.shape, tx, name)
                out[name] += (M @ flat).reshape(out[name].shape + (1,), order="F")[..., 0]
        return out


def si_mse(k: np.ndarray, ref: np.ndarray) -> float:
    """Scale-invariant MSE ||a k - ref||^2 / ||ref||^2, a = <k, ref> / <k, k> (L_PSF of docs/metrics.md)."""
    k = np.asarray(k).ravel()
    ref = np.asarray(ref).ravel()
    a = np.vdot(k, ref) / np.vdot(k, k)
    return float(np.linalg.norm(a * k - ref) ** 2 / np.linalg.norm(ref) ** 2)
