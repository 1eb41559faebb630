"""The plugin manager and the selector registry.

One plugin manager is built lazily (:func:`get_plugin_manager`):

1. add the hook specifications of :mod:`arraysel.selectors.hookspecs`;
2. block the plugin names listed in ``ARRAYSEL_DISABLE_PLUGINS``
   (comma-separated, e.g. ``ARRAYSEL_DISABLE_PLUGINS=arraysel.nlopt,mypkg``);
3. register the built-in plugin modules (:data:`BUILTIN_PLUGINS`), the same
   way any third-party module is registered;
4. ``load_setuptools_entrypoints("arraysel")`` for installed plugins;
5. ``check_pending()`` so a misspelt hook name fails loudly.

The :class:`SelectorRegistry` is then filled by calling every plugin's
``arraysel_register_selectors(register)`` hook; it remembers which plugin
registered each selector (its *origin*) and raises
:class:`DuplicateSelectorError` when two plugins claim the same name.

``--plugin MODULE_OR_PATH`` on the command line calls :func:`load_plugin`,
which imports a module by name or a ``.py`` file by path and registers it
without installing anything.

A plugin that fails while it is loaded (raises, or calls ``sys.exit``, at
import or in its ``arraysel_register_selectors`` hook; has hooks pluggy
refuses):

* given with ``--plugin`` (or a built-in one): :class:`PluginLoadError`, one
  line naming the plugin and what it raised (the command exits with code 2);
* installed (an entry point): skipped, with one warning line naming the entry
  point, its distribution and what it raised, so that one broken installed
  plugin does not stop every command; the other plugins load as usual.
  ``ARRAYSEL_DISABLE_PLUGINS`` silences it.
"""
from __future__ import annotations

import importlib
import importlib.util
import logging
import os
import re
import sys
import zlib
from pathlib import Path
from types import ModuleType
from typing import Iterable, Iterator

import pluggy

from arraysel.selectors import hookspecs
from arraysel.errors import ArrayselError, ParameterError, error_text
from arraysel.selectors.contract import Option, Selector

_log = logging.getLogger(__name__)

__all__ = [
    "BUILTIN_PLUGINS", "DISABLE_ENV", "ENTRY_POINT_GROUP", "DuplicateSelectorError",
    "PluginLoadError", "SelectorRegistry", "build_plugin_manager", "get_plugin_manager",
    "get_registry", "load_plugin", "reset", "plugin_origin",
]

#: built-in plugin modules, registered under these plugin names
BUILTIN_PLUGINS: dict[str, str] = {
    "arraysel.baselines": "arraysel_plugins.baselines",
    "arraysel.ste": "arraysel_plugins.ste",
    "arraysel.gumbel": "arraysel_plugins.gumbel",
    "arraysel.nlopt": "arraysel_plugins.nlopt_relax",
    "arraysel.greedy": "arraysel_plugins.greedy",
    "arraysel.swap": "arraysel_plugins.swap",
    "arraysel.ils": "arraysel_plugins.ils",
    "arraysel.anneal": "arraysel_plugins.anneal",
    "arraysel.genetic": "arraysel_plugins.genetic",
    "arraysel.memetic": "arraysel_plugins.memetic",
    "arraysel.lns": "arraysel_plugins.lns",
    "arraysel.nevergrad": "arraysel_plugins.nevergrad_bridge",
    "arraysel.spiral": "arraysel_plugins.spiral",
}
#: environment variable listing plugin names not to load
DISABLE_ENV = "ARRAYSEL_DISABLE_PLUGINS"
ENTRY_POINT_GROUP = hookspecs.PROJECT_NAME

_NAME_RE = re.compile(r"^[a-z][a-z0-9_\-]*$")
#: config names the runner uses itself
RESERVED_NAMES = frozenset({"full"})


class DuplicateSelectorError(ArrayselError):
    """Two plugins registered selectors with the same name."""


class PluginLoadError(ArrayselError):
    """A plugin given with ``--plugin`` could not be imported or registered."""


def disabled_plugins(env: dict | None = None) -> list[str]:
    """Plugin names listed in ``ARRAYSEL_DISABLE_PLUGINS``."""
    text = (os.environ if env is None else env).get(DISABLE_ENV, "")
    return [n.strip() for n in text.split(",") if n.strip()]


def build_plugin_manager(*, load_entrypoints: bool = True, builtins: bool = True,
                         disabled: Iterable[str] | None = None) -> pluggy.PluginManager:
    """Build a fresh plugin manager (see the module docstring for the steps).

    Parameters
    ----------
    load_entrypoints : load installed ``[project.entry-points.arraysel]`` plugins
        (tests pass False so that plugins installed on the machine cannot change results)
    builtins : register the built-in plugin modules
    disabled : plugin names to block; ``None`` reads ``ARRAYSEL_DISABLE_PLUGINS``
    """
    pm = pluggy.PluginManager(hookspecs.PROJECT_NAME)
    pm.add_hookspecs(hookspecs)
    for name in (disabled_plugins() if disabled is None else list(disabled)):
        pm.set_blocked(name)
    if builtins:
        for name, modname in BUILTIN_PLUGINS.items():
            if pm.is_blocked(name):
                continue
            pm.register(importlib.import_module(modname), name=name)
    if load_entrypoints:
        _load_entrypoints(pm)
    pm.check_pending()
    return pm


def _failure(exc: BaseException) -> str:
    """What a plugin did wrong, on one line."""
    if isinstance(exc, SystemExit):
        return f"it called sys.exit({exc.code!r})"
    return f"it raised {error_text(exc)}"


def _load_entrypoints(pm: pluggy.PluginManager) -> None:
    """``pm.load_setuptools_entrypoints`` after trying each entry point of the group alone: one
    that fails to import or to register (on a throwaway manager) is blocked with a warning line."""
    import importlib.metadata as md

    for dist in list(md.distributions()):
        for ep in dist.entry_points:
            if ep.group != ENTRY_POINT_GROUP or pm.get_plugin(ep.name) or pm.is_blocked(ep.name):
                continue
            try:
                plugin = ep.load()
                probe = pluggy.PluginManager(hookspecs.PROJECT_NAME)
                probe.add_hookspecs(hookspecs)
                probe.register(plugin, name=ep.name)
                probe.check_pending()
            except KeyboardInterrupt:
                raise
            except (Exception, SystemExit) as exc:
                dist_name = (dist.metadata["Name"] if dist.metadata else None) or "?"
                _log.warning("arraysel: skipping the installed plugin %r (entry point %s of %s %s): loading it "
                             "failed, %s; %s=%s silences this", ep.name, ep.value, dist_name, dist.version,
                             _failure(exc), DISABLE_ENV, ep.name)
                pm.set_blocked(ep.name)
    pm.load_setuptools_entrypoints(ENTRY_POINT_GROUP)


_PM: pluggy.PluginManager | None = None
_REGISTRY: "SelectorRegistry | None" = None


def get_plugin_manager() -> pluggy.PluginManager:
    """The process-wide plugin manager, built on first use."""
    global _PM
    if _PM is None:
        _PM = build_plugin_manager()
    return _PM


def get_registry(pm: pluggy.PluginManager | None = None) -> "SelectorRegistry":
    """The selector registry of ``pm`` (default: the process-wide manager, cached)."""
    global _REGISTRY
    if pm is not None:
        return SelectorRegistry.from_plugin_manager(pm)
    if _REGISTRY is None:
        _REGISTRY = SelectorRegistry.from_plugin_manager(get_plugin_manager())
    return _REGISTRY


def reset() -> None:
    """Forget the process-wide plugin manager and registry (they are rebuilt on next use)."""
    global _PM, _REGISTRY
    _PM = None
    _REGISTRY = None


def _invalidate_registry() -> None:
    global _REGISTRY
    _REGISTRY = None


def _import_path(path: Path) -> ModuleType:
    modname = "arraysel_plugin_file_" + re.sub(r"\W", "_", path.stem) + f"_{zlib.crc32(str(path).encode()):08x}"
    if modname in sys.modules:
        return sys.modules[modname]
    spec = importlib.util.spec_from_file_location(modname, path)
    if spec is None or spec.loader is None:
        raise PluginLoadError(f"cannot import plugin file {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[modname] = module
    try:
        spec.loader.exec_module(module)
    except KeyboardInterrupt:
        sys.modules.pop(modname, None)
        raise
    except (Exception, SystemExit) as exc:
        sys.modules.pop(modname, None)
        raise PluginLoadError(f"importing plugin file {path} failed: {_failure(exc)}") from None
    return module


def load_plugin(spec: str, pm: pluggy.PluginManager | None = None) -> str:
    """Import ``spec`` (a module name or a path to a ``.py`` file) and register it.

    Returns the plugin name it is registered under (the module name, or
    ``file:<absolute path>``). Loading the same plugin twice is a no-op.
    Raises :class:`PluginLoadError` with the reason when it cannot be loaded.
    """
    pm = get_plugin_manager() if pm is None else pm
    looks_like_path = spec.endswith(".py") or os.sep in spec or "/" in spec
    if looks_like_path:
        path = Path(spec).expanduser().resolve()
        if not path.is_file():
            raise PluginLoadError(f"plugin file {spec!r} does not exist")
        module = _import_path(path)
        name = f"file:{path}"
    else:
        try:
            module = importlib.import_module(spec)
        except ImportError as exc:
            missing = getattr(exc, "name", None)
            if missing and (spec == missing or spec.startswith(missing + ".")):
                raise PluginLoadError(f"cannot import plugin module {spec!r}: {exc}. "
                                      f"Give an importable module name or a path to a .py file") from None
            raise PluginLoadError(f"importing plugin module {spec!r} failed: {_failure(exc)}") from None
        except KeyboardInterrupt:
            raise
        except (Exception, SystemExit) as exc:
            raise PluginLoadError(f"importing plugin module {spec!r} failed: {_failure(exc)}") from None
        name = spec
    if not hasattr(module, "arraysel_register_selectors"):
        raise PluginLoadError(f"plugin {spec!r} defines no arraysel_register_selectors hook "
                              f"(decorate it with arraysel.selectors.hookspecs.hookimpl)")
    if pm.is_registered(module):
        return pm.get_name(module) or name
    if pm.is_blocked(name):
        raise PluginLoadError(f"plugin {name!r} is disabled by {DISABLE_ENV}")
    try:
        pm.register(module, name=name)
        pm.check_pending()
    except (ValueError, pluggy.PluginValidationError) as exc:
        raise PluginLoadError(f"cannot register plugin {spec!r}: {exc}") from exc
    if pm is _PM:
        _invalidate_registry()
    return name


def plugin_origin(pm: pluggy.PluginManager, plugin: object, plugin_name: str | None) -> str:
    """A short label for where a plugin comes from (name and distribution version)."""
    name = plugin_name or pm.get_name(plugin) or repr(plugin)
    for p, dist in pm.list_plugin_distinfo():
        if p is plugin:
            return f"{name} ({dist.project_name} {dist.version})"
    return name


class SelectorRegistry:
    """Selector classes by name, with the plugin each came from.

    ``registry[name]`` gives the class; an unknown name raises
    :class:`ParameterError` listing the known names.
    """

    def __init__(self):
        self._classes: dict[str, type[Selector]] = {}
        self._origins: dict[str, str] = {}

    @classmethod
    def from_plugin_manager(cls, pm: pluggy.PluginManager) -> "SelectorRegistry":
        reg = cls()
        caller = pm.hook.arraysel_register_selectors
        installed = {id(p) for p, _dist in pm.list_plugin_distinfo()}
        # hook implementations in registration order (built-ins first), so a
        # duplicate name is blamed on the later plugin
        for impl in caller.get_hookimpls():
            if getattr(impl, "hookwrapper", False) or getattr(impl, "wrapper", False):
                continue
            origin = plugin_origin(pm, impl.plugin, impl.plugin_name)
            classes: list = []
            try:
                impl.function(register=classes.append)
            except KeyboardInterrupt:
                raise
            except (Exception, SystemExit) as exc:
                if isinstance(exc, ArrayselError):
                    raise
                if id(impl.plugin) in installed:  # an installed plugin: skipped (module docstring)
                    _log.warning("arraysel: skipping the installed plugin %s: its arraysel_register_selectors "
                                 "failed, %s; %s=%s silences this", origin, _failure(exc), DISABLE_ENV,
                                 impl.plugin_name)
                    continue
                raise PluginLoadError(f"plugin {origin}: arraysel_register_selectors failed, "
                                      f"{_failure(exc)}") from None
            for selector_cls in classes:  # all or nothing: a hook that fails half-way adds none
                reg.register(selector_cls, origin=origin)
        return reg

    def register(self, selector_cls: type[Selector], origin: str = "<direct>") -> None:
        """Add ``selector_cls``; raise on a bad class or a duplicate name."""
        if not (isinstance(selector_cls, type) and issubclass(selector_cls, Selector)):
            raise ParameterError(f"plugin {origin} registered {selector_cls!r}, which is not a "
                                 f"subclass of arraysel.selectors.contract.Selector")
        name = selector_cls.name
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise ParameterError(f"plugin {origin}: selector class {selector_cls.__name__} has invalid "
                                 f"name {name!r} (use lower-case letters, digits, '_' or '-')")
        if name in RESERVED_NAMES:
            raise ParameterError(f"plugin {origin}: selector name {name!r} is reserved")
        if not isinstance(selector_cls.description, str) or not selector_cls.description.strip():
            raise ParameterError(f"plugin {origin}: selector {name!r} needs a one-line description")
        for key, opt in selector_cls.options.items():
            if not isinstance(opt, Option):
                raise ParameterError(f"plugin {origin}: option {name}.{key} is not an arraysel.selectors.contract.Option")
        if name in self._classes:
            raise DuplicateSelectorError(
                f"selector name {name!r} registered twice: by {self._origins[name]} and by {origin}; "
                f"disable one of them with {DISABLE_ENV}")
        self._classes[name] = selector_cls
        self._origins[name] = origin

    def __contains__(self, name: str) -> bool:
        return name in self._classes

    def __getitem__(self, name: str) -> type[Selector]:
        try:
            return self._classes[name]
        except KeyError:
            raise ParameterError(f"unknown selector {name!r}; known selectors: "
                                 f"{', '.join(self.names()) or '(none)'}") from None

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def __len__(self) -> int:
        return len(self._classes)

    def names(self) -> list[str]:
        return sorted(self._classes)

    def origin(self, name: str) -> str:
        self[name]
        return self._origins[name]

    def items(self) -> list[tuple[str, type[Selector]]]:
        return [(n, self._classes[n]) for n in self.names()]
