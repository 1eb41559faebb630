"""Time and memory of a sector scene's cold build, then of scoring selections on its points.

Builds the scene's objective, scores ``--masks`` fresh random selections with the per-beam view
(``objective.beams.beam_metrics``: with at least 64 selections every point's fast model is built
when it is not cached), then scores them again ``--rounds`` times. Prints, as JSON lines, the
build's wall time, the process's memory after it (``VmHWM`` the peak so far, ``RssAnon`` its own
memory, ``RssFile`` pages of mapped files such as the cache's tensors), and each round's ms a
selection. Run it with an empty cache folder to measure a cold build:

    ARRAYSEL_CACHE=$(mktemp -d) /usr/bin/time -v python benchmarks/bench_sector_build.py

(``/usr/bin/time -v`` adds the whole process's peak resident set and CPU time.)
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import torch

from arraysel.objective.build import build_objective
from arraysel.scenes.schema import load_scene


def memory() -> dict:
    """The process's memory from /proc/self/status (kB), where the system has it."""
    out = {}
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                key, _, value = line.partition(":")
                if key in ("VmHWM", "VmRSS", "RssAnon", "RssFile"):
                    out[key + "_kB"] = int(value.split()[0])
    except OSError:
        pass
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="matrix-1024-sector")
    ap.add_argument("--masks", type=int, default=64, help="selections a batch (>= 64 builds the fast models)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    t0 = time.time()
    obj = build_objective(load_scene(a.scene), device="cpu", dtype=torch.float32)
    beams = obj.beams
    if beams is None:
        raise SystemExit(f"--scene {a.scene} is not a sector scene")
    rng = np.random.default_rng(0)
    masks = np.zeros((a.masks, beams.n_elements), dtype=np.float32)
    for row in masks:
        row[rng.choice(beams.n_elements, beams.k, replace=False)] = 1
    masks = torch.from_numpy(masks)
    beams.beam_metrics(masks)
    print(json.dumps({"scene": a.scene, "build_and_first_score_s": round(time.time() - t0, 1),
                      "load_avg_1min": os.getloadavg()[0], **memory()}), flush=True)
    for r in range(a.rounds):
        t = time.time()
        beams.beam_metrics(masks)
        print(json.dumps({"round": r, "ms_a_selection": round((time.time() - t) / a.masks * 1e3, 1),
                          "load_avg_1min": os.getloadavg()[0], **memory()}), flush=True)


if __name__ == "__main__":
    main()
