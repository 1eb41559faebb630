"""The docs site is built around figures: every built-in scene has a results page that embeds the
committed figures of its comparisons, and result folders live in ``benchmarks/results/``, not
among the pages of ``docs/``.

The figures are linked by their repository path (``../../benchmarks/results/<folder>/psfs.png``)
and copied into the site by ``docs/gen_ref.py`` at build time; ``mkdocs build --strict`` (CI)
fails on a link that does not resolve. These checks read the Markdown only, so they take
milliseconds.
"""
from __future__ import annotations

import posixpath
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
RESULTS = DOCS / "results"

#: an embedded image: ![alt](target) (a link without the ``!`` is not an image)
_IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+)\)")

#: the figures each results page must embed, by the start of their file names (``psfs`` also
#: matches ``psfs_p0.png``, the PSFs of one field point of a several-point scene)
FIGURES_1D = ("psfs", "masks", "anytime")                      # PSFs at 40 dB, masks, anytime curves
FIGURES_3D = ("planes", "profiles", "masks", "anytime")
PAGES = {
    "paper": FIGURES_1D,
    "l11-5v": FIGURES_1D,
    "c5-2v": FIGURES_1D,
    "p4-2v-depths": FIGURES_1D,
    "matrix-1024": FIGURES_3D,
}
#: built-in scenes without a results page of their own (and where they are shown instead)
NO_PAGE = {"paper-e2e": "training.md", "matrix-1024-mux": "constraints.md",
           "matrix-1024-sector": "sector.md"}


def embedded_images(page: Path) -> list[Path]:
    """The repository files a Markdown page embeds as images (relative targets only)."""
    text = page.read_text(encoding="utf-8")
    out = []
    for target in _IMAGE.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):
            continue
        rel = posixpath.normpath(posixpath.join(page.parent.relative_to(ROOT).as_posix(), target.partition("#")[0]))
        out.append(ROOT / rel)
    return out


def test_image_pattern_counts_images_only():
    text = "![a](x.png) [b](y.md) ![c](../z/p.png){ width=80% } ![d](https://e.org/w.png)"
    assert _IMAGE.findall(text) == ["x.png", "../z/p.png", "https://e.org/w.png"]


@pytest.mark.parametrize("scene", sorted(PAGES))
def test_results_page_embeds_its_figures(scene):
    page = RESULTS / f"{scene}.md"
    assert page.is_file(), f"no results page for the built-in scene {scene!r}: {page.relative_to(ROOT)}"
    images = embedded_images(page)
    missing = [p.relative_to(ROOT).as_posix() for p in images if not p.is_file()]
    assert not missing, f"{page.name} embeds images that do not exist: {missing}"
    names = [p.name for p in images]
    for figure in PAGES[scene]:
        assert any(n.startswith(figure) and n.endswith(".png") for n in names), \
            f"{page.name} embeds no {figure} figure (it embeds {sorted(set(names))})"
    assert len(images) >= len(PAGES[scene])


def test_every_builtin_scene_has_a_results_page_in_the_navigation():
    from arraysel.scenes.schema import builtin_scenes

    nav = (ROOT / "mkdocs.yml").read_text(encoding="utf-8").split("\nnav:", 1)[1]
    for scene in builtin_scenes():
        if scene in NO_PAGE:
            assert NO_PAGE[scene] in nav
            continue
        assert scene in PAGES, f"built-in scene {scene!r} has no results page (tests/test_docs_site.py PAGES)"
        assert f"results/{scene}.md" in nav, f"results/{scene}.md is not in the mkdocs.yml nav"


def test_home_page_shows_a_figure():
    images = embedded_images(ROOT / "README.md")
    assert images and all(p.is_file() for p in images)


def test_result_folders_live_in_benchmarks_not_in_docs():
    """docs/ holds pages and their own images; comparison outputs (a run.json, tables, traces) and
    the experiments' folders belong under benchmarks/results/ with the command that makes them."""
    stray = sorted(p.relative_to(ROOT).as_posix() for p in DOCS.rglob("*")
                   if p.name in {"run.json", "runs.csv", "trace.csv", "table1.csv"} or p.name.startswith("compare-"))
    assert not stray, f"result files under docs/: {stray}"
    nav = (ROOT / "mkdocs.yml").read_text(encoding="utf-8").split("\nnav:", 1)[1]
    assert "compare-" not in nav, "a result folder is in the site's navigation"


def test_every_result_folder_says_how_to_make_it_again():
    for folder in sorted((ROOT / "benchmarks" / "results").glob("compare-*")):
        readme = folder / "README.md"
        assert readme.is_file(), f"{folder.name} has no README.md"
        text = readme.read_text(encoding="utf-8")
        assert "arraysel compare" in text, f"{folder.name}/README.md gives no command"
        assert f"benchmarks/results/{folder.name}" in text, f"{folder.name}/README.md: the command's --out is elsewhere"
