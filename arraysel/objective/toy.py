"""The toy objective: the PSF objective's contract on a cheap synthetic function of the mask.

:class:`ToyObjective` implements the same contract as :class:`arraysel.objective.psf_objective.Objective`
(evaluate / mask_loss / selection_loss / kernels / reference_kernel and the counters) on a smooth
synthetic function of the mask, in micro-seconds instead of seconds. Its optimum is close to a known,
spread-out target set (``objective.target``). ``arraysel compare --scene toy`` runs on it, and the test
suite and plugin authors' conformance tests use it.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import torch

from arraysel.errors import ParameterError, SelectionError, check_number
from arraysel.objective.contract import WorkerFactory, check_element_grid, dtype_name
from arraysel.objective.losses import DEFAULT_WEIGHTS, PSF_WEIGHT_KEYS, training_loss
from arraysel.objective.metrics import METRIC_NAMES

__all__ = ["ToyScene", "ToyFailure", "ToyObjective", "ToyObjectiveFactory", "TOY_PITCH"]

#: element pitch (m) of the toy array's ``element_positions`` (both directions for a grid)
TOY_PITCH = 3e-4
#: the weights of :meth:`ToyObjective.mask_loss`: the PSF terms' defaults
_PSF_WEIGHTS = {key: DEFAULT_WEIGHTS[key] for key in PSF_WEIGHT_KEYS}




class ToyScene:
    """Minimal scene of the toy objective (``.name`` and ``.to_dict()``)."""

    def __init__(self, n_elements: int, k: int, seed: int):
        self.name = "toy"
        self.n_elements = n_elements
        self.k = k
        self.seed = seed

    def to_dict(self) -> dict:
        return {"name": self.name, "kind": "toy", "n_elements": self.n_elements, "k": self.k,
                "seed": self.seed}


class ToyFailure(RuntimeError):
    """Raised by a :class:`ToyObjective` built with ``fail_after``."""


class ToyObjective:
    """A cheap objective with the real one's contract, for tests and demos.

    Parameters
    ----------
    n_elements, k : Ne and the number of elements to keep
    device, dtype : where and in which real dtype the terms are computed
    seed : picks the target set (one element in each of k equal strata)
    chunk : masks per internal batch of :meth:`evaluate`
    fail_after : raise :class:`ToyFailure` on any call once this many
        evaluations were made (0: every call raises)
    nan_element : masks that use this element give NaN metrics
    always_nan : every metric is NaN
    delay : seconds slept in each call (to test time budgets)
    grid : ``(ny, nx)`` with ``ny * nx = n_elements``: a toy matrix array (element index
        ``iy * nx + ix``, ``element_grid``); ``None`` (default): a 1-D array
    constraints : :class:`~arraysel.constraints.Constraints` for ``k`` of ``n_elements``
        (``docs/constraints.md``), None: none

    Layout: ``element_grid`` (the grid or None) and ``element_positions`` ``(Ne, 3)``, the element
    centres on a :data:`TOY_PITCH` grid centred on the origin (on the x axis for a 1-D array).

    Metrics, for weights ``w`` in [0, 1]^Ne and target indicator ``t``:

    * ``L_PSF = ||w - t||^2 / (2k)`` (1 - overlap/k for hard masks);
    * from the array factor ``A(u) = sum_n w_n exp(-2i pi n u)`` on
      ``4 Ne`` points, normalised to ``A(0) = 1``: main lobe ``|u| < 1/Ne``,
      side lobes elsewhere (with a grid: the 2-D array factor of the ``(ny, nx)`` weights on
      ``4 ny x 4 nx`` points, main lobe ``|u| < 1/nx`` and ``|v| < 1/ny``); ``L_contrast = 0.01 mean(side)/mean(main)``,
      ``L_SLR_q = 0.1 softmax-level of |A| on the side lobes``,
      ``L_SLR_i = 0.1 sum(side |A|^2)/sum(main |A|^2)``;
    * ``L_SLR = (L_SLR_q + L_SLR_i)/2``, ``Mean`` the mean of the four.

    An all-zero mask gives NaN (0/0), like a degenerate mask of the real objective.
    """

    metric_names = METRIC_NAMES

    def __init__(self, n_elements: int = 16, k: int = 8, *, device: str | torch.device = "cpu",
                 dtype: torch.dtype = torch.float32, seed: int = 0, chunk: int = 4096,
                 fail_after: int | None = None, nan_element: int | None = None,
                 always_nan: bool = False, delay: float = 0.0, grid: tuple[int, int] | None = None,
                 constraints=None):
        self.n_elements = int(check_number("n_elements", n_elements, lo=1, integer=True))
        self.k = int(check_number("k", k, lo=1, hi=self.n_elements, integer=True))
        if dtype not in (torch.float32, torch.float64):
            raise ParameterError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self.device = torch.device(device)
        self.dtype = dtype
        self.chunk = int(check_number("chunk", chunk, lo=1, integer=True))
        self.fail_after = fail_after
        self.nan_element = nan_element
        self.always_nan = bool(always_nan)
        self.delay = float(delay)
        self.scene = ToyScene(self.n_elements, self.k, seed)
        rng = np.random.default_rng(seed)
        edges = np.floor(np.arange(self.k + 1) * self.n_elements / self.k).astype(int)
        self.target = sorted(int(rng.integers(edges[i], edges[i + 1])) for i in range(self.k))
        t = torch.zeros(self.n_elements, dtype=dtype, device=self.device)
        t[self.target] = 1.0
        self._t = t
        self.element_grid = None if grid is None else check_element_grid(grid, self.n_elements)
        if constraints is not None and (constraints.n_elements, constraints.k) != (self.n_elements, self.k):
            raise ParameterError(f"constraints are for k = {constraints.k} of {constraints.n_elements} elements; "
                                 f"the toy objective has k = {self.k} of {self.n_elements}")
        #: a :class:`~arraysel.constraints.Constraints` every run on this objective meets (None: none)
        self.constraints = constraints
        if self.element_grid is None:
            nfft = 4 * self.n_elements
            u = torch.fft.fftfreq(nfft, dtype=torch.float64).to(self.device)
            self._main = (u.abs() < 1.0 / self.n_elements)
            ix, iy = np.arange(self.n_elements) - (self.n_elements - 1) / 2, np.zeros(self.n_elements)
        else:
            ny, nx = self.element_grid
            nfft = (4 * ny, 4 * nx)
            v = torch.fft.fftfreq(nfft[0], dtype=torch.float64).to(self.device)
            u = torch.fft.fftfreq(nfft[1], dtype=torch.float64).to(self.device)
            self._main = ((v.abs() < 1.0 / ny)[:, None] & (u.abs() < 1.0 / nx)[None, :]).reshape(-1)
            iy, ix = np.divmod(np.arange(self.n_elements), nx)
            ix, iy = ix - (nx - 1) / 2, iy - (ny - 1) / 2
        self.element_positions = np.stack([ix * TOY_PITCH, iy * TOY_PITCH, np.zeros(self.n_elements)], axis=1)
        self._nfft = nfft
        self.evaluations = 0
        self.gradient_steps = 0
        self.seconds = 0.0

    # -- helpers ------------------------------------------------------------
    def _enter(self, n: int) -> float:
        if self.fail_after is not None and self.evaluations + n > self.fail_after:
            raise ToyFailure(f"toy objective failure (fail_after={self.fail_after}, "
                             f"evaluations so far {self.evaluations})")
        if self.delay:
            time.sleep(self.delay)
        return time.perf_counter()

    def _as_weights(self, masks) -> torch.Tensor:
        if isinstance(masks, torch.Tensor):
            w = masks.to(device=self.device, dtype=self.dtype)
        else:
            w = torch.as_tensor(np.asarray(masks, dtype=np.float64), dtype=self.dtype, device=self.device)
        if w.ndim == 1:
            w = w[None, :]
        if w.ndim != 2 or w.shape[1] != self.n_elements:
            raise ParameterError(f"masks must have shape (B, {self.n_elements}), got {tuple(w.shape)}")
        if not bool(torch.isfinite(w).all()):  # as the scene objectives refuse them
            raise SelectionError("masks contain NaN or Inf")
        return w

    def _terms(self, w: torch.Tensor) -> dict[str, torch.Tensor]:
        d = w - self._t
        l_psf = (d * d).sum(dim=1) / (2.0 * self.k)
        if self.element_grid is None:
            spec = torch.fft.fft(w, n=self._nfft, dim=1)
        else:
            spec = torch.fft.fft2(w.reshape((w.shape[0],) + self.element_grid), s=self._nfft).reshape(w.shape[0], -1)
        power = spec.real ** 2 + spec.imag ** 2
        total = w.sum(dim=1, keepdim=True)
        power = power / (total * total)
        main, side = power[:, self._main], power[:, ~self._main]
        l_contrast = 0.01 * side.mean(dim=1) / main.mean(dim=1)
        amp = torch.sqrt(side + 1e-12)
        beta = 40.0
        l_slr_q = 0.1 * torch.logsumexp(beta * amp, dim=1) / beta
        l_slr_i = 0.1 * side.sum(dim=1) / main.sum(dim=1)
        terms = {"L_PSF": l_psf, "L_contrast": l_contrast, "L_SLR_q": l_slr_q, "L_SLR_i": l_slr_i}
        terms["L_SLR"] = 0.5 * (l_slr_q + l_slr_i)
        terms["Mean"] = 0.25 * (l_psf + l_contrast + l_slr_q + l_slr_i)
        bad = torch.zeros(w.shape[0], dtype=torch.bool, device=w.device)
        if self.always_nan:
            bad = ~bad
        if self.nan_element is not None:
            bad = bad | (w[:, self.nan_element] > 0.5)
        if bool(bad.any()):
            terms = {key: torch.where(bad, torch.full_like(v, math.nan), v) for key, v in terms.items()}
        return terms

    # -- contract -----------------------------------------------------------
    def evaluate(self, masks) -> dict[str, np.ndarray]:
        """Metrics of hard masks ``(B, Ne)``; float64 arrays ``(B,)``; no gradient."""
        w = self._as_weights(masks)
        t0 = self._enter(w.shape[0])
        try:
            out = {m: [] for m in METRIC_NAMES}
            with torch.no_grad():
                for s in range(0, w.shape[0], self.chunk):
                    terms = self._terms((w[s:s + self.chunk] > 0.5).to(self.dtype))
                    for m in METRIC_NAMES:
                        out[m].append(terms[m].double().cpu().numpy())
            self.evaluations += w.shape[0]
            return {m: np.concatenate(v) if v else np.zeros(0) for m, v in out.items()}
        finally:
            self.seconds += time.perf_counter() - t0

    def mask_loss(self, weights: torch.Tensor):
        """Differentiable loss of soft weights ``(B, Ne)``: ``10 L_PSF + 10 L_contrast + 10 L_SLR``."""
        w = self._as_weights(weights)
        t0 = self._enter(w.shape[0])
        try:
            total, terms = training_loss(self._terms(w), _PSF_WEIGHTS)
            self.evaluations += w.shape[0]
            if w.requires_grad:
                self.gradient_steps += 1
            return total, terms
        finally:
            self.seconds += time.perf_counter() - t0

    def selection_loss(self, P: torch.Tensor, P_soft: torch.Tensor, step: int):
        """Scalar loss of a selection matrix ``(Ne, k)``: PSF terms + ``L_ent`` + ``10 L_row``."""
        if P.shape != (self.n_elements, P.shape[1]) or P_soft.shape != P.shape:
            raise ParameterError(f"P and P_soft must have shape ({self.n_elements}, k), "
                                 f"got {tuple(P.shape)} and {tuple(P_soft.shape)}")
        t0 = self._enter(1)
        try:
            w = P.to(self.dtype).sum(dim=1)[None, :]
            terms = self._terms(w)
            total, terms = training_loss({key: v[0] for key, v in terms.items()}, DEFAULT_WEIGHTS,
                                         P_soft=P_soft.to(self.dtype))
            self.evaluations += 1
            if P.requires_grad or P_soft.requires_grad:
                self.gradient_steps += 1
            return total, terms
        finally:
            self.seconds += time.perf_counter() - t0

    def kernels(self, masks) -> torch.Tensor:
        """Synthetic complex PSFs ``(B, 128, 128)`` (axial pulse x lateral array factor), unit L2 norm."""
        w = (self._as_weights(masks) > 0.5).to(torch.float64)
        with torch.no_grad():
            lateral = torch.fft.fftshift(torch.fft.fft(w, n=128, dim=1), dim=1)
            z = torch.arange(128, dtype=torch.float64, device=w.device) - 64
            axial = torch.exp(-(z / 6.0) ** 2) * torch.exp(2j * math.pi * 0.25 * z)
            k = axial[None, :, None] * lateral[:, None, :]
            norm = torch.linalg.vector_norm(k.reshape(k.shape[0], -1), dim=1).clamp_min(1e-30)
            k = k / norm[:, None, None]
        return k.to(torch.complex64 if self.dtype == torch.float32 else torch.complex128)

    def worker_factory(self) -> "ToyObjectiveFactory":
        """A picklable recipe that rebuilds this objective (with its failure settings) on a worker."""
        return ToyObjectiveFactory(self.n_elements, self.k, device=str(self.device), dtype=dtype_name(self.dtype),
                                   seed=int(self.scene.seed), chunk=self.chunk, fail_after=self.fail_after,
                                   nan_element=self.nan_element, always_nan=self.always_nan, delay=self.delay,
                                   grid=self.element_grid)

    def reference_kernel(self) -> torch.Tensor:
        """The full-array kernel ``(128, 128)``."""
        return self.kernels(np.ones((1, self.n_elements), dtype=bool))[0]


@dataclasses.dataclass(frozen=True)
class ToyObjectiveFactory(WorkerFactory):
    """Builds a :class:`ToyObjective` (on a worker: tests, demos, benchmarks)."""

    n_elements: int = 64
    k: int = 32
    device: str = "cpu"
    dtype: str = "float32"
    seed: int = 0
    chunk: int = 4096
    fail_after: int | None = None
    nan_element: int | None = None
    always_nan: bool = False
    delay: float = 0.0
    grid: tuple[int, int] | None = None

    def __call__(self):
        return ToyObjective(self.n_elements, self.k, device=self.device, dtype=getattr(torch, self.dtype),
                            seed=self.seed, chunk=self.chunk, fail_after=self.fail_after,
                            nan_element=self.nan_element, always_nan=self.always_nan, delay=self.delay,
                            grid=self.grid)
