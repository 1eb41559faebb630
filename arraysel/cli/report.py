"""``arraysel report``: a finished comparison's table as Markdown or LaTeX."""
from __future__ import annotations

import sys


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "report", help="a finished comparison's table as Markdown or LaTeX",
        description="Read the folder written by `arraysel compare` (run.json, runs.csv) and print, or write to "
                    "--out, one table: the Table-1 metrics of each selector's listed selection (the best of "
                    "its seeds by Mean) and the statistics of its Means over seeds (median [IQR], bootstrap "
                    "95 %% confidence interval of the median, Mann-Whitney p-value against random). The tables "
                    "are built from runs.csv.")
    p.add_argument("folder", metavar="DIR", help="the --out folder of a finished `arraysel compare`")
    p.add_argument("--format", choices=("md", "latex"), default="md",
                   help="md (GitHub Markdown, default) or latex (a table with a booktabs tabular)")
    p.add_argument("--out", default=None, metavar="FILE", help="write the table to FILE instead of printing it")
    p.add_argument("--rebuild", action="store_true",
                   help="also rewrite DIR/table1.csv and DIR/stats.csv from DIR/runs.csv (e.g. a folder written "
                        "by an older version)")
    p.set_defaults(func=run)


def run(args) -> int:
    from arraysel.report.summary import report

    text, written = report(args.folder, args.format, args.out, rebuild=args.rebuild)
    if args.out is None:
        sys.stdout.write(text)
    for path in written:
        print(f"wrote {path}", file=sys.stderr)
    return 0
