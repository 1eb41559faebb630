"""Tests of the plugin system: hookspecs, plugin manager, registry, `--plugin`, `arraysel list`."""
from __future__ import annotations

import importlib.metadata
import subprocess
import sys
import types
from pathlib import Path

import pandas as pd
import pytest

from arraysel import cli

from arraysel.selectors import registry
from arraysel.selectors.hookspecs import hookimpl, hookspec
from arraysel.selectors.registry import (DuplicateSelectorError, PluginLoadError, build_plugin_manager, get_registry,
                               load_plugin)
from arraysel.selectors.contract import Option, Selector

ROOT = Path(__file__).resolve().parents[1]
SINGLE_FILE = ROOT / "examples" / "single_file_plugin.py"
EXAMPLE_SRC = ROOT / "examples" / "arraysel-example-plugin" / "src"
BUILTINS = {"uniform", "random", "ste", "gumbel", "nlopt", "greedy", "swap", "ils", "anneal", "genetic", "memetic",
            "lns", "nevergrad", "spiral"}


@pytest.fixture
def isolated_pm(monkeypatch):
    """A process-wide plugin manager without installed entry points, restored afterwards."""
    monkeypatch.delenv(registry.DISABLE_ENV, raising=False)
    pm = build_plugin_manager(load_entrypoints=False)
    registry.reset()
    registry._PM = pm
    try:
        yield pm
    finally:
        registry.reset()


def _compare_args(tmp_path, selectors, *extra):
    return ["compare", "--selectors", selectors, "--scene", "toy", "--budget-evals", "40",
            "--budget-s", "10", "--out", str(tmp_path), "--no-progress", "--no-figures", *extra]


def test_markers_use_the_project_name():
    assert hookspec.project_name == "arraysel" and hookimpl.project_name == "arraysel"


def test_builtins_register_through_the_hook_with_origins():
    reg = get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))
    assert set(reg.names()) == BUILTINS
    assert reg.origin("uniform") == reg.origin("random") == "arraysel.baselines"
    assert reg.origin("ste") == "arraysel.ste"
    with pytest.raises(Exception, match="known selectors: anneal, genetic, greedy, gumbel, ils, lns, memetic, nevergrad, nlopt, random, spiral, ste, swap, uniform"):
        reg["nope"]


def test_duplicate_name_raises():
    class Twin(Selector):
        name = "uniform"
        description = "clashes with the built-in"

        def select(self, objective, k, seed):
            return list(range(k))

    plugin = types.SimpleNamespace(arraysel_register_selectors=hookimpl(lambda register: register(Twin)))
    pm = build_plugin_manager(load_entrypoints=False, disabled=())
    pm.register(plugin, name="twin-plugin")
    try:
        with pytest.raises(DuplicateSelectorError, match="arraysel.baselines and by twin-plugin"):
            get_registry(pm)
    finally:
        pm.unregister(name="twin-plugin")


@pytest.mark.parametrize("bad", [int, "text"])
def test_registering_a_non_selector_raises(bad):
    reg = registry.SelectorRegistry()
    with pytest.raises(Exception, match="not a subclass"):
        reg.register(bad, origin="x")


def test_invalid_names_and_options_raise():
    reg = registry.SelectorRegistry()
    bad_name = type("B", (Selector,), {"name": "Bad Name", "description": "d"})
    with pytest.raises(Exception, match="invalid name"):
        reg.register(bad_name)
    reserved = type("R", (Selector,), {"name": "full", "description": "d"})
    with pytest.raises(Exception, match="reserved"):
        reg.register(reserved)
    no_desc = type("N", (Selector,), {"name": "nodesc", "description": ""})
    with pytest.raises(Exception, match="description"):
        reg.register(no_desc)


def test_disable_list_from_environment(monkeypatch):
    monkeypatch.setenv(registry.DISABLE_ENV, "arraysel.nlopt, arraysel.gumbel")
    reg = get_registry(build_plugin_manager(load_entrypoints=False))
    assert set(reg.names()) == BUILTINS - {"nlopt", "gumbel"}


def test_check_pending_catches_misspelt_hooks():
    plugin = types.ModuleType("misspelt_plugin")
    plugin.arraysel_register_selectors = hookimpl(lambda register: None)
    plugin.arraysel_register_selector = hookimpl(lambda register: None)  # typo: no such hook
    sys.modules["misspelt_plugin"] = plugin
    pm = build_plugin_manager(load_entrypoints=False, disabled=())
    try:
        with pytest.raises(PluginLoadError, match="arraysel_register_selector"):
            load_plugin("misspelt_plugin", pm)
    finally:
        del sys.modules["misspelt_plugin"]
        if pm.is_registered(plugin):
            pm.unregister(plugin)


def test_load_plugin_errors():
    pm = build_plugin_manager(load_entrypoints=False, disabled=())
    with pytest.raises(PluginLoadError, match="does not exist"):
        load_plugin("/no/such/file.py", pm)
    with pytest.raises(PluginLoadError, match="cannot import"):
        load_plugin("no_such_module_xyz", pm)
    with pytest.raises(PluginLoadError, match="no arraysel_register_selectors"):
        load_plugin("json", pm)


def test_load_plugin_file_twice_is_a_no_op():
    pm = build_plugin_manager(load_entrypoints=False, disabled=())
    name = load_plugin(str(SINGLE_FILE), pm)
    assert load_plugin(str(SINGLE_FILE), pm) == name
    reg = get_registry(pm)
    assert "centre" in reg and reg.origin("centre") == f"file:{SINGLE_FILE}"


class _FakeDist:
    """What importlib.metadata.distributions() yields, for one installed plugin package."""

    metadata = {"name": "arraysel-example-plugin"}
    version = "0.1.0"
    entry_points = [importlib.metadata.EntryPoint(name="example-swap", value="arraysel_example_plugin",
                                                  group="arraysel")]


def test_installed_style_plugin_through_entry_points(isolated_pm, monkeypatch, tmp_path, capsys):
    """An installed plugin (simulated entry point) shows up in `arraysel list` and in table1.csv."""
    monkeypatch.syspath_prepend(str(EXAMPLE_SRC))
    monkeypatch.setattr(importlib.metadata, "distributions", lambda: [_FakeDist()])
    assert isolated_pm.load_setuptools_entrypoints("arraysel") == 1
    try:
        assert cli.main(["list"]) == 0
        out = capsys.readouterr().out
        line = next(l for l in out.splitlines() if l.startswith("random-swap "))
        assert "example-swap (arraysel-example-plugin 0.1.0)" in line and "local search" in line
        assert cli.main(_compare_args(tmp_path, "random-swap,uniform")) == 0
        table = pd.read_csv(tmp_path / "table1.csv", keep_default_na=False)
        assert list(table["config"]) == ["full", "random-swap", "uniform"]
        assert (table["error"] == "").all()
    finally:
        isolated_pm.unregister(name="example-swap")
    assert "random-swap" not in get_registry(isolated_pm)


def test_plugin_object_registered_on_the_manager(isolated_pm, tmp_path, capsys):
    """A plugin registered directly on the process-wide manager behaves like a built-in."""
    class Last(Selector):
        name = "last-k"
        description = "the last k elements"
        options = {"unused": Option(int, 0, "an option, to test -o", lo=0)}

        def select(self, objective, k, seed):
            return list(range(objective.n_elements - k, objective.n_elements))

    plugin = types.SimpleNamespace(arraysel_register_selectors=hookimpl(lambda register: register(Last)))
    isolated_pm.register(plugin, name="last-plugin")
    try:
        registry._invalidate_registry()
        assert cli.main(["list"]) == 0
        out = capsys.readouterr().out
        assert any(l.split()[:2] == ["last-k", "last-plugin"] for l in out.splitlines())
        # its class reaches no child process (not pickled by name, no plugin a child can load):
        # refused naming --in-process, with which it runs
        assert cli.main(_compare_args(tmp_path, "last-k", "-o", "last-k.unused=3")) == 2
        assert "selector 'last-k' cannot run isolated" in capsys.readouterr().err
        assert cli.main(_compare_args(tmp_path, "last-k", "-o", "last-k.unused=3", "--in-process")) == 0
        table = pd.read_csv(tmp_path / "table1.csv", keep_default_na=False)
        assert "last-k(unused=3)" in list(table["config"])
        assert table.set_index("config").loc["last-k(unused=3)", "elements"] == " ".join(map(str, range(32, 64)))
    finally:
        isolated_pm.unregister(name="last-plugin")
        registry._invalidate_registry()


def test_single_file_plugin_with_cli_option(isolated_pm, tmp_path, capsys):
    try:
        assert cli.main(["list", "--plugin", str(SINGLE_FILE)]) == 0
        out = capsys.readouterr().out
        assert any(l.startswith("centre ") and "file:" in l for l in out.splitlines())
        assert cli.main(_compare_args(tmp_path, "centre,uniform", "--plugin", str(SINGLE_FILE))) == 0
        table = pd.read_csv(tmp_path / "table1.csv", keep_default_na=False)
        row = table.set_index("config").loc["centre"]
        assert row["elements"] == " ".join(map(str, range(16, 48))) and row["error"] == ""
    finally:
        for plugin in list(isolated_pm.get_plugins()):
            if (isolated_pm.get_name(plugin) or "").startswith("file:"):
                isolated_pm.unregister(plugin)


def test_cli_rejects_unknown_selector_and_bad_options(isolated_pm, tmp_path, capsys):
    assert cli.main(_compare_args(tmp_path, "ste,nosuch")) == 2
    err = capsys.readouterr().err
    assert "unknown selector(s) nosuch" in err and "anneal, genetic, greedy, gumbel, ils, lns, memetic, nevergrad, nlopt, random, spiral, ste, swap, uniform" in err
    assert cli.main(_compare_args(tmp_path, "ste", "-o", "ste.nosuch=1")) == 2
    assert "has no option 'nosuch'" in capsys.readouterr().err
    assert cli.main(_compare_args(tmp_path, "ste", "-o", "ste.lr=abc")) == 2
    assert "not a valid float" in capsys.readouterr().err
    assert cli.main(_compare_args(tmp_path, "ste", "-o", "random.n=3")) == 2
    assert "not in --selectors" in capsys.readouterr().err
    assert cli.main(_compare_args(tmp_path, "ste", "-o", "ste.draw=maybe")) == 2
    assert "choose one of" in capsys.readouterr().err
    assert cli.main(_compare_args(tmp_path, "ste", "--plugin", "/no/such.py")) == 2
    assert "does not exist" in capsys.readouterr().err


def test_installed_command_lists_builtins():
    exe = Path(sys.executable).with_name("arraysel")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "arraysel.cli.main"]
    out = subprocess.run(cmd + ["list"], capture_output=True, text=True, timeout=120, check=True).stdout
    names = {line.split()[0] for line in out.splitlines()[1:] if line.strip()}
    assert BUILTINS <= names


@pytest.mark.parametrize("name", ["ste", "gumbel"])
def test_decay_length_option_is_tau_steps(name):
    import importlib

    cls = {"ste": importlib.import_module("arraysel_plugins.ste").STESelector,
           "gumbel": importlib.import_module("arraysel_plugins.gumbel").GumbelSelector}[name]
    assert "tau_steps" in cls.options and "anneal_steps" not in cls.options
    assert cls(tau_steps=7).options["tau_steps"] == 7
