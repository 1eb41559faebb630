"""A griffe extension for the docs site: arraysel's docstrings, read as the numpy style they follow.

The package's docstrings are written for ``help()`` and the source: reStructuredText roles
(``:class:`~arraysel.scenes.schema.Scene```), double-backtick literals, and numpy-style
``Parameters`` lists whose entries are ``name : meaning`` (no types), sometimes followed by a
paragraph of prose. Before griffe parses a docstring, this extension

* turns a role into a code span (``:class:`~a.b.C``` -> `` `C` ``, without ``~`` the whole path),
  and a double-backtick literal into a single-backtick one;
* in ``Parameters``, ``Other Parameters`` and ``Attributes``, moves the meaning of a
  ``name : meaning`` entry under the name (so it is shown as the description, not as a type),
  unless it reads as a type (``int``, ``Tensor``, ... followed by an indented description), and gives each
  name of an ``a, b : meaning`` entry its own entry;
* puts prose that follows such a list (an unindented paragraph that is not an entry) under a
  ``Notes`` heading, so that it is shown rather than dropped.

Only the text griffe parses changes; the source is untouched. mkdocs.yml loads this file
(mkdocstrings, ``extensions``).
"""
from __future__ import annotations

import re

import griffe

_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|data|attr|exc|obj|const|term):`(~?)([^`]+)`")
_LITERAL = re.compile(r"``([^`]+?)``")
_ENTRY = re.compile(r"^(\*{0,2}[A-Za-z_][\w]*(?:\s*,\s*\*{0,2}[A-Za-z_][\w]*)*)\s+:\s+(.*)$")
_LIST_SECTIONS = {"parameters", "other parameters", "attributes", "keyword arguments"}


def _role(m: re.Match) -> str:
    target = m.group(2).strip()
    if m.group(1):
        target = target.split(".")[-1]
    return f"`{target}`"


def _is_header(lines: list[str], i: int) -> bool:
    return (i + 1 < len(lines) and lines[i].strip() != "" and not lines[i].startswith(" ")
            and re.fullmatch(r"-{3,}", lines[i + 1].strip() or "x") is not None)


_TYPE = re.compile(r"^(?:int|float|str|bool|list|dict|tuple|Sequence|Tensor|ndarray|array|Path|callable|None"
                   r"|torch\.\w+|np\.\w+)\b")


def _reads_as_type(text: str, next_line: str | None) -> bool:
    """``name : int`` with the description on the next, indented line: a real numpy entry."""
    return next_line is not None and next_line.startswith(" ") and _TYPE.match(text) is not None


def rewrite(doc: str) -> str:
    """The docstring text as the numpy parser should see it (see the module's docstring)."""
    doc = _ROLE.sub(_role, doc)
    doc = _LITERAL.sub(r"`\1`", doc)
    lines = doc.split("\n")
    out: list[str] = []
    i, in_list, after_blank = 0, False, False
    while i < len(lines):
        line = lines[i]
        if _is_header(lines, i):
            in_list = line.strip().lower() in _LIST_SECTIONS
            after_blank = False
            out += [line, lines[i + 1]]
            i += 2
            continue
        if in_list:
            if line.strip() == "":
                after_blank = True
                out.append(line)
                i += 1
                continue
            if not line.startswith(" "):
                m = _ENTRY.match(line)
                nxt = lines[i + 1] if i + 1 < len(lines) else None
                if m and not _reads_as_type(m.group(2), nxt):
                    # `a, b : meaning` -> one entry each (griffe would give b the default of a)
                    names = [n.strip() for n in m.group(1).split(",")]
                    j = i + 1
                    while j < len(lines) and lines[j].startswith(" "):
                        j += 1
                    for name in names:
                        out += [name, "    " + m.group(2), *lines[i + 1:j]]
                    after_blank = False
                    i = j
                    continue
                if not m and after_blank and not re.fullmatch(r"\*{0,2}[A-Za-z_]\w*", line.strip()):
                    out += ["Notes", "-----"]
                    in_list = False
            after_blank = False
        out.append(line)
        i += 1
    return "\n".join(out)


class ArrayselDocstrings(griffe.Extension):
    """Rewrite each docstring (see the module's docstring) before it is parsed."""

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = rewrite(obj.docstring.value)
