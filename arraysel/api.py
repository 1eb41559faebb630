"""The Python API for notebooks and scripts (``import arraysel as asel``).

>>> import arraysel as asel                                        # doctest: +SKIP
>>> scene = asel.load_scene("paper")
>>> obj = asel.build_objective(scene)
>>> obj.evaluate_indices([list(range(0, 64, 2))])["Mean"]
>>> res = asel.compare("paper", ["uniform", "random"], budget_s=30)
>>> res.table            # pandas DataFrame (table1.csv: each selector's best run)
>>> res.stats            # pandas DataFrame (stats.csv: statistics over seeds)
>>> res.figures["psfs"]  # matplotlib Figure
>>> res.selections["random"].indices  # the selection table1.csv lists

Everything here is a thin layer over the modules that do the work
(:mod:`arraysel.scenes.schema`, :mod:`arraysel.objective.psf_objective`, :mod:`arraysel.run.compare`).
"""
from __future__ import annotations

import dataclasses
import os
from typing import Any, Sequence

__all__ = ["CompareResult", "compare"]


def __getattr__(name):
    # CompareResult lives with compare (arraysel.run.compare); looked up on first use, so that
    # importing this module loads neither torch nor pandas
    if name == "CompareResult":
        from arraysel.run.compare import CompareResult

        return CompareResult
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def compare(scene: Any = "paper", selectors: Sequence = ("uniform", "random"), *, seeds: Sequence[int] = (0,),
            budget_s: float | None = 60.0, budget_evals: int | None = None, options: dict | None = None,
            out_dir: str | os.PathLike | None = None, force: bool = False, resume: bool = False,
            device: str = "cpu", dtype: str = "float32", isolate: bool = False, grace_s: float | None = None,
            progress: bool = True, figures: bool = True, objective=None) -> "CompareResult":
    """Compare selectors on a scene, as ``arraysel compare`` does, and return the results.

    Parameters
    ----------
    scene : scene name, ``.toml`` path, :class:`~arraysel.scenes.schema.Scene`, dict, or ``"toy"``
    selectors : selector names (see ``arraysel list``)
    seeds : each selector runs once per seed
    budget_s, budget_evals : per-run limits (seconds must be finite; at least one limit)
    options : ``{selector: {option: value}}``
    out_dir : where the files go (default: a new temporary folder, kept)
    force, resume : as ``--force`` / ``--resume`` for a folder that already holds results
    device, dtype : of the objective (``"cpu"``/``"cuda"``, ``"float32"``/``"float64"``)
    isolate : run each selector in a child process stopped ``grace_s`` s after its budget
    objective : an already built objective (then ``scene``, ``device``, ``dtype`` are unused)

    Returns
    -------
    :class:`~arraysel.run.compare.CompareResult` (pandas DataFrames: ``table``, ``stats``, ``runs``,
    ``trace``; each configuration's ``selections``; the ``failures``) with its ``figures``
    (``{"masks", "psfs", "profiles", "trace", "anytime"}`` -> matplotlib Figure, those drawn).
    """
    import tempfile

    from arraysel.report import plots
    from arraysel.run.compare import compare as _compare
    from arraysel.selectors.contract import Budget

    budget = Budget(seconds=budget_s, evaluations=budget_evals)
    if objective is None:
        from arraysel.objective.build import objective_for as _build
        from arraysel.scenes.schema import Scene, load_scene

        if isinstance(scene, str) and scene == "toy":
            objective = _build("toy", device, dtype)
        else:
            import torch

            from arraysel.objective.build import build_objective
            objective = build_objective(scene if isinstance(scene, Scene) else load_scene(scene), device=device,
                                        dtype=getattr(torch, dtype))
    if out_dir is None:
        out_dir = tempfile.mkdtemp(prefix="arraysel-compare-")
    opts = options or {}
    sels = [(name, opts.get(name, {})) for name in selectors]
    with plots.collect_figures() as figs:
        result = _compare(objective, sels, out_dir=out_dir, seeds=list(seeds), budget=budget, resume=resume,
                          force=force, progress=progress, figures=figures, isolate=isolate, grace_s=grace_s,
                          command_line=["arraysel.compare(...)"])
    return dataclasses.replace(result, figures=dict(figs))
