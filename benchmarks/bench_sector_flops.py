"""What a selection costs on a sector scene's fast path, in arithmetic, against this machine's rate.

Each point's fast model forms two products a selection (``docs/sector.md``): the receive sums
``w @ B`` (``B`` real, Ne x 2C: C complex columns, the pixels times the nodes each needs) and the
transmit sums ``c @ Psi`` (``Psi`` complex, R x C: R the transmits' summed ranks). Per selection and
point that is ``2 Ne 2C + 8 R C`` floating-point operations, whatever the code; a mirrored point costs
its model's. The script reads the sizes of the scene's cached models, measures the rate of this
machine's matrix products on the same shapes (a batch of ``--masks`` selections against blocks of
the stored columns, float32, one core, the best of 20 products), scores ``--masks`` fresh random
selections on every point (``beam_metrics``: the products, the images and the lobe metrics) and
prints the three side by side. The arithmetic's time at that rate, shared by ``--threads`` cores
each as fast as one (perfect scaling), is a floor for any code that forms these products with this
machine's matrix-product library.

    python benchmarks/bench_sector_flops.py --threads 1
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import machine, set_threads  # noqa: E402


def gemm_rate(m: int, k: int, n: int, complex_: bool, repeats: int = 20) -> float:
    """The best GFLOP/s of ``repeats`` products ``(m, k) @ (k, n)`` in float32 (complex64 with
    ``complex_``: 8 flops a product): the machine's rate at its quietest, so that the floor it
    gives is one."""
    import torch

    dt = torch.complex64 if complex_ else torch.float32
    a, b = torch.randn(m, k, dtype=dt), torch.randn(k, n, dtype=dt)
    a @ b
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t0)
    return (8 if complex_ else 2) * m * k * n / best / 1e9


def spectrum(beams, i: int) -> dict[int, float]:
    """``{r: share of the energy of point i's receive matrix B (Ne x 2C) that its best rank-r
    approximation leaves out}``, from the eigenvalues of ``B B^T`` formed a block of columns at a time."""
    import torch

    model = beams.exact._fast[i]
    model = getattr(model, "model", model)
    n = model._B.shape[1]
    G = torch.zeros(beams.n_elements, beams.n_elements, dtype=torch.float64)
    for a in range(0, n, 8192):
        blk = model._B[:, a:a + 8192].float()
        if model._B_scale is not None:
            blk = blk * model._B_scale[a:a + 8192]
        G += (blk @ blk.T).double()
    ev = torch.linalg.eigvalsh(G).flip(0).clamp_min(0)
    left = 1 - torch.cumsum(ev, 0) / ev.sum()
    return {r: float(left[r - 1]) for r in (64, 128, 256, 512, 768, 896) if r <= len(ev)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="matrix-1024-sector")
    ap.add_argument("--masks", type=int, default=64, help="selections a batch (the objective's chunk)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--spectrum", type=int, default=None, metavar="POINT",
                    help="also the energy a best rank-r approximation of POINT's receive matrix leaves out")
    a = ap.parse_args(argv)
    set_threads(a.threads)
    import numpy as np
    import torch

    from arraysel.objective.sector_objective import SectorObjective

    obj = SectorObjective(a.scene)
    b = obj.beams
    b.fast_min_masks = 1
    sizes = []
    for i in range(b.n_points):
        if not b.fast_point(i, build=False):
            raise SystemExit(f"point {i} has no cached fast model: run compare or bench_sector_build.py first")
        model = b.exact._fast[i]
        model = getattr(model, "model", model)      # a mirrored point: its model's sizes
        cols = model._B.shape[1] // 2
        rows = model._Psi.shape[0]
        sizes.append({"point": i, "columns": cols, "transmit_rows": rows,
                      "gflop": (2 * b.n_elements * 2 * cols + 8 * rows * cols) / 1e9})
    total = sum(s["gflop"] for s in sizes)
    # the products' rate on one core, then as if every thread ran at it (perfect scaling: a floor)
    torch.set_num_threads(1)
    rx = gemm_rate(a.masks, b.n_elements, 2048, False)
    r_mean = int(round(np.mean([s["transmit_rows"] for s in sizes])))
    tx = gemm_rate(a.masks, r_mean, 1024, True)
    torch.set_num_threads(a.threads)
    rx_flop = sum(2 * b.n_elements * 2 * s["columns"] for s in sizes) / 1e9
    tx_flop = total - rx_flop
    floor_ms = (rx_flop / rx + tx_flop / tx) / a.threads * 1e3
    masks = torch.as_tensor(b.fresh_random_masks(a.masks, seed=0).astype(np.float32))
    b.beam_metrics(masks)            # maps the models' pages
    ms = []
    for _ in range(a.rounds):
        t0 = time.perf_counter()
        b.beam_metrics(masks)
        ms.append((time.perf_counter() - t0) / a.masks * 1e3)
    print(f"{b.n_points} points, {total:.1f} GFLOP a selection ({rx_flop:.1f} receive, {tx_flop:.1f} transmit)")
    print(f"this machine, one core: {rx:.0f} GFLOP/s (receive shape), {tx:.0f} GFLOP/s (transmit shape), the best of 20")
    print(f"floor at those rates on {a.threads} thread(s), each at one core's rate: {floor_ms:.0f} ms a selection; "
          f"measured: {', '.join(f'{v:.0f}' for v in ms)} ms")
    tail = spectrum(b, a.spectrum) if a.spectrum is not None else None
    if tail is not None:
        print("receive matrix of point", a.spectrum, "energy left out by the best rank r:",
              ", ".join(f"r {r}: {v:.2f}" for r, v in tail.items()))
    print(json.dumps({"gflop_per_selection": total, "rank_tail": tail, "receive_gflop": rx_flop, "transmit_gflop": tx_flop,
                      "receive_gflops_rate": rx, "transmit_gflops_rate": tx, "floor_ms": floor_ms,
                      "measured_ms": ms, "points": sizes, "machine": machine()}))


if __name__ == "__main__":
    main()
