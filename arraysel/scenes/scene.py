"""The :class:`Scene`: a validated scene's values, in its keys' units, and the settings an
objective reads from it (:class:`ObjectiveSettings`); its physics setups come from
:class:`~arraysel.scenes.setups.SceneSetups`.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

from arraysel.scenes.checks import check_scene
from arraysel.scenes.keys import SCHEMA
from arraysel.scenes.setups import SceneSetups
from arraysel.scenes.values import LENGTH_UNITS, merge, parse_length, validate_tree


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
class Scene(SceneSetups):
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
        tree = merge(self.tree, validate_tree(overrides))
        return finish(self.name, tree)

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
        num, unit = parse_length("grid.pixel", raw, SCHEMA["grid"]["pixel"])
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
        num, unit = parse_length(f"{section}.{key}", raw, spec)
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


    @property
    def is_volume(self) -> bool:
        """True for a 3-D scene (a ``[volume]`` section: a matrix probe imaged on planes)."""
        return "volume" in self.tree

    @property
    def is_sector(self) -> bool:
        """True for a sector scene (a ``[sector]`` section: a matrix probe's point targets over a
        steered sector, ``docs/sector.md``)."""
        return "sector" in self.tree

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


def finish(name: str, tree: dict) -> Scene:
    """The scene of a resolved, validated ``tree``, checked as a whole (:func:`~arraysel.scenes.checks.check_scene`)."""
    return check_scene(Scene(name=tree.get("name", name), tree=tree))
