"""``arraysel completion bash|zsh|tcsh``: the shell completion script of the ``arraysel`` command.

The script is generated from the command's own parser by ``shtab`` (commands, options, their
choices, file arguments), so it never falls behind the options. Install it once::

    arraysel completion bash > ~/.local/share/bash-completion/completions/arraysel
    arraysel completion zsh > ~/.zfunc/_arraysel     # a folder on $fpath, then compinit
"""
from __future__ import annotations

import sys

#: the shells ``shtab`` writes completion scripts for
SHELLS = ("bash", "zsh", "tcsh")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "completion", help="print the shell completion script (bash, zsh, tcsh)",
        description="Print the completion script of the arraysel command for SHELL, generated from its "
                    "options. bash: arraysel completion bash > ~/.local/share/bash-completion/completions/"
                    "arraysel (or add 'eval \"$(arraysel completion bash)\"' to ~/.bashrc); zsh: arraysel "
                    "completion zsh > DIR/_arraysel for a DIR on $fpath, then restart the shell.")
    p.add_argument("shell", choices=SHELLS, help="the shell")
    p.set_defaults(func=run)


def run(args) -> int:
    import shtab

    from arraysel.cli.main import build_parser

    sys.stdout.write(shtab.complete(build_parser(), shell=args.shell))
    return 0
