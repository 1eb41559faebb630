"""The objective of a 3-D scene: a matrix probe's PSF on planes through one scatterer.

:class:`MatrixObjective` is :class:`~arraysel.objective.psf_objective.Objective`'s counterpart for
a scene with a ``[volume]`` section (``docs/matrix.md``): the same contract (``evaluate``,
``mask_loss``, ``selection_loss``, counters, a worker recipe), the Table-1 terms of
:func:`~arraysel.objective.metrics3d.psf3d_metrics` over every plane together as headline
metrics, and the 2-D array figures of merit (``PSL_dB``, ``width_x_6dB``, ``width_y_6dB``) as
extra columns (``breakdown_names``).

The planes come from the fast path (:class:`~arraysel.physics.volume.fast.MatrixFastPSF`) when
its build-time check against the exact path passes, else from the exact path, said once in the
log. The fast path's tensors are cached on disk like the 1-D pair basis (``arraysel cache``), so
only the first run with a scene's settings builds them.
"""
from __future__ import annotations

import hashlib
import logging

import numpy as np
import torch

from arraysel.errors import ParameterError, SelectionError
from arraysel.objective.tensors import objective_device
from arraysel.objective.metrics import METRIC_NAMES
from arraysel.objective.metrics3d import MERIT_NAMES, psf3d_metrics
from arraysel.objective.psf_objective import Objective, SceneObjectiveFactory, build_objective
from arraysel.objective.contract import dtype_name
from arraysel.scenes.schema import Scene, load_scene

__all__ = ["MatrixObjective", "MatrixObjectiveFactory", "matrix_model", "FAST_VERSION"]

_log = logging.getLogger(__name__)

#: the version of the cached fast-path tensors (bumped when their meaning changes)
FAST_VERSION = 2
#: the most interpolation harmonics (``FastSettings.replicas``) the fast path's build tries
MAX_REPLICAS = 2
#: masks per batch of :meth:`MatrixObjective.evaluate`: the fast path's matrix product is most
#: efficient from about 128 masks (``benchmarks/bench_matrix_fast.py``)
DEFAULT_CHUNK_3D = 128


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
    n = setup.probe.n_elements
    g = torch.Generator().manual_seed(0)
    checks = [torch.ones(n, dtype=torch.float64)]
    for _ in range(2):  # selections of the scene's size, where the check must hold
        m = torch.zeros(n, dtype=torch.float64)
        m[torch.randperm(n, generator=g)[:k]] = 1
        checks.append(m)
    checks = torch.stack(checks)

    def build() -> dict:
        # the fewest interpolation harmonics whose check is within a hundredth of the tolerance (a
        # sparse selection of a small array averages their error out less), else within it
        exact = MatrixPSF(setup, dtype=torch.float64)
        fallback = None
        for replicas in range(0, MAX_REPLICAS + 1):
            settings = FastSettings(replicas=replicas)
            try:
                fast_model = MatrixFastPSF(exact, settings, dtype=torch.float64, check_masks=checks)
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


class MatrixObjective(Objective):
    """Batched, differentiable objective of a 3-D scene (see the module docstring).

    Parameters: scene (a 3-D :class:`~arraysel.scenes.schema.Scene` or its name/path), device,
    dtype, chunk (masks per batch of :meth:`evaluate`), fast (False: the exact path only).
    """

    metric_names = METRIC_NAMES

    def __init__(self, scene: Scene | str = "matrix-1024", device="cpu", dtype=torch.float32,
                 chunk: int = DEFAULT_CHUNK_3D, fast: bool = True):
        self.scene = load_scene(scene) if not isinstance(scene, Scene) else scene
        if not self.scene.is_volume:
            raise ParameterError(f"scene {self.scene.name!r} has no [volume] section: use Objective for it")
        self.device = objective_device(device)
        self.dtype = dtype
        self.chunk = int(chunk)
        #: the scene's settings, read once: the objective does not go back to the scene
        self.settings = st = self.scene.objective_settings()
        self.setup = self.scene.matrix_setup()
        probe = self.setup.probe
        self.n_elements = probe.n_elements
        self.k = st.k
        #: the element grid (ny, nx) and centres (Ne, 3) in metres (ObjectiveContract's layout); a grid
        #: with blank rows or columns, or a planar layout, has no full grid: None, and its positions
        self.element_grid = probe.layout_grid
        self.element_positions = probe.element_positions()
        #: the scene's constraints (:mod:`arraysel.constraints`), None without a [constraints] section
        self.constraints = self.scene.constraints()
        self.n_points = 1
        self.points = [self.setup.scatterer]
        self.fast_requested = bool(fast) and st.fast
        self.model, self.exact_reason = matrix_model(self.setup, self.k, dtype, self.device, self.fast_requested)
        if self.exact_reason is not None:
            _log.warning("%s", self.exact_notice())
        self.coords = {k: v.numpy() for k, v in self.model.coords.items()}
        self.metric_kw = dict(wavelength=st.wavelength, **st.metric_radii)
        #: the 2-D array figures of merit, extra columns of a run's row
        self.breakdown_names = MERIT_NAMES
        self.weights = dict(st.weights)
        self._ref = None
        self._announced = True
        self.evaluations = 0
        self.gradient_steps = 0
        self.seconds = 0.0
        self.fallbacks = 0
        #: :meth:`mask_hessian` by autograd of :meth:`mask_loss`: the pair model of the 1-D basis
        #: does not apply to the planes
        self.hessian_from_pairs = False

    @property
    def fast(self) -> bool:
        """True when the planes come from the fast path."""
        return self.exact_reason is None

    def estimate_seconds(self, n_masks: int = 1) -> float:
        return n_masks * (0.01 if self.fast else 1.0)

    def exact_notice(self, n_masks: int | None = None) -> str:
        if self.fast:
            return f"scene {self.settings.name!r}: fast 3-D PSF path"
        return (f"scene {self.settings.name!r}: 3-D PSF fast path {self.exact_reason}; using the exact path "
                f"(about 1 s per mask)")

    # ------------------------------------------------------------------ planes
    def planes(self, weights) -> dict[str, torch.Tensor]:
        """The complex planes ``{name: (B, H, W)}`` of weights (B, Ne), differentiable."""
        return self.model.planes(weights)

    def reference_planes(self) -> dict[str, torch.Tensor]:
        """The full array's planes ``{name: (1, H, W)}`` (computed once, no gradient)."""
        if self._ref is None:
            with torch.no_grad():
                self._ref = self.model.planes(torch.ones(1, self.n_elements, dtype=self.dtype, device=self.device))
        return self._ref

    def kernels(self, masks, point=None):
        raise ParameterError("a 3-D scene has planes, not a 2-D kernel: use MatrixObjective.planes")

    def reference_kernel(self, point=None):
        raise ParameterError("a 3-D scene has planes, not a 2-D kernel: use MatrixObjective.reference_planes")

    def _metrics(self, planes, terms=None) -> dict[str, torch.Tensor]:
        ref = {k: v.to(planes[k].dtype) for k, v in self.reference_planes().items()}
        return psf3d_metrics(planes, self.coords, planes_ref=ref, terms=terms, **self.metric_kw)

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, masks, return_planes: bool = False, receive=None) -> dict[str, np.ndarray]:
        """Every Table-1 metric and figure of merit of a batch of masks: {name: float64 (B,)};
        with ``return_planes`` also ``"planes"``: {name: complex (B, H, W)}. No gradient.
        ``receive``: separate receive masks (B, Ne), ``masks`` then the transmit aperture."""
        with torch.no_grad(), self._timed():
            m = self.as_masks(masks)
            r = None if receive is None else self.as_masks(receive)
            out: dict[str, list] = {k: [] for k in (*METRIC_NAMES, *MERIT_NAMES)}
            kept: dict[str, list] = {}
            for i in range(0, m.shape[0], self.chunk):
                planes = (self.model.planes(m[i:i + self.chunk]) if r is None else
                          self.model.planes(m[i:i + self.chunk], receive=r[i:i + self.chunk]))
                met = self._metrics(planes)
                for k in out:
                    out[k].append(met[k].double().cpu())
                if return_planes:
                    for k, v in planes.items():
                        kept.setdefault(k, []).append(v.cpu())
            self.evaluations += int(m.shape[0])
        res = {k: torch.cat(v).numpy() for k, v in out.items()}
        if return_planes:
            res["planes"] = {k: torch.cat(v).numpy() for k, v in kept.items()}
        return res

    def psf_terms(self, weights: torch.Tensor, terms=None, receive=None) -> dict[str, torch.Tensor]:
        """Differentiable Table-1 terms (B,) of soft element weights (B, Ne); ``receive``:
        separate receive weights (B, Ne)."""
        w = weights if weights.dim() == 2 else weights[None]
        if w.shape[-1] != self.n_elements:
            raise SelectionError(f"weights must have shape (B, {self.n_elements}), got {tuple(w.shape)}")
        w = w.to(self.device, self.dtype)
        if receive is None:
            return self._metrics(self.model.planes(w), terms=terms)
        return self._metrics(self.model.planes(w, receive=receive.to(self.device, self.dtype)), terms=terms)

    def worker_factory(self) -> "MatrixObjectiveFactory | None":
        if type(self) is not MatrixObjective:
            return None
        return MatrixObjectiveFactory(self.scene.to_dict(), device=str(self.device), dtype=dtype_name(self.dtype),
                                      chunk=int(self.chunk))

    # ------------------------------------------------------------------ neighbourhoods
    def _neighbourhood(self):
        """The :class:`~arraysel.objective.matrix_neighbours.MatrixNeighbourhood` of the fast path
        (None on the exact path or off the CPU: neighbours are then scored as their masks)."""
        if not self.fast or self.device.type != "cpu":
            return None
        if getattr(self, "_neigh", None) is None:
            from arraysel.objective.matrix_neighbours import MatrixNeighbourhood

            self._neigh = MatrixNeighbourhood(self)
        return self._neigh

    def neighbourhood(self):
        """The :class:`~arraysel.objective.contract.Neighbourhood` of the fast path on the CPU
        (:meth:`evaluate_moves`, prepared by :meth:`prepare_neighbourhoods`); None on the exact path
        or off the CPU, where neighbours are scored as masks."""
        from arraysel.objective.contract import MovesNeighbourhood

        if self._neighbourhood() is None:
            return None
        return MovesNeighbourhood(self.evaluate_moves, self.prepare_neighbourhoods)

    def evaluate_swaps(self, mask, out, into) -> dict[str, np.ndarray]:
        """:meth:`evaluate` of the one-swap neighbours of a 0/1 selection ``mask`` (Ne,): element
        ``out[i]`` switched off and ``into[i]`` on (:class:`~arraysel.objective.contract.ScoresSwaps`):
        :meth:`evaluate_moves` with one element a move."""
        from arraysel.objective.neighbours import check_swaps

        m, a, b = check_swaps(mask, out, into)
        return self.evaluate_moves(m, a[:, None], b[:, None])

    def evaluate_moves(self, mask, out, into) -> dict[str, np.ndarray]:
        """:meth:`evaluate` of the neighbours of a 0/1 selection ``mask`` (Ne,) that switch the
        elements ``out[i]`` off and ``into[i]`` on (int ``(B, m)`` each, ``-1`` pads;
        :class:`~arraysel.objective.contract.ScoresMoves`), counted as ``B`` evaluations. On the
        fast path a dense set of swaps (many for each outgoing element, a whole neighbourhood) is
        scored from the selection's planes plus the low-rank change of each swap
        (:mod:`arraysel.objective.matrix_neighbours`): the same planes, to rounding, and the same
        metrics as scoring the masks; sparser requests, moves of several elements and the exact
        path score the masks."""
        from arraysel.objective.matrix_neighbours import check_selection
        from arraysel.objective.neighbours import check_moves, move_masks

        m, a, b = check_moves(mask, out, into)
        nb = self._neighbourhood()
        if nb is None or a.shape[0] == 0 or a.shape[1] != 1 or not (a >= 0).all() or not nb.dense(a[:, 0]):
            return self.evaluate(move_masks(m, a, b))
        check_selection(m, self.n_elements)
        with torch.no_grad(), self._timed():
            nb.select(m)
            res = nb.score(nb.swap_columns(a[:, 0], b[:, 0]), int(a.shape[0]))
            self.evaluations += int(a.shape[0])
        return {k: res[k] for k in (*METRIC_NAMES, *MERIT_NAMES)}

    def prepare_neighbourhoods(self) -> bool:
        """Form now what :meth:`evaluate_swaps` shares between selections on the fast path (the
        elements' transmit rows, their diagonal terms and the right factors of the cross terms,
        :mod:`arraysel.objective.matrix_neighbours`; about 1.3 GiB on matrix-1024), so that a
        search's first neighbourhoods do not pay for them. Returns True."""
        nb = self._neighbourhood()
        if nb is not None:
            nb.diagonal()
            nb.rights()
        return True


class MatrixObjectiveFactory(SceneObjectiveFactory):
    """Builds the :class:`MatrixObjective` of a 3-D scene on a worker (fields as
    :class:`~arraysel.objective.psf_objective.SceneObjectiveFactory`)."""

    def __hash__(self):
        return hash(self.key())

    def __call__(self):
        return build_objective(load_scene(dict(self.scene)), device=self.device, dtype=getattr(torch, self.dtype),
                               chunk=self.chunk, objective_class=MatrixObjective)
