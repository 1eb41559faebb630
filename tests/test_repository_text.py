"""Committed text speaks of the product, not of the machines it was developed on.

Every text file that git tracks (``git ls-files``; binary files, i.e. files with a NUL byte or
that are not UTF-8, are skipped) is searched for absolute paths of a development machine: a
home, root or scratch folder, a virtual environment's ``bin`` folder, an installed package's
``site-packages``. A path in a committed file works on one machine only; a user's command takes
the path as an argument or relative to the checkout instead.

The user documentation (Markdown files and the benchmark results) is also searched for the
words of a work diary: numbered work "stops" and "sessions", and other people's runs. What
changed and when belongs in the git log (and a changelog), not on the pages a user reads.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

#: an absolute path of a development machine. The lookbehind keeps URLs and relative paths
#: (``https://host/work/...``, ``docs/work/``) out: the path must start a word.
_START = r"(?<![\w.~$-])"
MACHINE_PATHS: tuple[tuple[str, re.Pattern[str]], ...] = (
    ("a folder under /work", re.compile(_START + r"/work/")),
    ("a file under /tmp", re.compile(_START + r"/tmp/[\w.-]")),
    ("root's home folder", re.compile(_START + r"/root/")),
    ("a home folder", re.compile(_START + r"/home/[\w.-]")),
    ("a macOS home folder", re.compile(_START + r"/Users/[\w.-]")),
    ("a folder under /opt", re.compile(_START + r"/opt/[\w.-]")),
    ("a virtual environment's programs", re.compile(r"venv/bin/")),
    ("an installed package's folder", re.compile(r"site-packages")),
)

#: legitimate mentions, removed from a line before it is searched. Each entry is small and says
#: why it is allowed. (``/dev/null``, ``/proc/self/...``, ``/usr/bin/time`` and ``/etc/...``
#: name the same thing on every Linux machine and are not matched by the patterns above.)
ALLOWED: tuple[re.Pattern[str], ...] = (
    # the set-up command activates the venv it creates in the checkout (relative path)
    re.compile(r"(?:^|[\s;&(])(?:\.|source) \.venv/bin/activate\b"),
    # CI's wheel check: a venv it makes in a fresh temporary folder ($work), and the check that the
    # package imported is the installed one (in site-packages), not the checkout
    re.compile(r'"\$work/venv/bin/'),
    re.compile(r'"site-packages" in where\.parts'),
    re.compile(r"in site-packages\b"),
)

#: files that may name the patterns themselves
ALLOWED_FILES = {
    "tests/test_repository_text.py",   # this test: it spells out what it searches for
}

#: work-diary wording in the user documentation
_ORDINAL = r"(?:first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|\d+(?:st|nd|rd|th))"
DIARY: tuple[tuple[str, re.Pattern[str]], ...] = (
    ("a numbered work stop", re.compile(rf"\b{_ORDINAL} stop\b|\bstop \d+\b|\b(?:this|that|each|previous|last) stop\b",
                                        re.IGNORECASE)),
    ("a work session", re.compile(r"\bsessions?\b", re.IGNORECASE)),
    ("other people's runs", re.compile(r"\bother engineers?\b", re.IGNORECASE)),
)

#: the ordinary uses of those words, removed from a line before it is searched
DIARY_ALLOWED: tuple[re.Pattern[str], ...] = (
    # a program's session, not a work session
    re.compile(r"\b(?:Jupyter|IPython|interactive|notebook|Python|dask|SSH|tmux|screen|HTTP|login)"
               r"(?:'s)? sessions?\b", re.IGNORECASE),
)

#: the history's own place (written as history on purpose)
DIARY_EXEMPT = {"CHANGELOG.md"}


def machine_path_findings(line: str) -> list[str]:
    """Names of the machine paths a line of text contains (after the allowed mentions are cut)."""
    for allowed in ALLOWED:
        line = allowed.sub(" ", line)
    return [name for name, pattern in MACHINE_PATHS if pattern.search(line)]


def diary_findings(line: str) -> list[str]:
    """Names of the diary wordings a line of documentation contains."""
    for allowed in DIARY_ALLOWED:
        line = allowed.sub(" ", line)
    return [name for name, pattern in DIARY if pattern.search(line)]


def is_user_doc(path: str) -> bool:
    """Whether a tracked file is user documentation searched for diary wording."""
    if path in DIARY_EXEMPT:
        return False
    return (path.endswith(".md") or path.startswith("docs/")
            or path.startswith("benchmarks/results/")) and not path.endswith(".py")


def _tracked_text_files() -> dict[str, str]:
    git = shutil.which("git")
    if git is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: the committed files are unknown")
    names = subprocess.run([git, "ls-files", "-z"], cwd=ROOT, check=True,
                           capture_output=True).stdout.decode("utf-8").split("\0")
    texts = {}
    for name in filter(None, names):
        path = ROOT / name
        if not path.is_file():          # deleted in the working tree, or a submodule
            continue
        data = path.read_bytes()
        if b"\0" in data:
            continue
        try:
            texts[name] = data.decode("utf-8")
        except UnicodeDecodeError:
            continue
    return texts


def _report(findings: list[str]) -> str:
    return "\n".join(findings[:50]) + (f"\n... and {len(findings) - 50} more" if len(findings) > 50 else "")


# -- the scanners find what they should, and only that -----------------------------------------

@pytest.mark.parametrize("line", [
    "python /work/venv/bin/python benchmarks/bench_psf.py",
    'cd /tmp && tar xzf /tmp/mnist.tgz',
    "touch /tmp/arraysel-core1.reserved",
    '"command_line": ["/work/wt-search/.venv/bin/arraysel", "compare"]',
    "cache in /root/.cache/arraysel",
    "see /home/alice/arraysel",
    "/opt/pypi/simple/torch/",
    "lib/python3.11/site-packages/arraysel",
    "    .venv/bin/arraysel compare --selectors ste",
    "x=/Users/bob/code",
])
def test_machine_paths_are_found(line):
    assert machine_path_findings(line)


@pytest.mark.parametrize("line", [
    'python -m venv .venv && . .venv/bin/activate && pip install -e ".[test]"',
    "source .venv/bin/activate",
    "/usr/bin/time -v arraysel evaluate --masks masks.txt --out m.csv > /dev/null",
    "VmHWM in /proc/self/status",
    "https://example.org/work/home/tmp/x and docs/work/ and ~/.cache/arraysel",
    "python scripts/make_samples.py --mnist DIR/mnist/package",
    "--cache $TMPDIR/asel",
])
def test_legitimate_mentions_pass(line):
    assert machine_path_findings(line) == []


@pytest.mark.parametrize("line", [
    "Ninth stop of 2026-11-25: three changes",
    "on the fourth stop's code",
    "measured earlier in the session",
    "(same session)",
    "the 5th stop",
    "shared with other engineers' runs",
    "after stop 3",
])
def test_diary_wording_is_found(line):
    assert diary_findings(line)


@pytest.mark.parametrize("line", [
    "greedy stops by itself when no removal improves",
    "a run that overruns its budget stops the comparison",
    "Ctrl-C stops the run; `--resume` finishes it",
    "the stop criterion of the swap search",
    "run it in a Jupyter session or an interactive session",
])
def test_ordinary_words_pass(line):
    assert diary_findings(line) == []


# -- the committed files --------------------------------------------------------------------------

def test_no_committed_text_names_a_development_machine_path():
    findings = []
    for name, text in sorted(_tracked_text_files().items()):
        if name in ALLOWED_FILES:
            continue
        for number, line in enumerate(text.splitlines(), 1):
            for what in machine_path_findings(line):
                findings.append(f"{name}:{number}: {what}: {line.strip()[:120]}")
    assert not findings, ("committed text names a path of a development machine (take it as an "
                          "argument, or make it relative to the checkout):\n" + _report(findings))


def test_user_docs_read_as_docs_not_as_a_work_diary():
    findings = []
    for name, text in sorted(_tracked_text_files().items()):
        if not is_user_doc(name):
            continue
        for number, line in enumerate(text.splitlines(), 1):
            for what in diary_findings(line):
                findings.append(f"{name}:{number}: {what}: {line.strip()[:120]}")
    assert not findings, ("the user documentation reads as a work diary (the history belongs in "
                          "the git log):\n" + _report(findings))


# -- the docs site's generated pages (docs/gen_ref.py; `mkdocs build --strict` builds the site) --

def _gen_ref():
    import importlib.util

    spec = importlib.util.spec_from_file_location("gen_ref", ROOT / "docs" / "gen_ref.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_scene_key_table_lists_every_key_of_the_schema():
    from arraysel.scenes.schema import SCHEMA

    table = _gen_ref().scene_key_table()
    for section, keys in SCHEMA.items():
        assert f"## `[{section}]`" in table
        for name, key in keys.items():
            row = next((line for line in table.splitlines() if line.startswith(f"| `{name}` |")), None)
            assert row is not None, f"{section}.{name} missing"
    assert "| `k` | int | 1 … 4096 |  |" in table                     # required, no default
    assert "| `window` | length | [4, 8192] px (whole pixels) | 128 |" in table
    assert '| `aggregate` | str | "mean", "worst" | "mean" |' in table
    assert "| `height` | float | (0, ∞) |" in table


def test_cli_reference_shows_every_command_help():
    import argparse

    from arraysel.cli.main import build_parser

    text = _gen_ref().cli_reference()
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert sub.choices
    for name in sub.choices:
        assert f"## `arraysel {name}`" in text
        assert f"usage: arraysel {name}" in text


def test_links_that_leave_docs_point_at_pages_of_the_site():
    gen = _gen_ref()
    copies: set[str] = set()
    text = ("[b](../benchmarks/README.md) ![p](../benchmarks/results/work_precision.png) "
            "[s](scenes.md#units) [w](https://example.org/x.md) [a](#here)")
    out = gen.rewrite_links(text, "docs/performance.md", copies)
    assert out == ("[b](benchmarks.md) ![p](benchmarks/results/work_precision.png) "
                   "[s](scenes.md#units) [w](https://example.org/x.md) [a](#here)")
    assert copies == {"benchmarks/results/work_precision.png"}
    assert gen.rewrite_links("[s](docs/scenes.md)", "README.md", copies) == "[s](scenes.md)"
    assert gen.rewrite_links("[p](../docs/performance.md)", "benchmarks/README.md", copies) == "[p](performance.md)"


def test_relative_links_of_the_markdown_files_resolve():
    """Every relative link of a Markdown file names a file of the checkout, or (from docs/) a page
    that docs/gen_ref.py generates at build time (the command-line, scene-key and API references)."""
    link = re.compile(r"\]\(([^)\s]+)\)")
    gen = _gen_ref()
    generated = {"reference/cli.md", "reference/scene-keys.md"} | {f"reference/api/{n}.md" for n in gen.API_PAGES}
    broken = []
    for name, text in sorted(_tracked_text_files().items()):
        if not name.endswith(".md"):
            continue
        for target in link.findall(text):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
                continue
            path = (ROOT / name).parent / target.partition("#")[0]
            if path.exists():
                continue
            site = os.path.relpath(path.resolve(), DOCS) if name.startswith("docs/") else ""
            if site.replace(os.sep, "/") not in generated:
                broken.append(f"{name}: {target}")
    assert not broken, "links to files that do not exist:\n" + "\n".join(broken)
