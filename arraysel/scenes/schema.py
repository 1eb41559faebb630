"""Scenes: everything an objective depends on, as validated data.

A scene bundles the probe, the acquisition, the transmits, the medium (one
or several point scatterers), the image grid, the PSF window, the metric
regions, the loss weights, and (for end-to-end scenes) the data set and
training settings. Built-in scenes are TOML files in ``arraysel/scenes/``; a
user's scene file may start from one with ``base = "paper"`` and override any
key. Scene files are parsed as data (``tomllib``), never executed. Unknown
keys and out-of-range values raise :class:`~arraysel.errors.ParameterError`
naming the key (``section.key``).

Units: SI (m, s, Hz, m/s), angles in degrees in scene files, attenuation in
dB/cm/MHz, bandwidth in percent. *Length* keys (:data:`SCHEMA` kind
``length``) also take a string with a unit: ``"3.5 mm"``, ``"20 um"``,
``"0.02 m"``, ``"1.5 wl"`` (wavelengths lambda0 = c / fc) or ``"128 px"``
(pixels of the grid pitch); a bare number is in the key's own unit (its
``unit`` in :data:`SCHEMA`: pixels for the grid sizes and the window,
wavelengths for the metric radii, metres for positions and the pitch). Every
key's default lives in :data:`SCHEMA` (``arraysel scenes NAME --show`` lists
them); ``docs/scenes.md`` describes the keys.
"""
from __future__ import annotations

import copy
import logging
import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import numpy as np

from arraysel.errors import ParameterError, check_choice, check_number

_INF = math.inf
_log = logging.getLogger(__name__)

#: physical length units a string may carry (metres per unit); "wl" and "px" are scene-relative
LENGTH_UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6}
_PHYSICAL = ("m", "mm", "um")
_LENGTH_RE = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zA-Zµ]+)\s*$")


@dataclass(frozen=True)
class Key:
    """One scene key: its kind, constraints, default and meaning.

    kind: ``float``, ``int``, ``bool``, ``str``, ``length`` (a number in
    ``unit`` or a string with one of ``units``) or ``points`` (a list of
    ``[x, z]`` lengths). cons: for numbers ``(lo, hi, lo_open)`` (ints:
    ``(lo, hi)``), in ``unit`` for lengths; for strings the allowed choices
    (None: any). default: the value used when no scene sets the key (None:
    none, or derived as ``help`` says).
    """

    kind: str
    cons: Any = None
    default: Any = None
    help: str = ""
    unit: str | None = None
    units: tuple = ()
    integer: bool = False


_GRID_UNITS = ("px", "m", "mm", "um", "wl")
_POS_UNITS = ("m", "mm", "um", "wl")
_W = (0, 1e9, False)

# section -> key -> Key
SCHEMA: dict[str, dict[str, Key]] = {
    "probe": {
        "name": Key("str", None, "P4-2v", "catalogue probe (arraysel.physics.probes.list_probes())"),
        "n_elements": Key("int", (1, 4096), None, "number of elements (default: the probe's; 1-D probes)"),
        "pitch": Key("float", (0, 1, True), None, "element pitch, m (default: the probe's; 1-D probes)"),
        "nx": Key("int", (1, 4096), None, "elements along x (default: the probe's; matrix probes)"),
        "ny": Key("int", (1, 4096), None, "elements along y (default: the probe's; matrix probes)"),
        "pitch_x": Key("float", (0, 1, True), None, "pitch along x, m (default: the probe's; matrix probes)"),
        "pitch_y": Key("float", (0, 1, True), None, "pitch along y, m (default: the probe's; matrix probes)"),
        "width": Key("float", (0, 1, True), None, "element width (along x), m (default: the probe's)"),
        "height": Key("float", (0, _INF, True), None, "element height (along y), m (default: the probe's)"),
        "elevation_focus": Key("float", (0, _INF, True), None, "elevation focus, m (default: the probe's)"),
        "radius": Key("float", (0, _INF, True), None, "radius of curvature, m; inf = linear (default: the probe's)"),
        "fc": Key("float", (1e3, 1e9, False), None, "centre frequency, Hz (default: the probe's)"),
        "bandwidth": Key("float", (0, 200, True), None, "pulse-echo bandwidth, % (default: the probe's)"),
        "baffle": Key("str", ("soft", "rigid"), None, "baffle (default: the probe's)"),
    },
    "acquisition": {
        "fs": Key("float", (1e3, 1e10, False), None, "sampling frequency, Hz (default: fs_over_fc * fc)"),
        "fs_over_fc": Key("float", (1, 1000, False), 4.0, "fs / fc when fs is not given"),
        "c": Key("float", (300, 10000, False), 1540.0, "speed of sound, m/s"),
        "attenuation": Key("float", (0, 100, False), 0.0, "attenuation, dB/cm/MHz"),
        "tx_cycles": Key("float", (0, 100, True), 1.0, "transmit pulse length, cycles"),
    },
    "transmit": {
        "n_tx": Key("int", (1, 512), 7, "number of plane waves (1-D probes)"),
        "max_tilt_deg": Key("float", (0, 89.9, False), 10.0, "tilts are linspace(-max, +max, n_tx), degrees "
                            "(3-D scenes: the largest tilt in x)"),
        "n_tx_x": Key("int", (1, 64), 3, "tilts in x (3-D scenes; the transmits are n_tx_x * n_tx_y)"),
        "n_tx_y": Key("int", (1, 64), 3, "tilts in y (3-D scenes)"),
        "max_tilt_deg_y": Key("float", (0, 89.9, False), None, "the largest tilt in y, degrees (3-D scenes; "
                              "default: max_tilt_deg)"),
        "source_distance": Key("length", (0, 1, False), 0.0, "3-D scenes: diverging waves from a virtual source "
                               "this far behind the array, m (0: plane waves)", "m", _POS_UNITS),
    },
    "grid": {
        "n_x": Key("length", (8, 8192, False), 400, "grid columns (lateral size)", "px", _GRID_UNITS, True),
        "n_z": Key("length", (8, 8192, False), 400, "grid rows (axial size)", "px", _GRID_UNITS, True),
        "pixel": Key("length", (0, 1, True), None, "grid pitch, both axes (default: (c / fs) / "
                     "pixel_per_wavelength_fs)", "m", _POS_UNITS),
        "pixel_per_wavelength_fs": Key("float", (0, 1000, True), 4.0, "pixels per c / fs when pixel is not given"),
        "z_offset": Key("int", (0, 10 ** 6), 0, "rows above the grid, px: z_i = (i + z_offset) pixel "
                        "(single-scatterer scenes; medium.points places each grid itself)"),
        "window": Key("length", (4, 8192, False), 128, "PSF window side (kernel size)", "px", _GRID_UNITS, True),
    },
    "medium": {
        "scatterer_x": Key("length", (-1, 1, False), None, "lateral position of the one scatterer, m "
                           "(default: 0)", "m", _POS_UNITS),
        "scatterer_z": Key("length", (0, 2, True), None, "depth of the one scatterer, m (default: the grid "
                           "row n_z // 2)", "m", _POS_UNITS),
        "points": Key("points", (1, 64), None, "field points [[x, z], ...] (lengths, m by default), each "
                      "simulated on its own grid centred on it; exclusive with scatterer_x/z and "
                      "grid.z_offset", "m", _POS_UNITS),
        "scatterer_y": Key("length", (-1, 1, False), None, "y of the one scatterer, m (3-D scenes; default: 0)",
                           "m", _POS_UNITS),
        "reflectivity": Key("float", (0, 1e6, True), 1.0, "reflection coefficient"),
    },
    "volume": {  # its presence makes a scene 3-D (a matrix probe, planes through the scatterer)
        "planes": Key("str", None, "xy,xz,yz", "the planes imaged, comma-separated: xy (the C-plane at the "
                      "scatterer's depth), xz, yz"),
        "half_x": Key("length", (0, 1000, True), 8.0, "half-size of the planes along x", "wl", _POS_UNITS),
        "half_y": Key("length", (0, 1000, True), 8.0, "half-size of the planes along y", "wl", _POS_UNITS),
        "half_z": Key("length", (0, 1000, True), 4.0, "half-size of the planes along z", "wl", _POS_UNITS),
        "pixels_per_wavelength": Key("float", (0.1, 100, False), 3.0, "pixel = lambda0 / this, every plane"),
        "fast": Key("bool", None, True, "use the fast 3-D path when its check passes (else the exact path)"),
    },
    "receive": {
        "fnumber": Key("float", (0, 100, False), 0.0, "receive f-number (0 = full aperture)"),
        "iq_bandwidth": Key("float", (0, 200, True), None, "I/Q low-pass bandwidth, % (default: the probe's)"),
    },
    "selection": {
        "k": Key("int", (1, 4096), None, "number of active elements (required)"),
    },
    "metrics": {
        "r_main": Key("length", (0, 1000, True), 1.5, "main-lobe radius", "wl", _GRID_UNITS),
        "r_guard": Key("length", (0, 1000, True), 2.5, "side-lobe region starts at this radius", "wl",
                       _GRID_UNITS),
        "quantile": Key("float", (0, 1, False), 0.99, "q of L_SLR_q"),
        "aggregate": Key("str", ("mean", "worst"), "mean", "headline metrics of a several-point scene: "
                         "the mean over points or the worst point"),
    },
    "weights": {name: Key("float", _W, 0.0, f"weight of {name} in the training loss")
                for name in ("L_PSF", "L_conv", "L_rec", "L_contrast", "L_SLR", "L_ent", "L_row")},
    "simulator": {
        "db_thresh": Key("float", (-400, 0, True), -100.0, "frequency components below this level are "
                         "dropped, dB"),
        "element_splitting": Key("int", (0, 1000), 0, "sub-elements per element (0 = ceil(width / lambda_min))"),
        "full_frequency_directivity": Key("bool", None, False, "directivity at every frequency"),
        "frequency_step": Key("float", (0, 10, True), 1.0, "frequency step, relative to MUST's"),
        "fast_margin": Key("int", (0, 4096), 8, "fast path: pixels around the window computed exactly"),
        "fast_block": Key("int", (1, 4096), 8, "fast path: side of the bound blocks, px"),
    },
    "data": {
        "dataset": Key("str", ("mnist", "fashion"), None, "image data set (end-to-end scenes)"),
        "source": Key("str", ("auto", "sample", "idx"), None, "where the images come from"),
        "image_size": Key("int", (8, 1024), None, "image side, px"),
        "depth_min": Key("float", (0, 2, False), None, "shallowest scatterer depth, m"),
        "depth_max": Key("float", (0, 2, True), None, "deepest scatterer depth, m"),
    },
    "training": {  # the one home of the training defaults (TrainConfig, E2ESettings read them)
        "epochs": Key("int", (0, 100000), 100, "training epochs (steps, when set, take precedence)"),
        "steps": Key("int", (0, 10 ** 8), None, "training steps (none: from epochs)"),
        "batch_size": Key("int", (1, 100000), 64, "scenes per batch"),
        "lr_mask": Key("float", (0, 10, True), 1e-4, "learning rate of the selection logits"),
        "lr_ista": Key("float", (0, 10, True), 5e-4, "learning rate of the ISTA parameters"),
        "lr_head": Key("float", (0, 10, True), 1e-4, "learning rate of the CNN head"),
        "tau_start": Key("float", (1e-6, 1e6, False), 6.0, "softmax temperature at step 0"),
        "tau_end": Key("float", (1e-6, 1e6, False), 1.2, "softmax temperature after the decay"),
        "tau_steps": Key("int", (0, 10 ** 8), 1500, "length of the cosine temperature decay, steps"),
        "ista_layers": Key("int", (1, 1000), 8, "unrolled ISTA layers"),
        "finetune_epochs": Key("int", (0, 100000), 0, "head fine-tuning epochs on the fixed selection"),
    },
}


def training_default(key: str):
    """The default of the scene key ``training.<key>`` (the one home of the training defaults)."""
    return SCHEMA["training"][key].default


TOP_LEVEL = ("name", "description", "base")


def _parse_length(key: str, value: Any, spec: Key) -> tuple[float, str]:
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
    num, unit = _parse_length(key, value, spec)
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


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k].update(v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def builtin_scenes() -> list[str]:
    """Names of the built-in scenes."""
    files = resources.files("arraysel") / "scenes"
    return sorted(p.name[:-5] for p in files.iterdir() if p.name.endswith(".toml"))


def _read_builtin(name: str) -> dict:
    path = resources.files("arraysel") / "scenes" / f"{name}.toml"
    if not path.is_file():
        raise ParameterError(f"unknown scene {name!r}; built-in scenes: {builtin_scenes()} (or give a .toml path)")
    return tomllib.loads(path.read_text())


def _resolve(tree: dict, seen: tuple = ()) -> dict:
    tree = validate_tree(tree)
    base = tree.pop("base", None)
    if base is None:
        return tree
    if base in seen:
        raise ParameterError(f"scene base cycle: {' -> '.join(seen + (base,))}")
    parent = _resolve(_read_builtin(base) if not base.endswith(".toml") else _read_file(base), seen + (base,))
    parent.pop("name", None)
    parent.pop("description", None)
    return _merge(parent, tree)


def _read_file(path: str) -> dict:
    try:
        with open(path, "rb") as fh:
            tree = tomllib.load(fh)
    except FileNotFoundError:
        raise ParameterError(f"scene file {path!r} does not exist") from None
    except IsADirectoryError:
        raise ParameterError(f"scene file {path!r} is a folder, not a file") from None
    except PermissionError:
        raise ParameterError(f"scene file {path!r} cannot be read (permission denied)") from None
    except UnicodeDecodeError as exc:
        raise ParameterError(f"scene file {path!r} is not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at "
                             f"offset {exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ParameterError(f"scene file {path!r} is not valid TOML: {exc}") from None
    except OSError as exc:
        raise ParameterError(f"scene file {path!r} cannot be read ({exc.strerror or exc})") from None
    base = tree.get("base")
    if isinstance(base, str) and base.endswith(".toml") and not os.path.isabs(os.path.expanduser(base)):
        # a relative base names a file next to this one, not in the working directory
        tree["base"] = os.path.join(os.path.dirname(os.path.abspath(path)), base)
    return tree


@dataclass(frozen=True)
class ObjectiveSettings:
    """What an objective reads from its scene, read once (:meth:`Scene.objective_settings`): the
    objective keeps this and its physics setups and never goes back to the scene.

    name: the scene's name (for messages); k: active elements; weights: the loss weights
    (``{term: weight}``, a read-only mapping); needs_data: a data term (L_conv, L_rec) is weighted;
    r_main, r_guard: metric radii (wavelengths); quantile: q of L_SLR_q; aggregate: several field
    points' headline (``mean`` or ``worst``); fast_margin, fast_block: the 1-D fast path's
    region and blocks (pixels); fast: a 3-D scene's ``volume.fast``; wavelength: lambda0 (m).
    """

    name: str
    k: int
    weights: Any
    needs_data: bool
    r_main: float
    r_guard: float
    quantile: float
    aggregate: str
    fast_margin: int
    fast_block: int
    fast: bool
    wavelength: float

    @property
    def metric_radii(self) -> dict[str, float]:
        """``r_main``, ``r_guard`` and ``quantile`` as the metric functions' keywords."""
        return {"r_main": self.r_main, "r_guard": self.r_guard, "quantile": self.quantile}


@dataclass(frozen=True)
class Scene:
    """A validated scene. ``tree`` holds the resolved sections (see :data:`SCHEMA`)."""

    name: str
    tree: dict = field(repr=False)

    def section(self, name: str) -> dict:
        """The keys this scene (or its base) sets in section ``name`` (no defaults)."""
        return dict(self.tree.get(name, {}))

    def get(self, section: str, key: str, default=None):
        return self.tree.get(section, {}).get(key, default)

    def value(self, section: str, key: str):
        """The value of ``section.key``: the scene's, else the default in :data:`SCHEMA`."""
        sec = self.tree.get(section, {})
        return sec[key] if key in sec else SCHEMA[section][key].default

    @property
    def description(self) -> str:
        return self.tree.get("description", "")

    @property
    def weights(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.section("weights").items()}

    @property
    def needs_data(self) -> bool:
        """True when a loss term that needs images (L_conv, L_rec) has a non-zero weight."""
        w = self.weights
        return w.get("L_conv", 0.0) > 0 or w.get("L_rec", 0.0) > 0

    @property
    def k(self) -> int:
        return int(self.get("selection", "k"))

    def to_dict(self) -> dict:
        return copy.deepcopy({"name": self.name, **self.tree})

    def replace(self, overrides: dict) -> "Scene":
        """A new scene with ``{section: {key: value}}`` overrides applied (validated)."""
        tree = _merge(self.tree, validate_tree(overrides))
        return _finish(self.name, tree)

    def objective_settings(self) -> ObjectiveSettings:
        """The settings an objective reads, typed and frozen (:class:`ObjectiveSettings`)."""
        from types import MappingProxyType

        return ObjectiveSettings(
            name=self.name, k=self.k, weights=MappingProxyType(dict(self.weights)), needs_data=self.needs_data,
            r_main=float(self.length("metrics", "r_main")), r_guard=float(self.length("metrics", "r_guard")),
            quantile=float(self.value("metrics", "quantile")), aggregate=str(self.value("metrics", "aggregate")),
            fast_margin=int(self.value("simulator", "fast_margin")), fast_block=int(self.value("simulator", "fast_block")),
            fast=bool(self.value("volume", "fast")), wavelength=self.wavelength)

    # units ---------------------------------------------------------------------
    @property
    def wavelength(self) -> float:
        """lambda0 = c / fc (m): the unit ``wl`` of length keys."""
        return float(self.value("acquisition", "c")) / self.probe().fc

    @property
    def pixel(self) -> float:
        """Grid pitch (m): ``grid.pixel``, else (c / fs) / ``grid.pixel_per_wavelength_fs``."""
        raw = self.get("grid", "pixel")
        if raw is None:
            acq = self.acquisition()
            return acq.c / acq.fs / float(self.value("grid", "pixel_per_wavelength_fs"))
        num, unit = _parse_length("grid.pixel", raw, SCHEMA["grid"]["pixel"])
        return self._to_metres(num, unit, pixel=None)

    def _to_metres(self, num: float, unit: str, pixel: float | None) -> float:
        if unit in LENGTH_UNITS:
            return num * LENGTH_UNITS[unit]
        if unit == "wl":
            return num * self.wavelength
        if unit == "px":
            return num * (self.pixel if pixel is None else pixel)
        raise AssertionError(unit)

    def length(self, section: str, key: str, value=None):
        """A length key (or ``value`` given in its syntax) in the key's own unit (:data:`SCHEMA`).

        Grid sizes and the window come back as whole pixels (rounded), the
        metric radii in wavelengths, positions and the pitch in metres.
        """
        spec = SCHEMA[section][key]
        raw = self.value(section, key) if value is None else value
        if raw is None:
            return None
        num, unit = _parse_length(f"{section}.{key}", raw, spec)
        if unit == spec.unit:
            out = num
        else:
            metres = self._to_metres(num, unit, pixel=None)
            out = {"m": metres, "wl": metres / self.wavelength, "px": metres / self.pixel}[spec.unit]
        if spec.integer:
            out = int(round(out))
        return out

    # field points --------------------------------------------------------------
    def points(self) -> list[tuple[float, float]]:
        """The field points (x, z) in metres: ``medium.points``, else the one scatterer."""
        pts = self.get("medium", "points")
        if pts is not None:
            return [(float(self.length("medium", "scatterer_x", x)), float(self.length("medium", "scatterer_z", z)))
                    for x, z in pts]
        pixel = self.pixel
        x = self.length("medium", "scatterer_x")
        z = self.length("medium", "scatterer_z")
        if z is None:
            z = (int(self.length("grid", "n_z")) // 2 + int(self.value("grid", "z_offset"))) * pixel
        return [(0.0 if x is None else float(x), float(z))]

    @property
    def n_points(self) -> int:
        pts = self.get("medium", "points")
        return 1 if pts is None else len(pts)

    # physics -------------------------------------------------------------------
    def probe(self):
        """The scene's probe: a :class:`~arraysel.physics.probes.Probe` or, for a matrix
        catalogue probe, a :class:`~arraysel.physics.probes.MatrixProbe` (keys of the other
        kind of probe are refused, naming the key)."""
        from arraysel.physics.probes import MATRIX_ONLY_FIELDS, LINEAR_ONLY_FIELDS, get_probe

        p = self.section("probe")
        name = p.pop("name", SCHEMA["probe"]["name"].default)
        matrix = get_probe(name).is_matrix
        wrong = [k for k in p if k in (LINEAR_ONLY_FIELDS if matrix else MATRIX_ONLY_FIELDS)]
        if wrong:
            kind, other = ("a matrix", "1-D") if matrix else ("a 1-D", "matrix")
            raise ParameterError(f"probe.{wrong[0]} applies to {other} probes only; probe.name = {name!r} is "
                                 f"{kind} probe")
        return get_probe(name, **p)

    def matrix_probe(self):
        """The scene's probe for a 3-D scene: refused, naming ``probe.name``, unless it is a matrix probe."""
        probe = self.probe()
        if not probe.is_matrix:
            raise ParameterError(f"probe.name = {probe.name!r} is a 1-D probe: a 3-D scene needs a matrix probe "
                                 "(e.g. 'MATRIX-32x32')")
        return probe

    @property
    def is_volume(self) -> bool:
        """True for a 3-D scene (a ``[volume]`` section: a matrix probe imaged on planes)."""
        return "volume" in self.tree

    def matrix_setup(self):
        """The :class:`~arraysel.physics.volume.MatrixPSFSetup` of a 3-D scene (``[volume]``)."""
        from arraysel.physics.volume import MatrixPSFSetup, diverging_delays3, plane_wave_delays3, tilt_grid

        if not self.is_volume:
            raise ParameterError(f"scene {self.name!r} has no [volume] section: it is not a 3-D scene")
        probe = self.matrix_probe()
        acq = self.acquisition()
        tx = self.value("transmit", "max_tilt_deg")
        ty = self.value("transmit", "max_tilt_deg_y")
        ax, ay = tilt_grid(int(self.value("transmit", "n_tx_x")), int(self.value("transmit", "n_tx_y")),
                           float(tx), float(tx if ty is None else ty))
        dist = float(self.length("transmit", "source_distance"))
        delays = (diverging_delays3(probe, ax, ay, dist, acq) if dist > 0 else plane_wave_delays3(probe, ax, ay, acq))
        lam = self.wavelength
        half = {k: float(self.length("volume", k)) * lam for k in ("half_x", "half_y", "half_z")}
        x = self.length("medium", "scatterer_x")
        y = self.length("medium", "scatterer_y")
        z = self.length("medium", "scatterer_z")
        return MatrixPSFSetup(probe=probe, acq=acq, delays=delays,
                              scatterer=(0.0 if x is None else float(x), 0.0 if y is None else float(y), float(z)),
                              pixel=lam / float(self.value("volume", "pixels_per_wavelength")),
                              planes=self.planes(), reflectivity=float(self.value("medium", "reflectivity")),
                              iq_bandwidth=self.value("receive", "iq_bandwidth"), options=self._sim_options(), **half)

    def planes(self) -> tuple[str, ...]:
        """The planes of a 3-D scene (``volume.planes``), checked."""
        from arraysel.physics.probes import MATRIX_PLANES as PLANES

        raw = str(self.value("volume", "planes"))
        names = tuple(p.strip() for p in raw.split(",") if p.strip())
        bad = [p for p in names if p not in PLANES]
        if bad or not names or len(set(names)) != len(names):
            raise ParameterError(f"volume.planes = {raw!r}: allowed a comma-separated subset of {list(PLANES)} "
                                 "without repeats")
        return names

    def _sim_options(self):
        from arraysel.physics.simus import SimOptions

        split = self.value("simulator", "element_splitting")
        return SimOptions(db_thresh=float(self.value("simulator", "db_thresh")),
                          element_splitting=None if not split else int(split),
                          full_frequency_directivity=bool(self.value("simulator", "full_frequency_directivity")),
                          frequency_step=float(self.value("simulator", "frequency_step")))

    def acquisition(self):
        from arraysel.physics.probes import Acquisition

        probe = self.probe()
        a = self.section("acquisition")
        ratio = a.pop("fs_over_fc", None)
        fs = a.pop("fs", None)
        if fs is None:
            fs = (ratio or SCHEMA["acquisition"]["fs_over_fc"].default) * probe.fc
        elif ratio is not None:
            raise ParameterError("acquisition.fs and acquisition.fs_over_fc are exclusive: give one")
        return Acquisition(fs=fs, **a)

    def psf_setups(self) -> list:
        """One :class:`~arraysel.physics.psf.PSFSetup` per field point (see :meth:`points`).

        With ``medium.points`` each point gets its own grid, shifted by whole
        pixels (``x_offset``, ``z_offset``) so that the point sits where the
        one-scatterer scene puts its scatterer: column ``n_x // 2``, row
        ``n_z // 2`` (to within half a pixel; rows never start above z = 0).
        """
        if self.get("medium", "points") is None:
            return [self.psf_setup()]
        pixel = self.pixel
        n_z = int(self.length("grid", "n_z"))
        out = []
        for x, z in self.points():
            z_off = max(0, int(round(z / pixel)) - n_z // 2)
            out.append(self._setup(x_offset=int(round(x / pixel)), z_offset=z_off, scatterer=(x, z)))
        return out

    def psf_setup(self, point: int = 0):
        """The :class:`~arraysel.physics.psf.PSFSetup` of field point ``point`` (the only one of most scenes)."""
        if self.get("medium", "points") is not None:
            setups = self.psf_setups()
            if not 0 <= point < len(setups):
                raise ParameterError(f"point = {point} is out of range; the scene has {len(setups)} point(s)")
            return setups[point]
        m = self.section("medium")
        scat = None
        if "scatterer_x" in m or "scatterer_z" in m:
            scat = self.points()[0]
        return self._setup(x_offset=0, z_offset=int(self.value("grid", "z_offset")), scatterer=scat)

    def _setup(self, x_offset: int, z_offset: int, scatterer):
        from arraysel.physics.psf import PSFSetup

        probe = self.probe()
        if probe.is_matrix:
            raise ParameterError(f"probe.name = {probe.name!r} is a matrix probe: this scene images the xz plane "
                                 "of a 1-D probe; a matrix probe needs a 3-D scene")
        _memory_check(self, probe.n_elements)
        acq = self.acquisition()
        n_tx = int(self.value("transmit", "n_tx"))
        tilt = float(self.value("transmit", "max_tilt_deg"))
        tilts = tuple(np.deg2rad(np.linspace(-tilt, tilt, n_tx))) if n_tx > 1 else (0.0,)
        pixel = self.pixel
        options = self._sim_options()
        return PSFSetup(probe=probe, acq=acq, tilts=tilts, n_x=int(self.length("grid", "n_x")),
                        n_z=int(self.length("grid", "n_z")), pixel=pixel, z_offset=z_offset, x_offset=x_offset,
                        scatterer=scatterer, reflectivity=float(self.value("medium", "reflectivity")),
                        window=int(self.length("grid", "window")), fnumber=float(self.value("receive", "fnumber")),
                        iq_bandwidth=self.value("receive", "iq_bandwidth"), options=options)

    def resolved(self) -> dict:
        """Every key of :data:`SCHEMA` for this scene: ``{section: {key: (value, resolved, source)}}``.

        ``value`` is what the scene (or its base) sets, else the default, else
        the value derived from other keys (the probe's fields, fs, the pitch);
        ``resolved`` the value in the key's own unit for lengths (None if the
        same); ``source`` is ``"scene"``, ``"default"`` or ``"derived"``.
        """
        derived = self._derived()
        out: dict = {}
        for sec, keys in SCHEMA.items():
            rows = {}
            for key, spec in keys.items():
                given = key in self.tree.get(sec, {})
                val = self.value(sec, key)
                if val is None and not given and (sec, key) in derived:
                    rows[key] = (derived[sec, key], None, "derived")
                    continue
                res = None
                if spec.kind == "length" and val is not None:
                    res = self.length(sec, key)
                    if not isinstance(val, str) and float(res) == float(val):
                        res = None
                if spec.kind == "points" and val is not None:
                    res = [(round(x, 9), round(z, 9)) for x, z in self.points()]
                rows[key] = (val, res, "scene" if given else "default")
            out[sec] = rows
        return out


    def _derived(self) -> dict:
        """Values of keys whose default is derived from other keys: {(section, key): value}."""
        probe = self.probe()
        out = {("probe", f): getattr(probe, f) for f in SCHEMA["probe"] if hasattr(probe, f)}
        out["acquisition", "fs"] = self.acquisition().fs
        out["grid", "pixel"] = self.pixel
        out["receive", "iq_bandwidth"] = probe.bandwidth
        if self.get("medium", "points") is None:
            x, z = self.points()[0]
            out["medium", "scatterer_x"], out["medium", "scatterer_z"] = x, z
        return out


def _region_checks(scene: Scene) -> None:
    """Windows, grids and metric regions in pixels: they must fit (errors name the keys)."""
    n_x, n_z = int(scene.length("grid", "n_x")), int(scene.length("grid", "n_z"))
    win = int(scene.length("grid", "window"))
    for key, n in (("n_x", n_x), ("n_z", n_z)):
        if not 8 <= n <= 8192:
            raise ParameterError(f"grid.{key} = {scene.value('grid', key)!r} is {n} pixels; allowed: [8, 8192] "
                                 f"pixels (pitch {scene.pixel * 1e3:.4g} mm)")
    if not 4 <= win <= 8192:
        raise ParameterError(f"grid.window = {scene.value('grid', 'window')!r} is {win} pixels; allowed: "
                             f"[4, 8192] pixels (pitch {scene.pixel * 1e3:.4g} mm)")
    if win > min(n_x, n_z):
        raise ParameterError(f"grid.window = {scene.value('grid', 'window')!r} must not exceed grid.n_x and "
                             f"grid.n_z (window {win} px, grid {n_x} x {n_z} px)")
    r_main = float(scene.length("metrics", "r_main"))
    r_guard = float(scene.length("metrics", "r_guard"))
    for key, r in (("r_main", r_main), ("r_guard", r_guard)):
        if not 0 < r <= 1000:
            raise ParameterError(f"metrics.{key} = {scene.value('metrics', key)!r} is {r:.4g} wavelengths; "
                                 f"allowed: (0, 1000]")
    if r_guard < r_main:
        raise ParameterError("metrics.r_guard must be >= metrics.r_main "
                             f"(r_main = {r_main:.4g} wl, r_guard = {r_guard:.4g} wl)")
    # in pixels, around the window's centre pixel (where the peak sits)
    lam_px = scene.wavelength / scene.pixel
    c = win // 2
    inscribed = min(c, win - 1 - c)
    corner = math.hypot(c, c)
    w_mm = win * scene.pixel * 1e3
    problem = None
    if r_main * lam_px > inscribed * (1 + 1e-9):
        problem = (
            f"metrics.r_main = {scene.value('metrics', 'r_main')!r} ({r_main * lam_px:.1f} px) does not fit "
            f"grid.window = {scene.value('grid', 'window')!r} ({win} px, {w_mm:.3g} mm): the main lobe region "
            f"must lie inside the window (r_main <= {inscribed} px = {inscribed / lam_px:.3g} wl); "
            f"enlarge grid.window or reduce metrics.r_main")
    elif r_guard * lam_px >= corner * (1 - 1e-9):
        problem = (
            f"metrics.r_guard = {scene.value('metrics', 'r_guard')!r} ({r_guard * lam_px:.1f} px) does not fit "
            f"grid.window = {scene.value('grid', 'window')!r} ({win} px, {w_mm:.3g} mm): the side-lobe region "
            f"r >= r_guard would be empty (r_guard < {corner:.1f} px = {corner / lam_px:.3g} wl needed); "
            f"enlarge grid.window or reduce metrics.r_guard")
    if problem is None:
        return
    if not scene.needs_data:
        raise ParameterError(problem)
    # an end-to-end scene's window is also the kernel of L_conv: small ones stay allowed there
    _log.warning("scene %r: %s (L_contrast and L_SLR are then 0 or partial)", scene.name, problem)


def _memory_check(scene: Scene, n_elements: int) -> None:
    """Refuse, from the sizes alone (nothing allocated), a grid whose setting up needs more memory
    than the cap ``ARRAYSEL_MEMORY_GIB`` (:func:`arraysel.physics.psf.settings.grid_bytes`):
    the message names the keys, the memory needed and allowed, and the largest grid allowed."""
    from arraysel.physics.psf.settings import MEMORY_GIB, grid_bytes, largest_grid_pixels, memory_limit_bytes

    n_x, n_z = int(scene.length("grid", "n_x")), int(scene.length("grid", "n_z"))
    win = int(scene.length("grid", "window"))
    need, step = grid_bytes(n_x, n_z, win, n_elements)
    limit = memory_limit_bytes()
    if need <= limit:
        return
    most = largest_grid_pixels(n_elements, limit)
    side = int(math.isqrt(most))
    raise ParameterError(
        f"grid.n_x x grid.n_z = {n_x} x {n_z} pixels needs about {need / 2 ** 30:.1f} GiB ({step}, "
        f"{n_elements} elements), more than the {limit / 2 ** 30:.1f} GiB allowed by {MEMORY_GIB}; allowed: "
        f"grid.n_x * grid.n_z up to about {most / 1e6:.3g} million pixels (e.g. {side} x {side}): reduce "
        f"grid.n_x / grid.n_z (or coarsen grid.pixel), or raise {MEMORY_GIB}")


#: keys that only a 3-D scene reads
VOLUME_ONLY_KEYS = (("transmit", "n_tx_x"), ("transmit", "n_tx_y"), ("transmit", "max_tilt_deg_y"),
                    ("transmit", "source_distance"), ("medium", "scatterer_y"))
#: keys that a 3-D scene does not read (it images planes, not the xz grid)
PLANAR_ONLY_SECTIONS = ("grid",)
PLANAR_ONLY_KEYS = (("transmit", "n_tx"), ("medium", "points"), ("receive", "fnumber"),
                    ("simulator", "fast_margin"), ("simulator", "fast_block"))


def _volume_checks(scene: Scene) -> None:
    """A 3-D scene: a matrix probe, one scatterer below the array, metric regions inside the planes."""
    scene.matrix_probe()
    for sec in PLANAR_ONLY_SECTIONS:
        if scene.section(sec):
            key = next(iter(scene.section(sec)))
            raise ParameterError(f"{sec}.{key} does not apply to a 3-D scene (its planes are set in [volume])")
    wrong = [f"{sec}.{key}" for sec, key in PLANAR_ONLY_KEYS if key in scene.section(sec)]
    if wrong:
        raise ParameterError(f"{wrong[0]} does not apply to a 3-D scene")
    if scene.length("medium", "scatterer_z") is None:
        raise ParameterError("medium.scatterer_z is required in a 3-D scene (the scatterer's depth, e.g. '30 mm')")
    scene.planes()
    halves = {k: float(scene.length("volume", k)) for k in ("half_x", "half_y", "half_z")}
    r_main = float(scene.length("metrics", "r_main"))
    r_guard = float(scene.length("metrics", "r_guard"))
    if r_guard < r_main:
        raise ParameterError("metrics.r_guard must be >= metrics.r_main "
                             f"(r_main = {r_main:.4g} wl, r_guard = {r_guard:.4g} wl)")
    if r_main > min(halves.values()):
        raise ParameterError(f"metrics.r_main = {r_main:.4g} wl does not fit the planes: allowed at most the "
                             f"smallest half-size, {min(halves.values()):.4g} wl (volume.half_x/y/z)")
    if r_guard >= max(halves.values()):
        raise ParameterError(f"metrics.r_guard = {r_guard:.4g} wl leaves no side-lobe region: allowed below the "
                             f"largest half-size, {max(halves.values()):.4g} wl (volume.half_x/y/z)")
    # the planes' pixels and extent (checked again, with the physics, by MatrixPSFSetup)
    per_wl = float(scene.value("volume", "pixels_per_wavelength"))
    for key, half in halves.items():
        n = max(1, int(round(2 * half * per_wl)))
        if n > 4096:
            raise ParameterError(f"volume.{key} = {half:.4g} wl is {n} pixels at volume.pixels_per_wavelength = "
                                 f"{per_wl:g}; allowed: at most 4096 pixels an axis")
    depth = float(scene.length("medium", "scatterer_z"))
    n_z = max(1, int(round(2 * halves["half_z"] * per_wl)))
    top = depth - (n_z // 2) * scene.wavelength / per_wl
    if top <= 0:
        raise ParameterError(f"volume.half_z = {halves['half_z']:.4g} wl reaches above the array from the "
                             f"scatterer's depth medium.scatterer_z = {depth:.4g} m; allowed: planes below z = 0")


def _finish(name: str, tree: dict) -> Scene:
    scene = Scene(name=tree.get("name", name), tree=tree)
    probe = scene.probe()
    k = scene.get("selection", "k")
    if k is None:
        raise ParameterError("selection.k is required")
    if not 1 <= int(k) <= probe.n_elements:
        raise ParameterError(f"selection.k = {k} is out of range; allowed: [1, {probe.n_elements}] "
                             f"(the probe has {probe.n_elements} elements)")
    if scene.is_volume:
        _volume_checks(scene)
        return scene
    wrong = [f"{sec}.{key}" for sec, key in VOLUME_ONLY_KEYS if key in scene.section(sec)]
    if wrong:
        raise ParameterError(f"{wrong[0]} applies to 3-D scenes only (a [volume] section and a matrix probe)")
    if scene.get("grid", "pixel") is not None:
        p = scene.pixel
        if not 0 < p <= 1:
            raise ParameterError(f"grid.pixel = {scene.get('grid', 'pixel')!r} is {p:.4g} m; allowed: (0, 1] m")
    _region_checks(scene)
    m = scene.section("medium")
    if "points" in m:
        clash = [f"medium.{k}" for k in ("scatterer_x", "scatterer_z") if k in m]
        clash += ["grid.z_offset"] if "z_offset" in scene.section("grid") else []
        if clash:
            raise ParameterError(f"medium.points and {', '.join(clash)} are exclusive: medium.points places "
                                 "each point's grid itself")
        for i, (x, z) in enumerate(scene.points()):
            if not -1 <= x <= 1:
                raise ParameterError(f"medium.points[{i}].x = {m['points'][i][0]!r} is {x:.4g} m; allowed: [-1, 1] m")
            if not 0 < z <= 2:
                raise ParameterError(f"medium.points[{i}].z = {m['points'][i][1]!r} is {z:.4g} m; allowed: (0, 2] m")
        if scene.needs_data and len(m["points"]) > 1:
            raise ParameterError("end-to-end scenes (weights.L_conv or weights.L_rec > 0) take one field point; "
                                 f"medium.points has {len(m['points'])}")
    else:
        for key, lo, hi, lo_open in (("scatterer_x", -1, 1, False), ("scatterer_z", 0, 2, True)):
            v = scene.length("medium", key)
            if v is not None:
                check_number(f"medium.{key} (m)", v, lo=lo, hi=hi, lo_open=lo_open)
    d = scene.section("data")
    if d and d.get("depth_max", 0.15) <= d.get("depth_min", 0.0):
        raise ParameterError("data.depth_max must be > data.depth_min")
    return scene


def load_scene(name_or_path: "str | Scene | dict", overrides: dict | None = None) -> Scene:
    """Load a built-in scene by name, a TOML scene file by path, or a dictionary.

    ``overrides`` ({section: {key: value}}) are applied last.
    """
    if isinstance(name_or_path, Scene):
        scene = name_or_path
        return scene.replace(overrides) if overrides else scene
    if isinstance(name_or_path, dict):
        tree = name_or_path
        name = tree.get("name", "custom")
    elif isinstance(name_or_path, (str, os.PathLike)):
        from arraysel.io.outputs import scene_input

        s = str(name_or_path)
        if scene_input(s) is not None:
            tree = _read_file(s)
            name = tree.get("name", os.path.splitext(os.path.basename(s))[0])
        else:
            tree = _read_builtin(s)
            name = s
    else:
        raise ParameterError(f"scene must be a name, a path or a dict, got {type(name_or_path).__name__}")
    resolved = _resolve(tree)
    if overrides:
        resolved = _merge(resolved, validate_tree(overrides))
    return _finish(name, resolved)
