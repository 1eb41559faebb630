"""The sdist and wheel hold every package, the plugins, the scene files and the data; one version."""
from __future__ import annotations

import configparser
import re
import shutil
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest

import arraysel

ROOT = Path(__file__).resolve().parents[1]


def _tracked(*patterns: str) -> list[str]:
    """Files of the checkout (tracked, or new and not ignored) under ``patterns``, '/'-separated."""
    out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", *patterns], cwd=ROOT,
                         capture_output=True, text=True)
    if out.returncode != 0:
        pytest.skip("not a git checkout: the file list is unknown")
    return sorted(p for p in set(out.stdout.split()) if (ROOT / p).is_file())


@pytest.fixture(scope="module")
def dists(tmp_path_factory) -> dict:
    """The sdist and the wheel built from it (as ``python -m build`` does), from a copy of the checkout's
    files: no build folder or egg-info left in the checkout can add what the configuration leaves out.
    ``"wheel"`` and ``"sdist"``: their file names; each ``.dist-info`` file of the wheel: its text."""
    pytest.importorskip("build")
    tmp = tmp_path_factory.mktemp("dist")
    src, out = tmp / "src", tmp / "out"
    for p in _tracked():
        (src / p).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / p, src / p)
    proc = subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--outdir", str(out), str(src)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    (whl,) = out.glob("arraysel-*.whl")
    (sdist,) = out.glob("arraysel-*.tar.gz")
    with zipfile.ZipFile(whl) as zf:
        names = {"wheel": set(zf.namelist())}
        names.update({n: zf.read(n).decode() for n in zf.namelist() if ".dist-info/" in n and not n.endswith("RECORD")})
    with tarfile.open(sdist) as tf:
        names["sdist"] = {m.name.split("/", 1)[1] for m in tf.getmembers() if m.isfile()}
    return names


@pytest.fixture(scope="module")
def wheel(dists) -> set[str]:
    return dists["wheel"]


def _dist_info(dists, name: str) -> str:
    (member,) = [n for n in dists if re.fullmatch(rf"arraysel-[^/]+\.dist-info/{name}", n)]
    return dists[member]


def test_wheel_holds_every_package_module_scene_and_data_file(wheel):
    names = wheel
    tracked = [p for p in _tracked("arraysel") if "__pycache__" not in p]
    packages = [p for p in tracked if p.endswith("/__init__.py")]
    assert "arraysel/physics/psf/__init__.py" in packages  # the package the hand-written list once left out
    missing = [p for p in tracked if p.endswith((".py", ".toml", ".npz")) and p not in names]
    assert not missing, f"files of the checkout not in the wheel: {missing}"
    scenes = [p for p in tracked if p.startswith("arraysel/scenes/") and p.endswith(".toml")]
    data = [p for p in tracked if p.startswith("arraysel/data/")]
    assert len(scenes) >= 5 and len(data) >= 2
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]


def test_wheel_installs_the_plugins_folder_as_arraysel_plugins_and_its_entry_points_resolve(dists, wheel):
    names = wheel
    plugins = [p for p in _tracked("plugins") if p.endswith(".py")]
    assert plugins
    for p in plugins:
        assert "arraysel_plugins/" + p.split("/", 1)[1] in names
    assert not [n for n in names if n.startswith("plugins/")]
    eps = configparser.ConfigParser()
    eps.read_string(_dist_info(dists, "entry_points.txt"))
    assert eps["console_scripts"]["arraysel"] == "arraysel.cli.main:main"
    assert len(eps["arraysel"]) >= 9
    for module in eps["arraysel"].values():
        assert module.replace(".", "/") + ".py" in names, module


def test_wheel_metadata_version_and_python_floor(dists):
    meta = _dist_info(dists, "METADATA")
    assert re.search(rf"^Version: {re.escape(arraysel.__version__)}$", meta, re.M)
    assert re.search(r"^Requires-Python: >=3\.11$", meta, re.M)
    assert "License-Expression: MIT" in meta


def test_sdist_holds_the_sources_scenes_data_tests_and_changelog(dists):
    names = dists["sdist"]
    wanted = [p for p in _tracked("arraysel", "plugins", "tests") if "__pycache__" not in p]
    wanted += ["pyproject.toml", "setup.py", "README.md", "LICENSE", "CHANGELOG.md", "CITATION.cff"]
    missing = [p for p in wanted if p not in names]
    assert not missing, f"files of the checkout not in the sdist: {missing}"
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]


def test_the_version_has_one_home():
    """pyproject.toml reads the version from arraysel.__version__; CITATION.cff, whose format needs it
    written out, agrees."""
    pyproject = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    assert not re.search(r"^version\s*=", pyproject.split("[tool.setuptools.dynamic]")[0], re.M)
    assert 'version = { attr = "arraysel.__version__" }' in pyproject
    cff = (ROOT / "CITATION.cff").read_text(encoding="utf-8")
    assert re.search(rf"^version: {re.escape(arraysel.__version__)}$", cff, re.M)
    changelog = (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    assert "## [Unreleased]" in changelog and f"## [{arraysel.__version__}]" in changelog


def test_wheel_metadata_is_complete_and_typed(dists, wheel):
    """Authors, keywords, classifiers, a URL, py.typed, and the documented extras (docs/install.md)."""
    meta = _dist_info(dists, "METADATA")
    assert re.search(r"^Author: .+", meta, re.M) and re.search(r"^Keywords: .*ultrasound", meta, re.M)
    assert "Classifier: Intended Audience :: Science/Research" in meta and "Classifier: Typing :: Typed" in meta
    assert re.search(r"^Project-URL: \w+, https://", meta, re.M)
    assert "arraysel/py.typed" in wheel
    extras = set(re.findall(r"^Provides-Extra: (\S+)$", meta, re.M))
    assert extras >= {"dask", "nevergrad", "netcdf", "docs", "test", "all"}
    core = [line for line in re.findall(r"^Requires-Dist: (.+)$", meta, re.M) if "extra ==" not in line]
    assert not [d for d in core if d.split(">")[0].split("<")[0].split("[")[0] in ("nevergrad", "dask", "xarray")]
    install = (ROOT / "docs" / "install.md").read_text(encoding="utf-8")
    for extra in extras:
        assert f"`{extra}`" in install, extra
