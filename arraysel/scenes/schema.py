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

This module gathers the scene API; each part lives in its own module:

* :mod:`arraysel.scenes.keys`: the key table :data:`SCHEMA` (:class:`Key`) and ``training_default``;
* :mod:`arraysel.scenes.values`: checking values against it, length units;
* :mod:`arraysel.scenes.scene`: :class:`Scene` (values in their units, field points) and
  :class:`ObjectiveSettings`;
* :mod:`arraysel.scenes.setups`: the probe, acquisition and PSF setups a scene describes;
* :mod:`arraysel.scenes.checks`: whole-scene checks (regions fit, 1-D versus 3-D keys);
* :mod:`arraysel.scenes.load`: ``load_scene`` and the built-in scene files.
"""
from __future__ import annotations

from arraysel.scenes.checks import PLANAR_ONLY_KEYS, PLANAR_ONLY_SECTIONS, VOLUME_ONLY_KEYS
from arraysel.scenes.keys import SCHEMA, TOP_LEVEL, Key, training_default
from arraysel.scenes.load import builtin_scenes, load_scene
from arraysel.scenes.scene import ObjectiveSettings, Scene
from arraysel.scenes.values import LENGTH_UNITS, validate_tree

__all__ = ["SCHEMA", "TOP_LEVEL", "Key", "training_default", "LENGTH_UNITS", "validate_tree", "Scene",
           "ObjectiveSettings", "load_scene", "builtin_scenes", "VOLUME_ONLY_KEYS", "PLANAR_ONLY_SECTIONS",
           "PLANAR_ONLY_KEYS"]
