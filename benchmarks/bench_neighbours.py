"""Neighbour evaluations a second: one-swap neighbourhoods scored in one call against the same masks
scored independently, and where the time of a neighbourhood goes.

    python benchmarks/bench_neighbours.py --scenes paper,l11-5v,c5-2v --pairs 256 --rounds 3 --threads 1

Per scene, ``--rounds`` steps of a search from the uniform layout: ``--pairs`` one-swap neighbours of
the selection (a random order, seed 0) are scored each way, alternated in one process, and the
selection moves to the best of them (so the rows the PSF objective keeps from one neighbourhood to
the next serve as in a search; the first step forms them); the rates are over all steps. The ways:
``arraysel.objective.neighbours.evaluate_swaps`` (the objective's own ``evaluate_swaps`` when it
has one, else its fallback: the neighbour masks through ``evaluate``) and ``objective.evaluate`` of
the neighbour masks built by the caller. Both must give the same Means to rounding (checked:
relative 1e-4; the largest relative difference is recorded). Then one more
neighbourhood evaluation runs under ``cProfile``, and the share of its time in the PSF fast path's
stages is printed: the channel envelopes of the certificates (``swap_envelopes`` for a
neighbourhood), the images on E, the block bounds, the refinement of loose blocks and ties, the
exact path, and the metrics. The last line is one JSON record.

``--start random`` starts from a random selection instead (seed 0), where a descent begins: there the
certificates leave many neighbours to the refinement, which delay-and-sums their loose blocks from
their I/Q channels; ``--channels`` scores each neighbourhood a third way, alternated with the
others, with those channels formed as the product with every pair channel instead of corrected from
the selection's held sums (``Certificates.swap_channels``), and prints both rates and their ratio
(each step's selection sums and pair-image rows formed first by an untimed call on 8 of its
neighbours, and the two ways taken in turn first):

    python benchmarks/bench_neighbours.py --scenes paper,l11-5v,c5-2v --pairs 64 --rounds 12 --threads 1 --prepare --start random --channels

With ``--prepare`` each scene runs twice, side by side: on a fresh objective as above, then on one
prepared for neighbourhoods first (``arraysel.objective.neighbours.prepare_neighbourhoods``: every
pair-image row formed, its seconds printed), as the runners prepare the objective of a run that
scores neighbourhoods. Chunks of a first-improvement descent are ``--pairs 64``:

    python benchmarks/bench_neighbours.py --scenes paper,l11-5v --pairs 64 --rounds 12 --threads 1 --prepare
"""
from __future__ import annotations

import argparse
import contextlib
import cProfile
import json
import os
import pstats
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import set_threads  # noqa: E402

#: profile entries (file suffix, functions) of the stages reported
STAGES = {
    "envelopes": ("certificate.py", ("envelopes", "swap_envelopes")),
    "images on E": ("basis.py", ("images", "swap_images")),
    "block bounds": ("certificate.py", ("bound",)),
    "refinement": ("refinement.py", ("refine",)),
    "exact path": ("operator.py", ("kernels_exact",)),
    "metrics": ("metrics.py", ("psf_metrics",)),
}


def _stage_shares(prof: cProfile.Profile) -> dict[str, float]:
    st = pstats.Stats(prof)
    total = max(st.total_tt, 1e-12)
    out = {}
    for name, (suffix, funcs) in STAGES.items():
        cum = sum(v[3] for (f, _, fn), v in st.stats.items() if f.endswith(suffix) and fn in funcs)
        out[name] = cum / total
    return out


def _corrected(obj) -> int:
    """Neighbours whose refinement channels were corrected from held sums, over the objective's bases."""
    return sum(p.basis.certificates.corrected for p in obj.psfs if p.basis is not None)


@contextlib.contextmanager
def _channels_as_product():
    """The refinement forms every selection's I/Q channels as the product with the pair channels."""
    from arraysel.physics.psf.certificate import Certificates

    keep = Certificates.swap_channels_most
    Certificates.swap_channels_most = -1
    try:
        yield
    finally:
        Certificates.swap_channels_most = keep


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="paper,l11-5v,c5-2v")
    ap.add_argument("--pairs", type=int, default=512)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--start", choices=("uniform", "random"), default="uniform",
                    help="the selection the steps start from")
    ap.add_argument("--channels", action="store_true",
                    help="also score each neighbourhood with the refinement's channels formed as the product")
    ap.add_argument("--prepare", action="store_true",
                    help="also run each scene on an objective prepared for neighbourhoods")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    import numpy as np

    from arraysel.objective.neighbours import evaluate_swaps, prepare_neighbourhoods, swap_masks, swap_pairs
    from arraysel.objective.psf_objective import build_objective
    from arraysel.selectors.layouts import uniform_layout

    record = {"pairs": args.pairs, "rounds": args.rounds, "threads": args.threads, "start": args.start, "scenes": {}}
    print(f"{'scene':17s} {'Ne':>4s} {'k':>4s} {'own':>4s} {'swaps/s':>9s} {'masks/s':>9s} {'ratio':>6s}  stages of a "
          f"neighbourhood (share of its time)")
    runs = [(s, False) for s in args.scenes.split(",") if s]
    if args.prepare:
        runs = [r for s, _ in runs for r in ((s, False), (s, True))]
    for scene, prepared in runs:
        obj = build_objective(scene)
        label = f"{scene}+prepared" if prepared else scene
        if prepared:
            print(f"{label}: prepare_neighbourhoods {prepare_neighbourhoods(obj):.1f} s")
        n, k = int(obj.n_elements), int(obj.k)
        base = np.zeros(n, dtype=bool)
        rng = np.random.default_rng(0)
        base[uniform_layout(n, k) if args.start == "uniform" else rng.choice(n, k, replace=False)] = True
        obj.evaluate(swap_masks(base, *(v[:8] for v in swap_pairs(base, rng))))  # warm: compiled passes, plans
        evaluate_swaps(obj, base, *(v[:8] for v in swap_pairs(base, rng)))
        t_swaps, t_masks, t_product, diff = [], [], [], 0.0
        corrected0 = _corrected(obj)  # (a basis from the process's cache keeps its counts)
        for _ in range(args.rounds):
            # a step of a search: this selection's neighbours, then a move to the best of them
            out, into = (v[:args.pairs] for v in swap_pairs(base, rng))
            if args.channels:
                # the selection's sums and rows formed first, so that both ways find them
                evaluate_swaps(obj, base, out[-8:], into[-8:])
                ways = [False, True] if len(t_swaps) % 2 == 0 else [True, False]
            else:
                ways = [False]
            for product in ways:
                with _channels_as_product() if product else contextlib.nullcontext():
                    t0 = time.perf_counter()
                    got = evaluate_swaps(obj, base, out, into)["Mean"]
                    (t_product if product else t_swaps).append(time.perf_counter() - t0)
                if product:
                    c = got
                else:
                    a = got
            if args.channels:
                diff = max(diff, float(np.nanmax(np.abs(a - c) / np.maximum(np.abs(c), 1e-30))))
            t0 = time.perf_counter()
            b = obj.evaluate(swap_masks(base, out, into))["Mean"]
            t_masks.append(time.perf_counter() - t0)
            diff = max(diff, float(np.nanmax(np.abs(a - b) / np.maximum(np.abs(b), 1e-30))))
            if not np.allclose(a, b, rtol=1e-4, atol=0):
                raise SystemExit(f"{scene}: the neighbourhood's Means differ from the masks' "
                                 f"(largest relative difference {diff:.3g})")
            best = int(np.argmin(b))
            base = swap_masks(base, out[best:best + 1], into[best:best + 1])[0]
        out, into = (v[:args.pairs] for v in swap_pairs(base, rng))
        prof = cProfile.Profile()
        prof.enable()
        evaluate_swaps(obj, base, out, into)
        prof.disable()
        shares = _stage_shares(prof)
        rs, rm = out.size * len(t_swaps) / sum(t_swaps), out.size * len(t_masks) / sum(t_masks)
        own = callable(getattr(obj, "evaluate_swaps", None))
        print(f"{label:17s} {n:4d} {k:4d} {'yes' if own else 'no':>4s} {rs:9.1f} {rm:9.1f} {rs / rm:6.2f}  " +
              ", ".join(f"{k_} {v:.0%}" for k_, v in shares.items()))
        if t_product:
            rp = out.size * len(t_product) / sum(t_product)
            corrected = _corrected(obj) - corrected0
            print(f"{'':17s} refinement's channels corrected from the held sums: {rs:.1f} swaps/s; as the product: "
                  f"{rp:.1f} swaps/s ({rs / rp:.2f}x; {corrected} neighbours' channels corrected)")
            record["scenes"][label + "+product-channels"] = {"swaps_per_s": rp, "seconds_swaps": t_product,
                                                              "channels_corrected": corrected}
        record["scenes"][label] = {"n_elements": n, "k": k, "own_evaluate_swaps": own, "swaps_per_s": rs,
                                   "masks_per_s": rm, "seconds_swaps": t_swaps, "seconds_masks": t_masks,
                                   "stage_shares": shares, "largest_relative_difference": diff}
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    sys.exit(main())
