"""The result columns of a scene scored over several imagers (field points): the headline metrics
aggregated over the points (their mean or their worst), every metric per point, their mean and
their worst (:func:`point_metric_names`, :func:`aggregated`), and the plane sets an evaluation keeps
(:func:`images_out`). :class:`~arraysel.objective.psf_objective.Objective` builds its rows with them.
"""
from __future__ import annotations

import numpy as np
import torch

from arraysel.objective.names import METRIC_NAMES

__all__ = ["AGGREGATES", "point_metric_names", "aggregated", "images_out"]

#: aggregates over the field points of a several-point scene
AGGREGATES = ("mean", "worst")


def point_metric_names(n_points: int) -> tuple[str, ...]:
    """Breakdown keys of a scene with ``n_points`` field points (none for one point).

    ``"<metric>@p<i>"`` for point i (in ``medium.points`` order), then
    ``"<metric>@mean"`` and ``"<metric>@worst"`` (the largest value over the
    points; every metric is lower-is-better).
    """
    if n_points <= 1:
        return ()
    names = [f"{m}@p{i}" for i in range(n_points) for m in METRIC_NAMES]
    names += [f"{m}@{a}" for a in AGGREGATES for m in METRIC_NAMES]
    return tuple(names)


def aggregated(per_point: list[dict], aggregate: str) -> dict[str, np.ndarray]:
    """The columns of a several-point scene from each point's metrics ``{name: (B,)}``: the headline
    metrics (the points' mean, or their worst for ``aggregate = "worst"``), then every metric per
    point, their mean and their worst (:func:`point_metric_names`)."""
    res = {}
    for name in METRIC_NAMES:
        st = torch.stack([d[name] for d in per_point], -1)
        mean, worst = st.mean(-1), st.amax(-1)
        res[name] = (mean if aggregate == "mean" else worst).numpy()
        for p, d in enumerate(per_point):
            res[f"{name}@p{p}"] = d[name].numpy()
        res[f"{name}@mean"] = mean.numpy()
        res[f"{name}@worst"] = worst.numpy()
    return res


def images_out(res: dict, kernels: bool, planes: bool, imagers) -> dict:
    """``res`` with the plane sets :meth:`~arraysel.objective.psf_objective.Objective.evaluate` kept as ``"kernels"`` ((B, w, w), or
    (B, P, w, w) for P points) and/or ``"planes"`` (``{name: (B, H, W)}``, or ``{"p<i>": ...}``), numpy."""
    sets = res.pop("_planes", None)
    one = len(imagers) == 1
    if kernels:
        w = imagers[0].setup.window
        ks = [s.kernel.numpy() if s is not None else np.zeros((0, w, w), np.complex64) for s in sets]
        res["kernels"] = ks[0] if one else np.stack(ks, 1)
    if planes:
        per = [{k: v.numpy() for k, v in s.images.items()} if s is not None else {} for s in sets]
        res["planes"] = per[0] if one else {f"p{i}": d for i, d in enumerate(per)}
    return res
