"""Errors and argument checks shared by the whole package.

Every check names the parameter, the value it got and what is allowed, so a
user reading the message knows what to change.
"""
from __future__ import annotations

import math
from typing import Any, Iterable


class ArrayselError(Exception):
    """Base class of arraysel's own errors."""


class ParameterError(ArrayselError, ValueError):
    """A parameter is missing, of the wrong type or out of its allowed range."""


class SelectionError(ArrayselError, ValueError):
    """An element selection is invalid (repeated, out-of-range or wrong count)."""


class NumericalError(ArrayselError, FloatingPointError):
    """A computation produced NaN/Inf or a degenerate (e.g. all-zero) result."""


def check_number(name: str, value: Any, *, lo: float | None = None, hi: float | None = None,
                 lo_open: bool = False, hi_open: bool = False, integer: bool = False) -> float:
    """Return ``value`` as a float (or int) after checking it lies in the allowed range.

    ``lo``/``hi`` are inclusive unless ``lo_open``/``hi_open``. Raises
    :class:`ParameterError` naming ``name``, the value and the range.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)) and not hasattr(value, "__float__"):
        raise ParameterError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if integer:
        if not float(v).is_integer():
            raise ParameterError(f"{name} must be an integer, got {value!r}")
    if math.isnan(v):
        raise ParameterError(f"{name} must not be NaN")
    left = "(" if lo_open else "["
    right = ")" if hi_open else "]"
    rng = f"{left}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}{right}"
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise ParameterError(f"{name} = {value!r} is out of range; allowed: {rng}")
    if hi is not None and (v > hi or (hi_open and v == hi)):
        raise ParameterError(f"{name} = {value!r} is out of range; allowed: {rng}")
    return int(v) if integer else v


def check_choice(name: str, value: Any, choices: Iterable[Any]) -> Any:
    """Check ``value`` is one of ``choices``; raise :class:`ParameterError` listing them."""
    choices = list(choices)
    if value not in choices:
        raise ParameterError(f"{name} = {value!r} is not allowed; choose one of {choices}")
    return value


def error_text(exc: BaseException) -> str:
    """``"TypeName: message"`` on one line (``"TypeName"`` when the message is empty): how a run's
    failure is written into a row, a log line or a :class:`~arraysel.run.workers.TaskFailed`."""
    text = str(exc).strip().replace("\n", " ")
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
