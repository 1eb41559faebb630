"""``arraysel report``: a finished comparison's table as Markdown or LaTeX."""
from __future__ import annotations

import logging
import sys


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "report", help="a finished comparison's table as Markdown or LaTeX",
        description="Read the folder written by `arraysel compare` (run.json, runs.csv) and print, or write to "
                    "--out, one table: the Table-1 metrics of each selector's listed selection (the best of "
                    "its seeds by Mean) and the statistics of its Means over seeds: median [IQR], the "
                    "distribution-free confidence interval of the median from order statistics labelled "
                    "with its exact coverage (93.8 % for 5 seeds; n/a when the seeds are too few for "
                    "--ci-level), the Mann-Whitney p-value against random Holm-adjusted over the "
                    "selectors, and Vargha-Delaney A (the chance of ending below a random run). "
                    "Deterministic selectors are single values, not tested. The tables are built from "
                    "runs.csv, so folders written by older versions read the same.")
    p.add_argument("folder", metavar="DIR", help="the --out folder of a finished `arraysel compare`")
    p.add_argument("--format", choices=("md", "latex"), default="md",
                   help="md (GitHub Markdown, default) or latex (a table with a booktabs tabular)")
    p.add_argument("--out", default=None, metavar="FILE", help="write the table to FILE instead of printing it")
    p.add_argument("--rebuild", action="store_true",
                   help="also rewrite DIR/table1.csv and DIR/stats.csv from DIR/runs.csv (e.g. a folder written "
                        "by an older version)")
    p.add_argument("--ci-level", type=float, default=None, metavar="P",
                   help="least coverage of the median's interval, between 0 and 1 (default 0.9: 5 seeds "
                        "give [min, max] at 93.8 %%; 0.95 needs 6 seeds)")
    p.set_defaults(func=run)


def run(args) -> int:
    from arraysel.report.stats import CI_LEVEL
    from arraysel.report.summary import report

    level = CI_LEVEL if args.ci_level is None else args.ci_level
    text, written = report(args.folder, args.format, args.out, rebuild=args.rebuild, level=level)
    if args.out is None:
        sys.stdout.write(text)
    for path in written:
        logging.getLogger(__name__).warning("wrote %s", path)
    return 0
