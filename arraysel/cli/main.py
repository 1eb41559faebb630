"""Command-line entry point: ``arraysel <command> ...``.

Each command lives in its own module under :mod:`arraysel.cli` and
provides ``add_parser(subparsers)`` (which sets ``func`` on its parser) .
"""
from __future__ import annotations

import argparse
import importlib
import sys

from arraysel.errors import ArrayselError

#: command modules, in the order they are listed by ``arraysel --help``
COMMAND_MODULES = ("psf", "evaluate", "compare", "report", "list", "scenes", "cache", "train")


def build_parser() -> argparse.ArgumentParser:
    from arraysel import __version__

    parser = argparse.ArgumentParser(
        prog="arraysel",
        description="Design sparse ultrasound probes: choose which k of Ne elements stay active.",
    )
    parser.add_argument("--version", action="version", version=f"arraysel {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(f"arraysel.cli.{name}").add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from arraysel.io.allocator import tune_malloc

    tune_malloc()
    try:
        return int(args.func(args) or 0)
    except ArrayselError as exc:
        print(f"arraysel {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"arraysel {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
