"""The objective assembled from its settings and imagers (``Objective.assemble``): the same scores as
the objective of the scene they come from, and nothing read from a scene."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from arraysel.errors import ParameterError
from arraysel.objective.build import build_objective
from arraysel.objective.psf_objective import Objective
from arraysel.scenes.schema import load_scene
from test_imagers import fixed_masks
from test_sector import TINY


@pytest.mark.parametrize("scene", ["matrix-1024", "tiny-sector"])
def test_an_objective_assembled_from_settings_and_imagers_scores_as_its_scene(scene):
    sc = load_scene(copy.deepcopy(TINY)) if scene == "tiny-sector" else load_scene(scene)
    whole = build_objective(sc)
    parts = Objective.assemble(whole.settings, whole.imagers)
    assert parts.scene is None and parts.constraints is None and parts.beams is None
    assert parts.worker_factory() is None and not hasattr(parts, "beam_metrics")
    assert (parts.device, parts.dtype, parts.chunk, parts.k) == (whole.device, whole.dtype, whole.chunk, whole.k)
    assert parts.breakdown_names == whole.breakdown_names and len(parts.points) == len(parts.imagers)
    masks = fixed_masks(whole.n_elements, whole.k)
    a, b = parts.evaluate(masks), whole.evaluate(masks)
    assert list(a) == list(b)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    w = torch.as_tensor(masks[:2] * 0.7 + 0.1, dtype=whole.dtype)
    torch.testing.assert_close(parts.mask_loss(w)[0], whole.mask_loss(w)[0], rtol=0, atol=0)


def test_settings_without_imagers_are_refused():
    with pytest.raises(ParameterError, match="imagers"):
        Objective(load_scene("matrix-1024").objective_settings())


def test_kernel_only_methods_ask_the_imagers():
    """What only serves kernels is refused by what the imagers give (a beam pattern: one plane off a
    pixel grid), and the quadratic model's pair basis is an imager's PSF model (none here)."""
    sector = build_objective(load_scene(copy.deepcopy(TINY)))
    with pytest.raises(ParameterError, match=r"planes, not a 2-D kernel .*\['pattern'\].*Objective\.planes"):
        sector.kernels(np.ones((1, sector.n_elements)))
    with pytest.raises(ParameterError, match=r"\['pattern'\]"):
        sector.evaluate(np.ones((1, sector.n_elements)), return_kernels=True)
    assert sector.image_kind == "planes" and set(sector.planes(np.ones((1, sector.n_elements)))) == {"pattern"}
    assert not sector.hessian_from_pairs and sector.psfs == [] and sector.imagers[0].psf_model is None
