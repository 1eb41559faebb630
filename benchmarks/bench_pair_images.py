"""The basis build's pair-image kernel: its rate and the time of one pass over region E.

The sketched build (probes with more than about 68 elements) delay-and-sums the symmetric pair
images on region E with the compiled kernel :func:`arraysel.physics.pairkernels.pair_images`,
a group of pixels with every pair per call, once or twice (the sketch's two passes; once when
the images fit ``keep_images_max_bytes``). This times it on synthetic inputs with a scene's
shapes (7 transmits, 300 samples per channel window, random signals and a smooth DAS plan whose
sample indices change slowly from pixel to pixel, as a real plan's do): ``--pixels`` pixels
in calls of ``--call`` pixels (the build's 16 x 16 tiles: 256), best of ``--repeat``, scaled to
E's 144 x 144 pixels. The rate counts complex multiply-adds of one (transmit, receive,
transmit-element) triple at a pixel: ``ntx Ne^2`` a pixel.

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
    p.add_argument("--call", type=int, default=256, help="pixels a kernel call (default 256)")
    p.add_argument("--samples", type=int, default=300, help="samples per channel window (default 300)")
    p.add_argument("--transmits", type=int, default=7)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=None)
    args = p.parse_args(argv)
    C.set_threads(args.threads)

    import numpy as np

    from arraysel.physics.pairkernels import pair_images

    ntx, ne, T, npix = args.transmits, args.elements, args.samples, args.pixels
    rng = np.random.default_rng(0)
    X = rng.standard_normal((ntx, ne, T, 2, ne)).astype(np.float32)
    pix = np.arange(npix)
    i0 = (pix[None, None, :] // 144 + (pix[None, None, :] % 144) // 4 + np.arange(ne)[None, :, None]
          + 3 * np.arange(ntx)[:, None, None]) % (T - 2)
    ang = rng.random((ntx, ne, npix)) * 2 * np.pi
    plan = (i0.astype(np.int32), rng.random((ntx, ne, npix)).astype(np.float32),
            np.cos(ang).astype(np.float32), np.sin(ang).astype(np.float32))
    pair_images(X, tuple(a[:, :, :4].copy() for a in plan))  # compile (or load the cached code)
    calls = [tuple(np.ascontiguousarray(a[:, :, p0:p0 + args.call]) for a in plan) for p0 in range(0, npix, args.call)]
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        for part in calls:
            pair_images(X, part)
        times.append(time.perf_counter() - t0)
    best = min(times)
    rate = ntx * ne * ne * npix / best
    scaled = best * 144 * 144 / npix
    print(f"{ne} elements, {ne * (ne + 1) // 2} pairs, {ntx} transmits, {T} samples, {npix} pixels "
          f"in {len(calls)} calls of {args.call}")
    print(C.table([[f"{best:.2f} s", f"{rate / 1e6:.0f} M/s", f"{scaled:.1f} s"]],
                  ["best time", "complex multiply-adds", "one pass over 144 x 144 px"]))
    C.emit_json({"machine": C.machine(), "elements": ne, "pixels": npix, "call": args.call,
                 "best_s": best, "times_s": times, "multiply_adds_per_s": rate, "e_pass_s": scaled})


if __name__ == "__main__":
    main()
