"""The basis build's pair-image kernel: pixel tiles with every pair row against row blocks.

The sketched build (probes with more than about 68 elements) delay-and-sums the symmetric pair
images on region E with the compiled kernel :func:`arraysel.physics.pairkernels.pair_images`.
It can be called two ways: row blocks of ``build_rows`` pair rows over every pixel (the
streaming pass used when the images do not fit in memory), or a tile of pixels with every pair
row (``BasisBuild._dense_pair_images``). Both are timed here on the same inputs, one after the
other, and checked to agree.

The inputs have a 128-element scene's shapes (7 transmits, 300 samples per channel window) with
synthetic signals and a smooth DAS plan (sample indices that change slowly from pixel to pixel,
as a real plan's do); ``--pixels`` of E's pixels are computed and the time is scaled to E's
144 x 144 pixels.

Usage::

    python benchmarks/bench_pair_images.py [--elements 128] [--pixels 2048] [--threads N]

The last output line is a JSON record; everything before it is for people.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as C  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--elements", type=int, default=128)
    p.add_argument("--pixels", type=int, default=2048, help="pixels computed (default 2048)")
    p.add_argument("--samples", type=int, default=300, help="samples per channel window (default 300)")
    p.add_argument("--transmits", type=int, default=7)
    p.add_argument("--rows", type=int, default=512, help="pair rows per block (the build's build_rows)")
    p.add_argument("--threads", type=int, default=None)
    args = p.parse_args(argv)
    C.set_threads(args.threads)

    import numpy as np

    from arraysel.physics.pairkernels import pair_images, pair_row_blocks

    ntx, ne, T, npix = args.transmits, args.elements, args.samples, args.pixels
    rng = np.random.default_rng(0)
    X = (rng.standard_normal((ntx, ne, T, ne)) + 1j * rng.standard_normal((ntx, ne, T, ne))).astype(np.complex64)
    pix = np.arange(npix)
    i0 = (pix[None, None, :] // 144 + (pix[None, None, :] % 144) // 4 + np.arange(ne)[None, :, None]
          + 3 * np.arange(ntx)[:, None, None]) % (T - 2)
    ang = rng.random((ntx, ne, npix)) * 2 * np.pi
    plan = (i0.astype(np.int32), rng.random((ntx, ne, npix)).astype(np.float32),
            np.cos(ang).astype(np.float32), np.sin(ang).astype(np.float32))
    pair_images(X, tuple(a[:, :, :4].copy() for a in plan), 0, 2)  # compile

    blocks = pair_row_blocks(ne, args.rows)
    t0 = time.perf_counter()
    by_rows = np.concatenate([pair_images(X, plan, e0, e1) for e0, e1, _ in blocks], axis=1)
    t_rows = time.perf_counter() - t0
    t0 = time.perf_counter()
    by_tile = pair_images(X, plan, 0, ne)
    t_tile = time.perf_counter() - t0
    diff = float(np.abs(by_rows - by_tile).max() / np.abs(by_rows).max())
    scale = 144 * 144 / npix
    rows = [["row blocks over all pixels", f"{len(blocks)} calls", f"{t_rows:.2f} s", f"{t_rows * scale:.1f} s"],
            ["one pixel tile, every row", "1 call", f"{t_tile:.2f} s", f"{t_tile * scale:.1f} s"]]
    print(f"{ne} elements, {ne * (ne + 1) // 2} pairs, {ntx} transmits, {T} samples, {npix} pixels")
    print(C.table(rows, ["way", "calls", "time", "scaled to 144 x 144 px"]))
    print(f"speed-up {t_rows / t_tile:.2f}x, max relative difference {diff:.1e}")
    C.emit_json({"machine": C.machine(), "elements": ne, "pixels": npix, "row_blocks_s": t_rows,
                 "pixel_tile_s": t_tile, "speedup": t_rows / t_tile, "max_rel_diff": diff})


if __name__ == "__main__":
    main()
