"""Scenes: the TOML schema with its defaults (:mod:`arraysel.scenes.schema`) and the built-in scene files."""
from arraysel.scenes.schema import SCHEMA, Scene, builtin_scenes, load_scene

__all__ = ["SCHEMA", "Scene", "builtin_scenes", "load_scene"]
