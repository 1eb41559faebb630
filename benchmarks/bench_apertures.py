"""Milliseconds a mask of a scene's objective with one shared aperture, a full transmit with a
sparse receive (``aperture.mode = "full-tx"``) and separate transmit and receive apertures
(``"separate"``, ``k_tx = k_rx = k``) and, on scenes imaged on planes, a transmit aperture per
transmit event (``"per-transmit"``, ``k_tx = k_rx = k``), on random selections
(``docs/apertures.md``).

``objective.evaluate`` of a batch (one warm-up call of two masks first, not timed), float32, one
torch thread, the median of ``--repeats`` calls divided by the batch. The 1-D scenes evaluate
``full-tx`` and ``separate`` on the exact path (the pair basis holds only the shared aperture), so
their batch is small.

    python benchmarks/bench_apertures.py                       # matrix-1024, matrix-1024-sector, paper
    python benchmarks/bench_apertures.py --scenes matrix-1024 --repeats 3
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from arraysel.objective.build import build_objective
from arraysel.scenes.schema import load_scene

BATCH = {"matrix-1024": 128, "matrix-1024-sector": 64, "paper": 4}


def ms_a_mask(obj, masks: np.ndarray, repeats: int) -> float:
    obj.evaluate(masks[:2])
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        obj.evaluate(masks)
        times.append(time.perf_counter() - t0)
    return statistics.median(times) / len(masks) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="matrix-1024,matrix-1024-sector,paper")
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(1)
    for scene in args.scenes.split(","):
        rng = np.random.default_rng(0)
        base = build_objective(load_scene(scene))
        n, k, b = base.n_elements, base.k, BATCH.get(scene, 16)
        shared = np.zeros((b, n), dtype=bool)
        both = np.zeros((b, 2 * n), dtype=bool)
        for r in range(b):
            shared[r, rng.choice(n, k, replace=False)] = True
            both[r, rng.choice(n, k, replace=False)] = True
            both[r, n + rng.choice(n, k, replace=False)] = True
        row = [f"{scene} (batch {b})", f"shared {ms_a_mask(base, shared, args.repeats):.2f}"]
        for mode, masks in (("full-tx", shared), ("separate", both)):
            obj = build_objective(load_scene(scene, overrides={"aperture": {"mode": mode}}))
            row.append(f"{mode} {ms_a_mask(obj, masks, args.repeats):.2f}")
        if getattr(base, "image_kind", None) == "planes" and not hasattr(base, "beam_metrics"):
            obj = build_objective(load_scene(scene, overrides={"aperture": {"mode": "per-transmit"}}))
            events = np.zeros((b, obj.n_elements), dtype=bool)
            for r in range(b):
                for block in range(obj.n_events + 1):
                    events[r, block * n + rng.choice(n, k, replace=False)] = True
            row.append(f"per-transmit ({obj.n_events} events) {ms_a_mask(obj, events, args.repeats):.2f}")
        print(" | ".join(row) + " ms a mask", flush=True)


if __name__ == "__main__":
    main()
