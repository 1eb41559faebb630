"""The ``arraysel`` command line: :mod:`arraysel.cli.main` builds the parser; one module per command."""
from arraysel.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
