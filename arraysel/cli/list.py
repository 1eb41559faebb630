"""``arraysel list``: every registered selector with its origin and description."""
from __future__ import annotations

import json


def _flags(cls) -> str:
    flags = []
    if cls.uses_gradients:
        flags.append("gradients")
    if cls.deterministic:
        flags.append("deterministic")
    if not cls.needs_evaluations:
        flags.append("no-evaluations")
    if cls.missing():
        flags.append("NOT-INSTALLED")
    return ",".join(flags) or "-"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "list", help="list the available selectors (built-in and plugins)",
        description="List every registered selector with the plugin it comes from (origin), its "
                    "capability flags (gradients, deterministic: one run whatever the seed, "
                    "no-evaluations, NOT-INSTALLED: a package it needs is missing) and a one-line "
                    "description; a selector that is not installed is followed by the pip command "
                    "that installs it.")
    p.add_argument("--plugin", action="append", default=[], metavar="MODULE_OR_PATH",
                   help="load a plugin module or .py file first (repeatable)")
    p.add_argument("-v", "--verbose", action="store_true", help="also show each selector's options")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=run)


def run(args) -> int:
    # imported here, not at the top: building the parser (``arraysel --help``) loads no torch
    from arraysel.selectors.registry import get_registry, load_plugin

    for spec in args.plugin:
        load_plugin(spec)
    reg = get_registry()
    if args.json:
        data = [{"name": n, "origin": reg.origin(n), "description": c.description,
                 "uses_gradients": c.uses_gradients, "deterministic": c.deterministic,
                 "requires": list(c.requires), "missing": c.missing(),
                 "install": c.install_hint() if c.missing() else None,
                 "options": {k: {"type": o.type.__name__, "default": o.default, "help": o.help,
                                 "choices": list(o.choices) if o.choices else None}
                             for k, o in c.options.items()}}
                for n, c in reg.items()]
        print(json.dumps(data, indent=2, default=str))
        return 0
    rows = [(n, reg.origin(n), _flags(c), c.description) for n, c in reg.items()]
    head = ("name", "origin", "flags", "description")
    widths = [max(len(r[i]) for r in rows + [head]) for i in range(3)]
    print("  ".join(h.ljust(w) for h, w in zip(head[:3], widths)) + "  " + head[3])
    for (n, c), r in zip(reg.items(), rows):
        print("  ".join(x.ljust(w) for x, w in zip(r[:3], widths)) + "  " + r[3])
        if c.missing():
            print(f"      needs {', '.join(c.missing())}: {c.install_hint()}")
        if args.verbose:
            for key, opt in c.options.items():
                print(f"      -o {n}.{key}=...  ({opt.describe()})")
    return 0
