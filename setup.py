"""The package list, found rather than written out: ``arraysel`` and every folder under it (the
data folder ``arraysel/data`` included) and the top-level ``plugins/`` folder, installed as
``arraysel_plugins`` (its folder is mapped in ``pyproject.toml``, which holds every other setting)."""
from setuptools import find_namespace_packages, setup

setup(packages=[*find_namespace_packages(include=["arraysel", "arraysel.*"], exclude=["*.__pycache__"]),
                "arraysel_plugins"])
