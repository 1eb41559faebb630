"""Pages of the docs site that are generated, not written (run by mkdocs-gen-files).

``mkdocs build`` runs this script (``mkdocs.yml``, plugin ``gen-files``); it writes into the
site's virtual docs folder, never into the checkout:

* ``index.md``: the README, and ``benchmarks.md``: ``benchmarks/README.md``;
* ``quickstart.ipynb``: ``examples/quickstart.ipynb`` with its committed outputs (rendered by
  mkdocs-jupyter, not executed);
* ``reference/cli.md``: ``arraysel --help`` and ``arraysel <command> --help`` of every command
  of :func:`arraysel.cli.main.build_parser`;
* ``reference/scene-keys.md``: every key of :data:`arraysel.scenes.schema.SCHEMA`, its kind,
  allowed values, default and meaning;
* ``reference/api/*.md``: the mkdocstrings pages of the public API.

Links between Markdown files are written for the repository (so that they work when the files
are read on their own, on a code host or in an editor); a link that leaves ``docs/`` is pointed
at the generated page or at a copy of the file in the site, published at its repository path.
This is how the figures of ``benchmarks/results/`` reach the results pages: a page embeds
``![PSFs](../../benchmarks/results/compare-20s/psfs.png)`` and the build copies that one file
(never copy result figures into ``docs/img/``). A Markdown file copied this way (a result
folder's ``README.md``) has its own links rewritten the same way, and what it links to is
copied in turn. ``python docs/gen_ref.py OUT_DIR`` writes the same pages into OUT_DIR (to read
them without building the site).
"""
from __future__ import annotations

import os
import posixpath
import re
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

#: repository files published as generated pages: repository path -> page in the site
PAGES = {
    "README.md": "index.md",
    "benchmarks/README.md": "benchmarks.md",
}

#: notebooks rendered by mkdocs-jupyter (with their committed outputs): repository path -> page
NOTEBOOKS = {
    "examples/quickstart.ipynb": "quickstart.ipynb",
}

#: the API reference: page -> (title, introduction, objects documented by mkdocstrings)
API_PAGES: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "arraysel": (
        "`arraysel`: the notebook API",
        "`import arraysel as asel` gives these names (imported on first use, so `import arraysel` "
        "itself loads neither torch nor pandas). Each is documented where it lives.",
        ("arraysel", "arraysel.scenes.load.load_scene", "arraysel.objective.psf_objective.build_objective",
         "arraysel.api.compare", "arraysel.run.compare.CompareResult", "arraysel.io.cache.cache_dir"),
    ),
    "scenes": (
        "Scenes",
        "Loading, validating and reading scenes; every key is listed in the "
        "[scene-key table](../scene-keys.md).",
        ("arraysel.scenes.load.load_scene", "arraysel.scenes.scene.Scene",
         "arraysel.scenes.load.builtin_scenes", "arraysel.scenes.keys.Key"),
    ),
    "objective": (
        "Objective",
        "The PSF objective (Table-1 metrics of a batch of selections, and the differentiable "
        "losses) and the contract every objective meets.",
        ("arraysel.objective.psf_objective.Objective", "arraysel.objective.psf_objective.build_objective",
         "arraysel.objective.contract"),
    ),
    "selectors": (
        "Selectors: the plugin contract",
        "What a selector plugin implements and receives (see [Write your own selector]"
        "(../../selectors.md)), the hook specifications, and the conformance suite a plugin "
        "can run in its own tests.",
        ("arraysel.selectors.contract", "arraysel.selectors.budget", "arraysel.selectors.hookspecs",
         "arraysel.testing"),
    ),
    "run": (
        "Running comparisons",
        "`arraysel compare` and `asel.compare` in Python: selectors under one budget, the output "
        "folder, the tables and figures.",
        ("arraysel.api", "arraysel.run.compare"),
    ),
    "report": (
        "Reports: tables and figures",
        "The columns of the result tables, the tables and IOHprofiler export, every figure, and a "
        "selection exported for a scanner (with the probe files it is read back from).",
        ("arraysel.report.columns", "arraysel.report.tables", "arraysel.report.plots", "arraysel.report.export",
         "arraysel.physics.probe_files"),
    ),
}

_LINK = re.compile(r"(\]\()([^)\s]+)(\))")


def _site_path(repo_path: str) -> str | None:
    """Where a repository file lives in the site (None: not published)."""
    if repo_path in PAGES:
        return PAGES[repo_path]
    if repo_path in NOTEBOOKS:
        return NOTEBOOKS[repo_path]
    if repo_path.startswith("docs/"):
        return repo_path[len("docs/"):]
    return None


def rewrite_links(text: str, repo_path: str, copies: set[str]) -> str:
    """Relative links of a Markdown file at ``repo_path``, pointed at the site's pages.

    A link to a file outside ``docs/`` that is not a generated page adds that file to
    ``copies`` (published at its repository path) and points at the copy. A file that is not
    a page of its own is itself published at its repository path.
    """
    page = _site_path(repo_path) or repo_path
    page_dir = posixpath.dirname(page)

    def fix(m: re.Match) -> str:
        target = m.group(2)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith(("#", "/")):
            return m.group(0)
        path, _, anchor = target.partition("#")
        repo_target = posixpath.normpath(posixpath.join(posixpath.dirname(repo_path), path))
        if repo_target.startswith("..") or not (ROOT / repo_target).exists():
            return m.group(0)                  # mkdocs reports it (strict mode fails)
        site = _site_path(repo_target)
        if site is None:
            copies.add(repo_target)
            site = repo_target
        new = posixpath.relpath(site, page_dir or ".")
        return m.group(1) + new + ("#" + anchor if anchor else "") + m.group(3)

    return _LINK.sub(fix, text)


def cli_reference() -> str:
    """``arraysel --help`` and every command's ``--help``, as argparse prints them (100 columns)."""
    import argparse

    os.environ["COLUMNS"] = "100"
    from arraysel.cli.main import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    out = ["# Command-line reference", "",
           "Generated from the `arraysel` command's own parsers (`arraysel --help`, "
           "`arraysel COMMAND --help`). Every command takes `--scene NAME_OR_TOML` and "
           "`--device cpu|cuda`; errors in the arguments are one line and exit code 2.", "",
           "## `arraysel`", "", "```text", parser.format_help().rstrip(), "```", ""]
    for name, command in sub.choices.items():
        out += [f"## `arraysel {name}`", "", "```text", command.format_help().rstrip(), "```", ""]
    return "\n".join(out)


def _fmt(value) -> str:
    import math

    if value is None:
        return ""
    if isinstance(value, float) and math.isinf(value):
        return "∞" if value > 0 else "−∞"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


def _allowed(key) -> str:
    kind, cons = key.kind, key.cons
    if kind == "bool":
        return "true, false"
    if kind == "str":
        return "any" if cons is None else ", ".join(f'"{c}"' for c in cons)
    if kind in ("int", "points", "ints"):
        lo, hi = cons
        text = f"{_fmt(lo)} … {_fmt(hi)}"
        return {"points": f"{text} points", "ints": f"a list of {text}"}.get(kind, text)
    if kind == "beams":
        return f"{_fmt(cons[0])} … {_fmt(cons[1])} points [theta_x, theta_y, range]"
    lo, hi, lo_open = cons
    text = f"{'(' if lo_open else '['}{_fmt(lo)}, {_fmt(hi)}{')' if hi == float('inf') else ']'}"
    if kind == "length":
        text += f" {key.unit}" + (" (whole pixels)" if key.integer else "")
    return text


def scene_key_table() -> str:
    """Every scene key of :data:`arraysel.scenes.schema.SCHEMA`, one table per section."""
    from arraysel.scenes.schema import SCHEMA, TOP_LEVEL

    out = ["# Scene keys", "",
           "Generated from `arraysel.scenes.schema.SCHEMA`, the one place where every scene key, "
           "its allowed values and its default are defined (`arraysel scenes NAME` shows a "
           "scene's values and where each comes from). A scene file sets keys by section "
           "(`[grid]`, `window = 96`); unknown keys and values outside the allowed range are "
           "errors naming `section.key`. How the keys are used: [Scenes](../scenes.md).", "",
           "Top-level keys: " + ", ".join(f"`{k}`" for k in TOP_LEVEL) + " (`base` names the scene "
           "this one starts from).", "",
           "*Length* keys take a number in the key's unit or a string with a unit: "
           "`\"3.5 mm\"`, `\"20 um\"`, `\"1.5 wl\"` (wavelengths c / fc) or `\"128 px\"` (grid "
           "pixels), as the units column allows. An empty default is derived (the key's text says "
           "from what) or, for `selection.k`, required.", ""]
    for section, keys in SCHEMA.items():
        out += [f"## `[{section}]`", "", "| key | kind | allowed | default | units | meaning |",
                "|---|---|---|---|---|---|"]
        for name, key in keys.items():
            units = ", ".join(key.units) if key.units else (key.unit or "")
            meaning = key.help.replace("|", "\\|")
            out.append(f"| `{name}` | {key.kind} | {_allowed(key)} | {_fmt(key.default)} | {units} | {meaning} |")
        out.append("")
    return "\n".join(out)


def api_page(title: str, intro: str, objects: tuple[str, ...]) -> str:
    out = [f"# {title}", "", intro, ""]
    for obj in objects:
        out += [f"::: {obj}", ""]
    return "\n".join(out)


def generated_pages() -> tuple[dict[str, str], dict[str, Path]]:
    """(page -> Markdown text, site path -> repository file to copy)."""
    pages: dict[str, str] = {}
    copies: set[str] = set()
    for repo_path, page in PAGES.items():
        pages[page] = rewrite_links((ROOT / repo_path).read_text(encoding="utf-8"), repo_path, copies)
    # the docs pages' own links that leave docs/
    for md in sorted(DOCS.rglob("*.md")):
        repo_path = md.relative_to(ROOT).as_posix()
        text = md.read_text(encoding="utf-8")
        fixed = rewrite_links(text, repo_path, copies)
        if fixed != text:
            pages[_site_path(repo_path)] = fixed
    pages["reference/cli.md"] = cli_reference()
    pages["reference/scene-keys.md"] = scene_key_table()
    for name, (title, intro, objects) in API_PAGES.items():
        pages[f"reference/api/{name}.md"] = api_page(title, intro, objects)
    files: dict[str, Path] = {}
    pending, seen = sorted(copies), set()
    while pending:                      # copied Markdown files get their links rewritten too
        path = pending.pop()
        if path in seen:
            continue
        seen.add(path)
        if path.endswith(".md"):
            found: set[str] = set()
            pages[path] = rewrite_links((ROOT / path).read_text(encoding="utf-8"), path, found)
            pending += sorted(found - seen)
        else:
            files[path] = ROOT / path
    for repo_path, page in NOTEBOOKS.items():
        files[page] = ROOT / repo_path
    return pages, files


def _write_site() -> None:
    import mkdocs_gen_files

    pages, files = generated_pages()
    for page, text in pages.items():
        with mkdocs_gen_files.open(page, "w") as fh:
            fh.write(text)
    for page, source in files.items():
        with mkdocs_gen_files.open(page, "wb") as fh:
            fh.write(source.read_bytes())


def _write_folder(out: Path) -> None:
    pages, files = generated_pages()
    for page, text in pages.items():
        (out / page).parent.mkdir(parents=True, exist_ok=True)
        (out / page).write_text(text, encoding="utf-8")
    for page, source in files.items():
        (out / page).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, out / page)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python docs/gen_ref.py OUT_DIR")
    _write_folder(Path(sys.argv[1]))
elif "mkdocs_gen_files" in sys.modules:  # run by the gen-files plugin (imported: tests use the functions)
    _write_site()
