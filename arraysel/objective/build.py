"""Build the objective a command or the notebook API asks for: a scene by name or path, or ``toy``
(the cheap synthetic :class:`~arraysel.objective.toy.ToyObjective`, Ne = 64, k = 32)."""
from __future__ import annotations

from arraysel.errors import ParameterError

__all__ = ["TOY_SCENE", "objective_for", "build_objective"]

#: the scene name that gives the toy objective, and its size
TOY_SCENE = "toy"
TOY_SIZE = (64, 32)


def objective_for(scene: str, device: str = "cpu", dtype_name: str = "float32", aggregate: str | None = None):
    """The objective of ``scene`` (``"toy"``: a :class:`~arraysel.objective.toy.ToyObjective`);
    ``aggregate`` overrides the scene's ``metrics.aggregate``."""
    import torch

    if device == "cuda" and not torch.cuda.is_available():
        raise ParameterError("--device cuda was given but torch sees no CUDA device")
    dtype = getattr(torch, dtype_name)
    if scene == TOY_SCENE:
        from arraysel.objective.toy import ToyObjective
        return ToyObjective(*TOY_SIZE, device=device, dtype=dtype)
    from arraysel.scenes.schema import load_scene

    over = {"metrics": {"aggregate": aggregate}} if aggregate else None
    return build_objective(load_scene(scene, overrides=over), device=device, dtype=dtype)


def build_objective(scene="paper", device="cpu", dtype=None, **kw):
    """Build (or reuse, within a process) the objective of a scene: the
    :class:`~arraysel.objective.psf_objective.Objective` over its imagers (1-D, 3-D and sector
    scenes; keywords: its own)."""
    import torch

    from arraysel.objective import psf_objective
    from arraysel.scenes.schema import Scene, load_scene

    try:
        torch.device(device)
    except (RuntimeError, TypeError):
        raise ParameterError(f"device must be 'cpu' or 'cuda' (or a torch device), got {device!r}") from None
    sc = scene if isinstance(scene, Scene) else load_scene(scene)
    obj = psf_objective.build_objective(sc, device=device, dtype=torch.float32 if dtype is None else dtype, **kw)
    mode = sc.section("aperture").get("mode", "shared")
    if mode == "shared":
        return obj
    from arraysel.objective.aperture import ApertureObjective  # docs/apertures.md

    return ApertureObjective(obj, mode, sc.get("aperture", "k_tx"), sc.get("aperture", "k_rx"))
