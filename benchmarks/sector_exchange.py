"""Polish a sector scene's selection by the exchange method and write what it did.

:func:`arraysel.run.sector_exchange.exchange_polish`: rounds of a scan of the selection on
random points of the sector (exact path), the worst ones added to the scene's points, and a polish
on the enlarged set. Writes to ``--out``: ``exchange.csv`` (``config``, ``elements``: the start
and the polished selection, for ``benchmarks/sector_recheck.py --extra``), ``exchange.json`` (each
round: the scanned points and their side lobes, the added points, the polish). Check the result on points it never scanned with
``sector_recheck.py``.

    python benchmarks/sector_exchange.py --selections benchmarks/results/compare-matrix-sector/polished/polish.csv \
        --config "anneal + polish" --rounds 3 --scan 24 --add 2 --seconds 300 --out DIR
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import set_threads  # noqa: E402
from sector_recheck import read_selections  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="matrix-1024-sector", help="a sector scene (name or TOML file)")
    ap.add_argument("--selections", type=Path, required=True, help="CSV with columns config, elements")
    ap.add_argument("--config", required=True, help="the row of --selections to start from")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--scan", type=int, default=24, help="random points scanned a round")
    ap.add_argument("--add", type=int, default=2, help="the most points added a round")
    ap.add_argument("--seconds", type=float, default=300.0, help="seconds of polish a round")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ranges-mm", type=float, nargs=2, default=(20.0, 110.0), help="the scanned points' ranges")
    ap.add_argument("--edge-deg", type=float, default=2.0,
                    help="the scanned points' angles stay this many degrees inside the sector's half-angles")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    set_threads(args.threads)
    import numpy as np

    from arraysel.run.sector_exchange import exchange_polish

    start = read_selections([args.selections], [args.config], 1024)[args.config]
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    res = exchange_polish(args.scene, start, rounds=args.rounds, scan=args.scan, add=args.add, seconds=args.seconds,
                          seed=args.seed, ranges=tuple(r * 1e-3 for r in args.ranges_mm), edge_deg=args.edge_deg,
                          log=lambda line: print(f"[{time.perf_counter() - t0:6.0f} s] {line}", flush=True))
    name = f"{args.config} + exchange"
    rows = [(args.config, start), (name, res["mask"])]
    with open(args.out / "exchange.csv", "w", encoding="utf-8") as f:
        f.write("config,elements\n")
        for cfg, mask in rows:
            f.write(f"\"{cfg}\",{' '.join(str(int(i)) for i in np.flatnonzero(mask))}\n")
    summary = {"command": shlex.join(["python", "benchmarks/sector_exchange.py", *(sys.argv[1:] if argv is None else argv)]),
               "seconds": time.perf_counter() - t0, "points": res["points"], "added": res["added"],
               "history": res["history"]}
    (args.out / "exchange.json").write_text(json.dumps(summary, indent=1, default=float), encoding="utf-8")
    print(f"done in {summary['seconds']:.0f} s; {len(res['added'])} points added", flush=True)


if __name__ == "__main__":
    main()
