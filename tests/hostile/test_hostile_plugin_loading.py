"""Hostile cases, plugin loading: a plugin that raises or calls ``sys.exit`` while it is loaded.

Contract (arraysel.selectors.registry): given with ``--plugin`` (a file or a module name), it is
an error naming the plugin, one line, exit code 2, before any run; installed (an entry point),
it is skipped with one warning line naming it, and the command goes on with the others.
"""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from arraysel.selectors import registry
from arraysel.selectors.registry import PluginLoadError, build_plugin_manager, get_registry, load_plugin

GOOD = textwrap.dedent("""
    from arraysel.selectors.hookspecs import hookimpl
    from arraysel.selectors.contract import Selector

    class Fine(Selector):
        name = "fine-{tag}"
        description = "picks the first k elements"
        deterministic = True

        def select(self, objective, k, budget, rng):
            return list(range(k))

    @hookimpl
    def arraysel_register_selectors(register):
        register(Fine)
""")

BAD = {
    "exit0-at-import": "import sys\nsys.exit(0)\n",
    "exit3-at-import": "import sys\nsys.exit(3)\n",
    "raise-at-import": "raise ValueError('no config file\\nsecond line')\n",
    "import-error": "import no_such_dependency_xyz\n",
    "exit-in-hook": textwrap.dedent("""
        import sys
        from arraysel.selectors.hookspecs import hookimpl

        @hookimpl
        def arraysel_register_selectors(register):
            sys.exit(0)
    """),
    "raise-in-hook": textwrap.dedent("""
        from arraysel.selectors.hookspecs import hookimpl

        @hookimpl
        def arraysel_register_selectors(register):
            raise RuntimeError("boom")
    """),
}
SAID = {"exit0-at-import": "sys.exit(0)", "exit3-at-import": "sys.exit(3)", "raise-at-import": "ValueError",
        "import-error": "no_such_dependency_xyz", "exit-in-hook": "sys.exit(0)", "raise-in-hook": "RuntimeError"}


@pytest.fixture
def isolated_pm(monkeypatch):
    monkeypatch.delenv(registry.DISABLE_ENV, raising=False)
    pm = build_plugin_manager(load_entrypoints=False)
    registry.reset()
    registry._PM = pm
    try:
        yield pm
    finally:
        registry.reset()


@pytest.mark.parametrize("case", sorted(BAD))
def test_compare_with_a_plugin_file_that_fails_to_load_is_refused(tmp_path, capsys, isolated_pm, case):
    from arraysel.cli.main import main

    plugin = tmp_path / f"{case}.py"
    plugin.write_text(BAD[case])
    out = tmp_path / "out"
    code = main(["compare", "--selectors", "uniform", "--scene", "toy", "--budget-evals", "5", "--out", str(out),
                 "--plugin", str(plugin), "--no-progress", "--no-figures"])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("arraysel compare: error:"), err
    assert plugin.name in lines[0] and SAID[case] in lines[0], lines[0]
    assert not out.exists()                                   # no run, no half-written folder
    assert main(["list", "--plugin", str(plugin)]) == 2        # the same from `arraysel list`
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_a_module_plugin_that_exits_at_import_is_refused(tmp_path, monkeypatch, isolated_pm):
    (tmp_path / "exits_plugin_xyz.py").write_text(BAD["exit0-at-import"])
    (tmp_path / "deps_plugin_xyz.py").write_text(BAD["import-error"])
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(PluginLoadError, match=r"'exits_plugin_xyz' failed: it called sys.exit\(0\)"):
        load_plugin("exits_plugin_xyz")
    with pytest.raises(PluginLoadError, match="'deps_plugin_xyz' failed: it raised ModuleNotFoundError"):
        load_plugin("deps_plugin_xyz")
    with pytest.raises(PluginLoadError, match="cannot import plugin module 'nope_plugin_xyz'"):
        load_plugin("nope_plugin_xyz")
    assert "exits_plugin_xyz" not in sys.modules
    assert set(get_registry().names()) >= {"uniform", "random"}     # nothing half-registered


def test_a_hook_that_fails_half_way_registers_nothing(tmp_path, isolated_pm):
    plugin = tmp_path / "half.py"
    plugin.write_text(GOOD.format(tag="half").replace("register(Fine)", "register(Fine)\n    raise KeyError('x')"))
    load_plugin(str(plugin))
    with pytest.raises(PluginLoadError, match="arraysel_register_selectors failed, it raised KeyError"):
        get_registry()


def _fake_distribution(site: Path, name: str, modules: dict[str, str]) -> None:
    """An installed distribution ``name`` (a .dist-info folder) whose modules are entry points."""
    for mod, code in modules.items():
        (site / f"{mod}.py").write_text(code)
    info = site / f"{name}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[arraysel]\n" + "".join(f"{m} = {m}\n" for m in modules))


def test_an_installed_plugin_that_fails_to_load_is_skipped_with_one_warning(tmp_path, monkeypatch, capsys,
                                                                            caplog):
    import logging

    from arraysel.cli.main import main

    site = tmp_path / "site"
    site.mkdir()
    _fake_distribution(site, "broken-plugins", {
        "ep_exits_xyz": BAD["exit0-at-import"], "ep_raises_xyz": BAD["raise-at-import"],
        "ep_hook_exits_xyz": BAD["exit-in-hook"], "ep_good_xyz": GOOD.format(tag="installed")})
    monkeypatch.syspath_prepend(str(site))   # importlib.metadata finds the distribution there
    monkeypatch.delenv(registry.DISABLE_ENV, raising=False)
    registry.reset()
    try:
        with caplog.at_level(logging.WARNING, logger="arraysel.selectors.registry"):
            code = main(["list"])
        listed = capsys.readouterr().out
    finally:
        registry.reset()
    assert code == 0
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 3 and all("skipping the installed plugin" in w and "\n" not in w for w in warnings), \
        warnings
    for ep, said in (("ep_exits_xyz", "sys.exit(0)"), ("ep_raises_xyz", "ValueError"),
                     ("ep_hook_exits_xyz", "sys.exit(0)")):
        assert [w for w in warnings if ep in w and said in w], (ep, warnings)
    assert all("broken-plugins" in w for w in warnings)
    assert "fine-installed" in listed and "uniform" in listed            # the others still load
    caplog.clear()
    monkeypatch.setenv(registry.DISABLE_ENV, "ep_exits_xyz,ep_raises_xyz,ep_hook_exits_xyz")
    try:
        with caplog.at_level(logging.WARNING, logger="arraysel.selectors.registry"):
            assert main(["list"]) == 0
    finally:
        registry.reset()
    assert not caplog.records and "fine-installed" in capsys.readouterr().out
