"""Checking a scene's values against :data:`~arraysel.scenes.keys.SCHEMA`, and length units.

*Length* keys take a bare number in the key's own unit or a string with a unit: ``"3.5 mm"``,
``"20 um"``, ``"0.02 m"``, ``"1.5 wl"`` (wavelengths lambda0 = c / fc) or ``"128 px"`` (pixels of
the grid pitch). Here a length's unit is read and its sign checked; its value in the key's own
unit needs the whole scene (:meth:`arraysel.scenes.scene.Scene.length`).
"""
from __future__ import annotations

import copy
import math
import re
from typing import Any

from arraysel.errors import ParameterError, check_choice, check_number
from arraysel.scenes.keys import SCHEMA, TOP_LEVEL, Key

#: physical length units a string may carry (metres per unit); "wl" and "px" are scene-relative
LENGTH_UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6}
_LENGTH_RE = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zA-Zµ]+)\s*$")


def parse_length(key: str, value: Any, spec: Key) -> tuple[float, str]:
    """(number, unit) of a length value; a bare number is in ``spec.unit``."""
    if isinstance(value, str):
        m = _LENGTH_RE.match(value)
        if m is None:
            raise ParameterError(f"{key} must be a number ({spec.unit}) or a string with a unit like "
                                 f"'3.5 mm' (units: {', '.join(spec.units)}), got {value!r}")
        num, unit = float(m.group(1)), m.group(2).lower().replace("µ", "u")
        if unit not in spec.units:
            raise ParameterError(f"{key} = {value!r}: unit {m.group(2)!r} is not allowed here; "
                                 f"use one of {list(spec.units)}")
        if not math.isfinite(num):
            raise ParameterError(f"{key} = {value!r} must be finite")
        return num, unit
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParameterError(f"{key} must be a number ({spec.unit}) or a string with a unit like '3.5 mm' "
                             f"(units: {', '.join(spec.units)}), got {value!r}")
    return float(value), spec.unit


def _check_length(key: str, value: Any, spec: Key) -> Any:
    num, unit = parse_length(key, value, spec)
    lo, hi, lo_open = spec.cons
    if unit == spec.unit:
        check_number(key, value if not isinstance(value, str) else num, lo=lo, hi=hi, lo_open=lo_open,
                     integer=spec.integer and not isinstance(value, str))
    elif lo >= 0:  # the sign now; the range once the scene is complete (pitch and wavelength known)
        check_number(key, num, lo=0, lo_open=lo_open)
    return value.strip() if isinstance(value, str) else value


def _check_value(key: str, value: Any, spec: Key) -> Any:
    kind, cons = spec.kind, spec.cons
    if kind == "str":
        if not isinstance(value, str):
            raise ParameterError(f"{key} must be a string, got {value!r}")
        if cons is not None:
            check_choice(key, value.lower(), cons)
            return value.lower()
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            raise ParameterError(f"{key} must be true or false, got {value!r}")
        return value
    if kind == "int":
        lo, hi = cons
        return check_number(key, value, lo=lo, hi=hi, integer=True)
    if kind == "float":
        lo, hi, lo_open = cons
        if isinstance(value, str) and value.strip().lower() in ("inf", "infinity"):
            value = math.inf
        return check_number(key, value, lo=lo, hi=hi, lo_open=lo_open)
    if kind == "length":
        return _check_length(key, value, spec)
    if kind == "ints":
        lo, hi = cons
        if not isinstance(value, list):
            raise ParameterError(f"{key} must be a list of integers in [{lo}, {hi}], got {value!r}")
        return [check_number(f"{key}[{i}]", v, lo=lo, hi=hi, integer=True) for i, v in enumerate(value)]
    if kind == "points":
        lo, hi = cons
        if not isinstance(value, list) or not lo <= len(value) <= hi:
            raise ParameterError(f"{key} must be a list of {lo} to {hi} points [x, z], got {value!r}")
        xs = Key("length", (-1, 1, False), unit=spec.unit, units=spec.units)
        zs = Key("length", (0, 2, True), unit=spec.unit, units=spec.units)
        out = []
        for i, pt in enumerate(value):
            if not isinstance(pt, list) or len(pt) != 2:
                raise ParameterError(f"{key}[{i}] must be a pair [x, z] (lengths, {spec.unit} by default), "
                                     f"got {pt!r}")
            out.append([_check_length(f"{key}[{i}].x", pt[0], xs), _check_length(f"{key}[{i}].z", pt[1], zs)])
        return out
    if kind == "beams":
        lo, hi = cons
        if not isinstance(value, list) or not lo <= len(value) <= hi:
            raise ParameterError(f"{key} must be a list of {lo} to {hi} points [theta_x_deg, theta_y_deg, range], "
                                 f"got {value!r}")
        rs = Key("length", (0, 2, True), unit=spec.unit, units=spec.units)
        out = []
        for i, pt in enumerate(value):
            if not isinstance(pt, list) or len(pt) != 3:
                raise ParameterError(f"{key}[{i}] must be [theta_x_deg, theta_y_deg, range], got {pt!r}")
            ax = check_number(f"{key}[{i}].theta_x", pt[0], lo=-80, hi=80)
            ay = check_number(f"{key}[{i}].theta_y", pt[1], lo=-80, hi=80)
            out.append([ax, ay, _check_length(f"{key}[{i}].range", pt[2], rs)])
        return out
    raise AssertionError(kind)


def validate_tree(tree: dict) -> dict:
    """Check a scene dictionary against :data:`SCHEMA`; return a normalised deep copy."""
    if not isinstance(tree, dict):
        raise ParameterError("a scene must be a table of sections")
    out: dict = {}
    for key, value in tree.items():
        if key in TOP_LEVEL:
            if not isinstance(value, str):
                raise ParameterError(f"{key} must be a string, got {value!r}")
            out[key] = value
            continue
        if key not in SCHEMA:
            raise ParameterError(f"unknown scene key {key!r}; allowed sections: {sorted(SCHEMA)} "
                                 f"and keys {list(TOP_LEVEL)}")
        if not isinstance(value, dict):
            raise ParameterError(f"scene section {key!r} must be a table, got {value!r}")
        sec = {}
        for k, v in value.items():
            if k not in SCHEMA[key]:
                raise ParameterError(f"unknown scene key '{key}.{k}'; allowed in [{key}]: {sorted(SCHEMA[key])}")
            sec[k] = _check_value(f"{key}.{k}", v, SCHEMA[key][k])
        out[key] = sec
    return out


def merge(base: dict, over: dict) -> dict:
    """``base`` with the sections (and top-level keys) of ``over`` laid over it, key by key (copies)."""
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k].update(v)
        else:
            out[k] = copy.deepcopy(v)
    return out
