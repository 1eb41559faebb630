"""The checks of a probe's fields, shared by every kind of probe (1-D, matrix, planar layout).

Each check returns the value it accepts (normalised: floats, lower-case baffle names) or raises
:class:`~arraysel.errors.ParameterError` naming the field, the value and what is allowed.
"""
from __future__ import annotations

import math
from typing import Any, Union

from arraysel.errors import ParameterError, check_number

__all__ = ["C_MIN", "C_MAX", "Baffle", "check_sound_speed", "positive", "check_baffle", "check_name",
           "check_transducer", "check_field_names"]

#: Range accepted for the speed of sound (m/s): air-like to very stiff solids.
C_MIN = 300.0
C_MAX = 10000.0

Baffle = Union[str, float]


def check_sound_speed(c: Any, name: str = "c") -> float:
    """Return the speed of sound ``c`` (m/s) as a float after checking it lies in [C_MIN, C_MAX]."""
    return check_number(name, c, lo=C_MIN, hi=C_MAX)


def positive(name: str, value: Any, *, allow_inf: bool = False) -> float:
    """A strictly positive number, finite unless ``allow_inf``."""
    v = check_number(name, value, lo=0.0, lo_open=True)
    if math.isinf(v) and not allow_inf:
        raise ParameterError(f"{name} = {value!r} must be finite; allowed: (0, inf)")
    return v


def check_baffle(value: Any) -> Baffle:
    """'soft', 'rigid' or a positive finite impedance ratio."""
    if isinstance(value, str):
        key = value.strip().lower()
        if key in ("soft", "rigid"):
            return key
        raise ParameterError(
            f"baffle = {value!r} is not allowed; use 'soft', 'rigid' or a positive number "
            "(ratio of the medium impedance to the baffle impedance)")
    try:
        v = check_number("baffle", value, lo=0.0, lo_open=True)
    except ParameterError as exc:
        raise ParameterError(
            f"{exc}; baffle must be 'soft', 'rigid' or a positive finite number") from None
    if math.isinf(v):
        raise ParameterError(f"baffle = {value!r} must be 'soft', 'rigid' or a positive finite number")
    return v


def check_name(name: Any) -> None:
    """A probe's name: a non-empty string."""
    if not isinstance(name, str) or not name.strip():
        raise ParameterError(f"name = {name!r} must be a non-empty string")


def check_transducer(probe, set_) -> None:
    """Check and set the fields every probe kind shares: ``fc``, ``bandwidth`` and ``baffle``."""
    set_("fc", positive("fc", probe.fc))
    set_("bandwidth", check_number("bandwidth", probe.bandwidth, lo=0.0, hi=200.0,
                                   lo_open=True, hi_open=True))
    set_("baffle", check_baffle(probe.baffle))


def check_field_names(changes: dict[str, Any], names: tuple) -> None:
    """Refuse keys of ``changes`` that are not among ``names``, naming them."""
    unknown = [k for k in changes if k not in names]
    if unknown:
        raise ParameterError(
            f"unknown probe field(s) {', '.join(map(repr, unknown))}; "
            f"allowed: {', '.join(names)}")
