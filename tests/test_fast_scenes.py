"""Fast path against the exact path on every built-in scene (issue 17), degenerate masks
included: the uniform mask, a random one, 'edges' (the k/2 outermost elements on each side,
whose peak can leave the scatterer) and 'centre' (the k middle elements).

Each scene's basis is built once (minutes for the 128-element probes on two cores): slow."""
import numpy as np
import pytest
import torch

from arraysel.objective.metrics import si_mse
from arraysel.objective.psf_objective import Objective
from arraysel.scenes.schema import builtin_scenes, load_scene

pytestmark = pytest.mark.slow


def _masks(ne, k, seed=0):
    uniform = np.zeros(ne)
    uniform[[(i * ne) // k for i in range(k)]] = 1
    rng = np.random.default_rng(seed)
    random = np.zeros(ne)
    random[rng.choice(ne, k, replace=False)] = 1
    edges = np.zeros(ne)
    edges[: k // 2] = 1
    edges[ne - (k - k // 2):] = 1
    centre = np.zeros(ne)
    centre[(ne - k) // 2:(ne - k) // 2 + k] = 1
    return torch.tensor(np.stack([uniform, random, edges, centre]), dtype=torch.float32)


@pytest.mark.parametrize("name", [n for n in builtin_scenes()
                                  if load_scene(n).weights.get("L_rec", 0) == 0 and not load_scene(n).is_volume and not load_scene(n).is_sector])
def test_fast_equals_exact_on_builtin_scene(name):
    obj = Objective(name)
    w = _masks(obj.n_elements, obj.k)
    for point, model in enumerate(obj.psfs):
        assert model.basis is not None, f"{name}: point {point} has no fast path"
        with torch.no_grad():
            kf, exact = model.kernels(w, return_info=True)
            ke = model.kernels_exact(w)
        err = si_mse(kf.to(torch.complex128), ke.to(torch.complex128))
        assert bool((err <= 1e-4).all()), (name, point, err.tolist(), exact.tolist())
