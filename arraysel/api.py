"""The Python API for notebooks and scripts (``import arraysel as asel``).

>>> import arraysel as asel                                        # doctest: +SKIP
>>> scene = asel.load_scene("paper")
>>> obj = asel.build_objective(scene)
>>> obj.evaluate_indices([list(range(0, 64, 2))])["Mean"]
>>> asel.evaluate("paper", [range(0, 64, 2), range(32)])   # pandas DataFrame, one row per selection
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

__all__ = ["CompareResult", "compare", "evaluate"]


def __getattr__(name):
    # CompareResult lives with compare (arraysel.run.compare); looked up on first use, so that
    # importing this module loads neither torch nor pandas
    if name == "CompareResult":
        from arraysel.run.compare import CompareResult

        return CompareResult
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _objective(scene, device: str, dtype: str):
    """The objective of a scene name, ``.toml`` path, :class:`~arraysel.scenes.schema.Scene` or ``"toy"``
    (a ``dtype`` or ``device`` it cannot take refused by name)."""
    from arraysel.errors import ParameterError, check_choice
    from arraysel.objective.build import objective_for

    check_choice("dtype", dtype, ("float32", "float64"))
    if not isinstance(device, str) or device.split(":")[0] not in ("cpu", "cuda"):
        raise ParameterError(f"device must be 'cpu' or 'cuda', got {device!r}")

    if isinstance(scene, str) and scene == "toy":
        return objective_for("toy", device, dtype)
    import torch

    from arraysel.objective.build import build_objective
    from arraysel.scenes.schema import Scene, load_scene

    return build_objective(scene if isinstance(scene, Scene) else load_scene(scene), device=device,
                           dtype=getattr(torch, dtype))


def evaluate(scene: Any = "paper", selections: Sequence = (), *, device: str = "cpu", dtype: str = "float32",
             objective=None) -> Any:
    """Score selections on a scene, as ``arraysel evaluate`` does, and return a pandas DataFrame.

    Parameters
    ----------
    scene : scene name, ``.toml`` path, :class:`~arraysel.scenes.schema.Scene` or ``"toy"``
    selections : a list of selections, each a sequence of 0-based active element indices, a
        :class:`~arraysel.selection.Selection` or a boolean mask of ``Ne`` values; or a 2-D array
        of ``(B, Ne)`` 0/1 masks
    device, dtype : of the objective (``"cpu"``/``"cuda"``, ``"float32"``/``"float64"``)
    objective : an already built objective (then ``scene``, ``device``, ``dtype`` are unused)

    Returns
    -------
    pandas DataFrame: one row per selection, in order: ``elements`` (the indices as text, ``"0 2
    4"``), ``k``, then every metric the objective returns (the Table-1 metrics; a 3-D scene's
    figures of merit; a several-point scene's per-point values), as float64.
    """
    import numpy as np
    import pandas as pd

    from arraysel.selection import format_elements, masks_from_indices

    obj = _objective(scene, device, dtype) if objective is None else objective
    rows = _indices(selections, int(obj.n_elements))
    res = obj.evaluate(masks_from_indices(rows, int(obj.n_elements))) if rows else {}
    out: dict[str, Any] = {"elements": [format_elements(r) for r in rows], "k": [len(r) for r in rows]}
    for name, value in res.items():
        v = np.asarray(value)
        if v.ndim == 1 and v.shape[0] == len(rows) and v.dtype.kind in "fiu":
            out[name] = v.astype(np.float64)
    return pd.DataFrame(out)


def _indices(selections, n: int) -> list[list[int]]:
    """The active indices of each selection given to :func:`evaluate`."""
    import numpy as np

    from arraysel.errors import ParameterError
    from arraysel.selection import Selection, mask_to_indices

    if hasattr(selections, "detach"):   # a torch tensor of masks
        selections = selections.detach().cpu().numpy()
    if isinstance(selections, np.ndarray):
        if selections.ndim != 2 or selections.shape[1] != n:
            raise ParameterError(f"selections: an array must hold (B, {n}) masks, got shape {selections.shape}")
        return [mask_to_indices(m) for m in selections]
    out = []
    for sel in selections:
        if isinstance(sel, Selection):
            out.append(list(sel.indices))
        elif isinstance(sel, np.ndarray) and sel.dtype == bool:
            out.append(mask_to_indices(sel))
        else:
            out.append([int(i) for i in sel])
    return out


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

    from arraysel.errors import ParameterError

    budget = Budget(seconds=budget_s, evaluations=budget_evals)
    if isinstance(selectors, str):  # "random,uniform", as --selectors takes them
        selectors = [s.strip() for s in selectors.split(",") if s.strip()]
    try:
        selectors = list(selectors)
    except TypeError:
        raise ParameterError(f"selectors must be a list of selector names, got {type(selectors).__name__}") from None
    if options is not None and not isinstance(options, dict):
        raise ParameterError(f"options must be a dict {{selector: {{option: value}}}}, got {type(options).__name__}")
    stray = [name for name in (options or {}) if name not in selectors]
    if stray:
        raise ParameterError(f"options names selector(s) {', '.join(map(repr, stray))}, not in selectors")
    if objective is None:
        objective = _objective(scene, device, dtype)
    if out_dir is None:
        out_dir = tempfile.mkdtemp(prefix="arraysel-compare-")
    opts = options or {}
    sels = [(name, opts.get(name) or {}) for name in selectors]
    with plots.collect_figures() as figs:
        result = _compare(objective, sels, out_dir=out_dir, seeds=seeds, budget=budget, resume=resume,
                          force=force, progress=progress, figures=figures, isolate=isolate, grace_s=grace_s,
                          command_line=["arraysel.compare(...)"])
    return dataclasses.replace(result, figures=dict(figs))
