"""The files of ``arraysel apodize``: selections in, apodized weights and their table out.

:func:`compare_selections` reads the selections of a comparison folder (``run.json``'s scene,
``table1.csv``'s rows); :func:`arraysel.selectors.apodization.apodize_many` fits the weights of
each, and :func:`write_apodization` writes the files:

* ``apodize.csv``: two rows per selection, ``weighting = binary`` (the 0/1 selection) and
  ``weighting = apodized`` (its weights), each with the scene's loss and every metric; a row
  holds one weighting, never a mix;
* ``weights.csv``: one row per selected element (selection, config, element, weight);
* ``weights.json``: per selection, its elements, weights, losses, metrics before and after, the
  loss history and the options.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os

from arraysel.errors import ParameterError

__all__ = ["OUTPUT_FILES", "WEIGHTINGS", "compare_selections", "table_rows", "write_apodization"]

#: the files :func:`write_apodization` writes into its folder
OUTPUT_FILES = ("apodize.csv", "weights.csv", "weights.json")
#: the row labels of the two weightings in ``apodize.csv``
WEIGHTINGS = ("binary", "apodized")


def compare_selections(folder: str, configs=None) -> tuple[dict, list[tuple[str, str]]]:
    """``(scene dict, [(config, elements text), ...])`` of a folder written by ``arraysel compare``:
    the scene of its ``run.json`` and every row of its ``table1.csv`` that holds a selection (only
    the ``configs`` named, when given; an unknown name is refused, listing the folder's)."""
    from arraysel.report.tables import compare_folder

    scene, rows, table = compare_folder(folder, "--from-compare")
    rows = [r for r in rows if (r.get("elements") or "").strip()]
    names = [r.get("config") for r in rows]
    if configs is not None:
        bad = [c for c in configs if c not in names]
        if bad:
            raise ParameterError(f"--configs: {bad} not in {table!r}; its configs with a selection: {names}")
        rows = [r for r in rows if r["config"] in configs]
    if not rows:
        raise ParameterError(f"--from-compare: {table!r} holds no selection")
    return scene, [(r["config"], r["elements"]) for r in rows]


def _number(v) -> str:
    return "" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{float(v):.8g}"


def _finite(metrics: dict) -> dict:
    return {k: (float(v) if math.isfinite(float(v)) else None) for k, v in metrics.items()}


def table_rows(labels, results) -> tuple[list[str], list[list[str]]]:
    """``(header, rows)`` of ``apodize.csv``: per selection a ``binary`` row, then its ``apodized``
    row (module docstring)."""
    names = list(results[0].metrics_binary) if results else []
    header = ["selection", "config", "weighting", "k", "loss", *names, "min_weight", "elements"]
    rows = []
    for i, (label, res) in enumerate(zip(labels, results), start=1):
        idx = [int(e) for e in res.mask.nonzero()[0]]
        text = " ".join(map(str, idx))
        for weighting, loss, met, wmin in (("binary", res.loss_binary, res.metrics_binary, 1.0),
                                           ("apodized", res.loss_apodized, res.metrics_apodized,
                                            float(res.weights[idx].min()))):
            rows.append([str(i), label, weighting, str(len(idx)), _number(loss),
                         *[_number(met.get(n)) for n in names], _number(wmin), text])
    return header, rows


def _csv_text(header, rows) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue()


def write_apodization(folder: str, scene_name: str, labels, results) -> dict[str, str]:
    """Write :data:`OUTPUT_FILES` into ``folder`` (atomically, each) from the
    :class:`~arraysel.selectors.apodization.ApodizationResult` of each selection and its label;
    returns ``{name: path}``."""
    from arraysel.io.atomic import atomic_write_text

    os.makedirs(folder, exist_ok=True)
    header, rows = table_rows(labels, results)
    weights = [[str(i), label, str(int(e)), f"{res.weights[e]:.8g}"]
               for i, (label, res) in enumerate(zip(labels, results), start=1) for e in res.mask.nonzero()[0]]
    doc = {"scene": scene_name, "weightings": list(WEIGHTINGS), "selections": [
        {"selection": i, "config": label, "elements": [int(e) for e in res.mask.nonzero()[0]],
         "weights": [float(res.weights[e]) for e in res.mask.nonzero()[0]],
         "loss_binary": res.loss_binary, "loss_apodized": res.loss_apodized,
         "metrics_binary": _finite(res.metrics_binary), "metrics_apodized": _finite(res.metrics_apodized),
         "history": res.history, "options": {"w_min": res.settings.w_min, "steps": res.settings.steps,
                                             "lr": res.settings.lr, "method": res.settings.method}}
        for i, (label, res) in enumerate(zip(labels, results), start=1)]}
    paths = {name: os.path.join(folder, name) for name in OUTPUT_FILES}
    atomic_write_text(paths["weights.csv"], _csv_text(["selection", "config", "element", "weight"], weights))
    atomic_write_text(paths["weights.json"], json.dumps(doc, indent=1, allow_nan=False) + "\n")
    atomic_write_text(paths["apodize.csv"], _csv_text(header, rows))
    return paths
