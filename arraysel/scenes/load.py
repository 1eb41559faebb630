"""Loading a scene: a built-in name, a TOML file (its ``base`` first) or a dictionary.

Scene files are parsed as data (``tomllib``), never executed.
"""
from __future__ import annotations

import os
import tomllib
from importlib import resources

from arraysel.errors import ParameterError
from arraysel.scenes.scene import Scene, finish
from arraysel.scenes.values import merge, validate_tree


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
    return merge(parent, tree)


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
    probe = tree.get("probe")
    if isinstance(probe, dict) and isinstance(probe.get("file"), str) and probe["file"].strip():
        # a relative probe file, like a relative base, names a file next to this one
        where = os.path.expanduser(probe["file"].strip())
        if not os.path.isabs(where):
            probe["file"] = os.path.join(os.path.dirname(os.path.abspath(path)), where)
    cons = tree.get("constraints")
    if isinstance(cons, dict) and isinstance(cons.get("groups"), str) and cons["groups"].strip().endswith(".csv"):
        # a relative group file, like a probe file, names a file next to this one
        where = os.path.expanduser(cons["groups"].strip())
        if not os.path.isabs(where):
            cons["groups"] = os.path.join(os.path.dirname(os.path.abspath(path)), where)
    base = tree.get("base")
    if isinstance(base, str) and base.endswith(".toml") and not os.path.isabs(os.path.expanduser(base)):
        # a relative base names a file next to this one, not in the working directory
        tree["base"] = os.path.join(os.path.dirname(os.path.abspath(path)), base)
    return tree


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
        resolved = merge(resolved, validate_tree(overrides))
    return finish(name, resolved)
