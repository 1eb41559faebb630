"""The best-known selection of each built-in scene: the lowest ``Mean`` any search has found, with the
elements, the command that found it and when (``best_known.json`` beside this module).

``arraysel compare`` reports each configuration's gap to it (``gap_to_best_known`` of ``stats.csv``,
:mod:`arraysel.report.stats`). A value enters the file only after ``arraysel evaluate`` re-scored its
elements (float32, the scene's defaults); ``tests/test_scenes.py`` checks that each stored selection
has ``k`` distinct elements of the scene's probe.
"""
from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

__all__ = ["BEST_KNOWN_FILE", "best_known", "load_best_known"]

#: the stored best-known selections: ``{scene: {"k", "Mean", "elements", "command", "found", "rescored"}}``,
#: optionally ``long_runs`` (what runs of 30 min or more ended at), ``reference_Mean`` (a lower
#: value reported without its mask, which the gaps use then) and ``reference_note`` (where it
#: comes from)
BEST_KNOWN_FILE = Path(__file__).with_name("best_known.json")


@lru_cache(maxsize=1)
def _table() -> dict:
    return json.loads(BEST_KNOWN_FILE.read_text(encoding="utf-8"))


def load_best_known() -> dict[str, dict]:
    """Every stored entry by scene name (a copy)."""
    return {name: dict(entry) for name, entry in _table().items()}


def best_known(scene: str | None, k: int | None = None) -> dict | None:
    """The entry of built-in scene ``scene`` (``None`` when there is none, or when it was found for
    another ``k``)."""
    entry = _table().get(str(scene)) if scene is not None else None
    if entry is None or (k is not None and int(entry["k"]) != int(k)):
        return None
    return dict(entry)
