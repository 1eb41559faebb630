"""Command-line entry point: ``arraysel <command> ...``.

Each command lives in its own module under :mod:`arraysel.cli` and
provides ``add_parser(subparsers)`` (which sets ``func`` on its parser); a module imports
torch, pandas or matplotlib only inside its ``func``, so that ``arraysel --help``,
``scenes`` and ``cache`` start without them.

The global ``-v`` / ``-q`` set the level of the ``arraysel`` logger (warnings by default;
``-v`` information such as the basis build's steps, ``-vv`` debug; ``-q`` errors only), whose
records go to stderr. An error of the command is one line on stderr and exit code 2; the exit
codes are listed in ``arraysel --help`` (:data:`EXIT_CODES`).
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys
import textwrap

from arraysel.errors import ArrayselError

#: command modules, in the order they are listed by ``arraysel --help``
COMMAND_MODULES = ("psf", "evaluate", "compare", "report", "export", "apodize", "list", "scenes", "cache", "train", "completion")

#: the exit codes of every command, as ``arraysel --help`` lists them
EXIT_CODES = (
    (0, "success"),
    (1, "compare finished, but some runs failed (their error column in runs.csv)"),
    (2, "an error: bad input, a missing file or package, a selector that cannot run (one line on stderr); "
        "also a command line argparse refuses"),
    (130, "interrupted (Ctrl-C); compare keeps its finished runs for --resume"),
    (143, "terminated (SIGTERM, compare); as 130"),
)


def build_parser() -> argparse.ArgumentParser:
    from arraysel import __version__

    parser = argparse.ArgumentParser(
        prog="arraysel",
        description="Design sparse ultrasound probes: choose which k of Ne elements stay active.",
        epilog="exit codes:\n" + "\n".join(textwrap.fill(text, 79, initial_indent=f"  {code:<4d} ",
                                                            subsequent_indent=" " * 7) for code, text in EXIT_CODES)
               + "\n\nshell completion: arraysel completion bash|zsh|tcsh (see arraysel completion --help)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"arraysel {__version__}")
    level = parser.add_mutually_exclusive_group()
    level.add_argument("-v", "--verbose", dest="log_verbose", action="count", default=0,
                       help="log more: -v information (e.g. the basis build's steps), -vv debug")
    level.add_argument("-q", "--quiet", dest="log_quiet", action="count", default=0,
                       help="log errors only (no notices such as the basis build's, no warnings)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(f"arraysel.cli.{name}").add_parser(sub)
    return parser


class _Handler(logging.StreamHandler):
    """The command's log handler: writes to the ``sys.stderr`` of the moment of each record."""

    def __init__(self):
        super().__init__()
        self.setFormatter(logging.Formatter("%(message)s"))

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):  # StreamHandler sets it; the handler always uses the current stderr
        pass


def configure_logging(verbose: int = 0, quiet: int = 0) -> int:
    """Set the ``arraysel`` logger's level from the count of ``-v`` and ``-q`` (warnings by
    default) and give it one stderr handler; returns the level."""
    level = min(logging.CRITICAL, max(logging.DEBUG, logging.WARNING - 10 * verbose + 10 * quiet))
    log = logging.getLogger("arraysel")
    for h in [h for h in log.handlers if isinstance(h, _Handler)]:
        log.removeHandler(h)
    log.addHandler(_Handler())
    log.setLevel(level)
    return level


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.log_verbose, args.log_quiet)
    from arraysel.io.allocator import tune_malloc

    tune_malloc()
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # here, so that a closed pipe is met inside the try
        return code
    except BrokenPipeError:
        return _pipe_closed()
    except ArrayselError as exc:
        print(f"arraysel {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"arraysel {args.command}: interrupted", file=sys.stderr)
        return 130


def _pipe_closed() -> int:
    """The reader of stdout went away (``arraysel list -v | head -1``): stop quietly, as a command
    killed by SIGPIPE would (exit code 141), with stdout pointed at the null device so that the
    interpreter's last flush at exit does not fail again."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # a stdout without a file descriptor
        pass
    return 141


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
