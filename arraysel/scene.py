"""Scenes: everything an objective depends on, as validated data.

A scene bundles the probe, the acquisition, the transmits, the medium (one
point scatterer), the image grid, the PSF window, the metric regions, the
loss weights, and (for end-to-end scenes) the data set and training
settings. Built-in scenes are TOML files in ``arraysel/scenes/``; a user's
scene file may start from one with ``base = "paper"`` and override any key.
Scene files are parsed as data (``tomllib``), never executed. Unknown keys
and out-of-range values raise :class:`~arraysel.errors.ParameterError`
naming the key (``section.key``).

Units: SI (m, s, Hz, m/s), angles in degrees in scene files, attenuation in
dB/cm/MHz, bandwidth in percent.
"""
from __future__ import annotations

import copy
import math
import os
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import numpy as np

from .errors import ParameterError, check_choice, check_number

# section -> key -> (kind, constraints); kinds: float, int, bool, str, floats (list), dict
_INF = math.inf
SCHEMA: dict[str, dict[str, tuple]] = {
    "probe": {
        "name": ("str", None),
        "n_elements": ("int", (1, 4096)),
        "pitch": ("float", (0, 1, True)),
        "width": ("float", (0, 1, True)),
        "height": ("float", (0, _INF, True)),
        "elevation_focus": ("float", (0, _INF, True)),
        "radius": ("float", (0, _INF, True)),
        "fc": ("float", (1e3, 1e9, False)),
        "bandwidth": ("float", (0, 200, True)),
        "baffle": ("str", ("soft", "rigid")),
    },
    "acquisition": {
        "fs": ("float", (1e3, 1e10, False)),
        "fs_over_fc": ("float", (1, 1000, False)),
        "c": ("float", (300, 10000, False)),
        "attenuation": ("float", (0, 100, False)),
        "tx_cycles": ("float", (0, 100, True)),
    },
    "transmit": {
        "n_tx": ("int", (1, 512)),
        "max_tilt_deg": ("float", (0, 89.9, False)),
    },
    "grid": {
        "n_x": ("int", (8, 8192)),
        "n_z": ("int", (8, 8192)),
        "pixel": ("float", (0, 1, True)),
        "pixel_per_wavelength_fs": ("float", (0, 1000, True)),
        "z_offset": ("int", (0, 10 ** 6)),
        "window": ("int", (4, 8192)),
    },
    "medium": {
        "scatterer_x": ("float", (-1, 1, False)),
        "scatterer_z": ("float", (0, 2, True)),
        "reflectivity": ("float", (0, 1e6, True)),
    },
    "receive": {
        "fnumber": ("float", (0, 100, False)),
        "iq_bandwidth": ("float", (0, 200, True)),
    },
    "selection": {
        "k": ("int", (1, 4096)),
    },
    "metrics": {
        "r_main": ("float", (0, 1000, True)),
        "r_guard": ("float", (0, 1000, True)),
        "quantile": ("float", (0, 1, False)),
    },
    "weights": {
        "L_PSF": ("float", (0, 1e9, False)),
        "L_conv": ("float", (0, 1e9, False)),
        "L_rec": ("float", (0, 1e9, False)),
        "L_contrast": ("float", (0, 1e9, False)),
        "L_SLR": ("float", (0, 1e9, False)),
        "L_ent": ("float", (0, 1e9, False)),
        "L_row": ("float", (0, 1e9, False)),
    },
    "simulator": {
        "db_thresh": ("float", (-400, 0, True)),
        "element_splitting": ("int", (0, 1000)),
        "full_frequency_directivity": ("bool", None),
        "frequency_step": ("float", (0, 10, True)),
        "fast_margin": ("int", (0, 4096)),
        "fast_block": ("int", (1, 4096)),
    },
    "data": {
        "dataset": ("str", ("mnist", "fashion")),
        "source": ("str", ("auto", "sample", "idx")),
        "image_size": ("int", (8, 1024)),
        "depth_min": ("float", (0, 2, False)),
        "depth_max": ("float", (0, 2, True)),
    },
    "training": {
        "epochs": ("int", (0, 100000)),
        "steps": ("int", (0, 10 ** 8)),
        "batch_size": ("int", (1, 100000)),
        "lr_mask": ("float", (0, 10, True)),
        "lr_ista": ("float", (0, 10, True)),
        "lr_head": ("float", (0, 10, True)),
        "tau_start": ("float", (1e-6, 1e6, False)),
        "tau_end": ("float", (1e-6, 1e6, False)),
        "tau_steps": ("int", (0, 10 ** 8)),
        "ista_layers": ("int", (1, 1000)),
        "finetune_epochs": ("int", (0, 100000)),
    },
}

TOP_LEVEL = ("name", "description", "base")


def _check_value(key: str, value: Any, kind: str, cons) -> Any:
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
        v = check_number(key, value, lo=lo, hi=hi, lo_open=lo_open)
        return v
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
            kind, cons = SCHEMA[key][k]
            sec[k] = _check_value(f"{key}.{k}", v, kind, cons)
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
class Scene:
    """A validated scene. ``tree`` holds the resolved sections (see :data:`SCHEMA`)."""

    name: str
    tree: dict = field(repr=False)

    def section(self, name: str) -> dict:
        return dict(self.tree.get(name, {}))

    def get(self, section: str, key: str, default=None):
        return self.tree.get(section, {}).get(key, default)

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

    # physics -------------------------------------------------------------------
    def probe(self):
        from .probes import get_probe

        p = self.section("probe")
        name = p.pop("name", "P4-2v")
        return get_probe(name, **p)

    def acquisition(self):
        from .probes import Acquisition

        probe = self.probe()
        a = self.section("acquisition")
        ratio = a.pop("fs_over_fc", None)
        fs = a.pop("fs", None)
        if fs is None:
            fs = (ratio or 4.0) * probe.fc
        elif ratio is not None:
            raise ParameterError("acquisition.fs and acquisition.fs_over_fc are exclusive: give one")
        return Acquisition(fs=fs, **a)

    def psf_setup(self):
        from .psf import PSFSetup
        from .simus import SimOptions

        probe = self.probe()
        acq = self.acquisition()
        t = self.section("transmit")
        n_tx = int(t.get("n_tx", 7))
        tilt = float(t.get("max_tilt_deg", 10.0))
        tilts = tuple(np.deg2rad(np.linspace(-tilt, tilt, n_tx))) if n_tx > 1 else (0.0,)
        g = self.section("grid")
        pixel = g.get("pixel")
        if pixel is None:
            pixel = acq.c / acq.fs / g.get("pixel_per_wavelength_fs", 4.0)
        m = self.section("medium")
        scat = None
        if "scatterer_x" in m or "scatterer_z" in m:
            z_default = (int(g.get("n_z", 400)) // 2 + int(g.get("z_offset", 0))) * pixel
            scat = (float(m.get("scatterer_x", 0.0)), float(m.get("scatterer_z", z_default)))
        sim = self.section("simulator")
        split = sim.get("element_splitting", 0)
        options = SimOptions(db_thresh=float(sim.get("db_thresh", -100.0)),
                             element_splitting=None if not split else int(split),
                             full_frequency_directivity=bool(sim.get("full_frequency_directivity", False)),
                             frequency_step=float(sim.get("frequency_step", 1.0)))
        r = self.section("receive")
        return PSFSetup(probe=probe, acq=acq, tilts=tilts, n_x=int(g.get("n_x", 400)), n_z=int(g.get("n_z", 400)),
                        pixel=pixel, z_offset=int(g.get("z_offset", 0)), scatterer=scat,
                        reflectivity=float(m.get("reflectivity", 1.0)), window=int(g.get("window", 128)),
                        fnumber=float(r.get("fnumber", 0.0)), iq_bandwidth=r.get("iq_bandwidth"),
                        options=options)


def _finish(name: str, tree: dict) -> Scene:
    scene = Scene(name=tree.get("name", name), tree=tree)
    probe = scene.probe()
    k = scene.get("selection", "k")
    if k is None:
        raise ParameterError("selection.k is required")
    if not 1 <= int(k) <= probe.n_elements:
        raise ParameterError(f"selection.k = {k} is out of range; allowed: [1, {probe.n_elements}] "
                             f"(the probe has {probe.n_elements} elements)")
    g = scene.section("grid")
    win = int(g.get("window", 128))
    if win > min(int(g.get("n_x", 400)), int(g.get("n_z", 400))):
        raise ParameterError(f"grid.window = {win} must not exceed grid.n_x and grid.n_z")
    met = scene.section("metrics")
    if met.get("r_guard", 2.5) < met.get("r_main", 1.5):
        raise ParameterError("metrics.r_guard must be >= metrics.r_main")
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
        s = str(name_or_path)
        if s.endswith(".toml") or os.path.sep in s:
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
