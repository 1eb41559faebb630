"""What a plugin running in this process must leave as it found it, beyond the objective: the
functions the tables are computed with.

``compare`` computes every table (``table1.csv``, ``stats.csv``: medians, AOCC, confidence
intervals) in the ``arraysel`` process. A selector run there (``--in-process``), or a plugin
loaded there, could replace ``numpy.mean``, ``torch.mean``, a ``pandas.Series`` method or one of
arraysel's own report functions, and every later table would be wrong with nothing to show it.
:class:`Reductions` takes a snapshot of those functions (by identity, read from the modules' and
classes' own dictionaries, so looking imports or loads nothing) and says which were replaced,
removed or, where a class inherits them (``torch.Tensor.mean``), added since;
:meth:`Reductions.restore` puts them back.

What is watched (:data:`WATCHED`): every function of ``numpy``, ``math``, ``statistics``,
``scipy.stats`` and arraysel's report modules; the reductions of ``torch``, ``torch.Tensor``,
``pandas`` and its frames and series by name (torch itself replaces some of its other functions
when it loads ``torch._dynamo``, which is not a plugin's doing).
"""
from __future__ import annotations

import sys

__all__ = ["Reductions", "WATCHED", "describe", "watched_reductions"]

_TORCH = ("mean", "sum", "median", "nanmean", "nanmedian", "quantile", "std", "var", "min", "max", "amin", "amax",
          "argmin", "argmax", "sort", "argsort", "cumsum", "diff", "clamp", "clip", "log10", "isfinite",
          "tensor", "as_tensor", "from_numpy", "where")
_PANDAS = ("mean", "median", "quantile", "std", "var", "sum", "min", "max", "idxmin", "idxmax", "count",
           "groupby", "agg", "aggregate", "apply", "to_numpy", "to_csv", "sort_values", "cummin", "cumsum",
           "diff", "dropna", "fillna", "isna", "notna", "astype")
_BUILTINS = ("sum", "min", "max", "sorted", "abs", "round", "float", "int", "len", "map", "zip", "enumerate",
             "open", "print", "repr", "str", "isinstance")

#: ``(module, class or None, names or None)``: the functions watched (None: every function the
#: module or class holds itself); modules and classes not loaded when the snapshot is taken are left out
WATCHED = (
    ("builtins", None, _BUILTINS), ("math", None, None), ("statistics", None, None), ("numpy", None, None),
    ("torch", None, _TORCH), ("torch", "Tensor", _TORCH), ("pandas", None, ("to_numeric", "concat", "read_csv",
                                                                          "DataFrame", "Series", "isna")),
    ("pandas", "DataFrame", _PANDAS), ("pandas", "Series", _PANDAS),
    ("pandas.core.groupby.generic", "DataFrameGroupBy", _PANDAS),
    ("pandas.core.groupby.generic", "SeriesGroupBy", _PANDAS), ("scipy.stats", None, None),
    ("arraysel.report.stats", None, None), ("arraysel.report.tables", None, None),
    ("arraysel.report.summary", None, None), ("arraysel.report.columns", None, None),
    ("arraysel.run.store", None, None), ("arraysel.io.atomic", None, None),
)

_MISSING = object()


def _is_function(value) -> bool:
    return callable(value) or isinstance(value, (staticmethod, classmethod))


class Reductions:
    """A snapshot of the watched functions (see the module); :meth:`changed` lists what differs."""

    def __init__(self, watched=WATCHED):
        self.owners: dict[str, object] = {}
        self.snapshot: dict[tuple[str, str], object] = {}
        for modname, clsname, names in watched:
            owner = sys.modules.get(modname)
            if owner is not None and clsname is not None:
                owner = vars(owner).get(clsname)
                if not isinstance(owner, type):
                    continue
            if owner is None:
                continue
            where = modname if clsname is None else f"{modname}.{clsname}"
            own = vars(owner)
            self.owners[where] = owner
            if names is None:
                picked = {k: v for k, v in list(own.items()) if _is_function(v)}
            else:  # by name: one the class inherits is _MISSING here, and a change when it appears
                picked = {k: own.get(k, _MISSING) for k in names}
            self.snapshot.update({(where, k): v for k, v in picked.items()})

    def changed(self) -> list[str]:
        """``module.name`` of each watched function replaced, removed or added since the
        snapshot (sorted)."""
        return sorted(f"{where}.{key}" for (where, key), value in self.snapshot.items()
                      if vars(self.owners[where]).get(key, _MISSING) is not value)

    def restore(self) -> list[str]:
        """Put every changed function back; returns what was changed (as :meth:`changed`)."""
        changed = [(where, key) for (where, key), value in self.snapshot.items()
                   if vars(self.owners[where]).get(key, _MISSING) is not value]
        for where, key in changed:
            value = self.snapshot[(where, key)]
            if value is _MISSING:  # added where the class inherits it
                delattr(self.owners[where], key)
            else:
                setattr(self.owners[where], key, value)
        return sorted(f"{where}.{key}" for where, key in changed)


def describe(changed: list[str], most: int = 3) -> str:
    """``'numpy.mean and torch.mean'``, ``'numpy.mean, numpy.sum, torch.mean and 4 more'``: a list
    for a message."""
    if len(changed) > most:
        return ", ".join(changed[:most]) + f" and {len(changed) - most} more"
    return changed[0] if len(changed) == 1 else ", ".join(changed[:-1]) + " and " + changed[-1]


def watched_reductions() -> Reductions:
    """:class:`Reductions` of every watched module, each imported first (``arraysel compare``
    takes it before it loads any plugin)."""
    import importlib

    for name in ("numpy", "torch", "pandas", "arraysel.report.stats", "arraysel.report.tables",
                 "arraysel.report.summary", "arraysel.run.store"):
        importlib.import_module(name)
    return Reductions()
