"""The fast 3-D PSF of the 1024-element matrix probe against the exact path and the PyMUST 3-D pipeline.

The scene is the geometry of the built-in ``matrix-1024``: MATRIX-32x32 (3 MHz, 300 um pitch, 250 um
elements), 9 diverging waves (tilts 3 x 3 over +-10 deg in x and y, virtual sources 10 mm behind
the array), one scatterer at (0, 0, 30 mm), three planes (C-plane 48 x 48, xz and yz 24 x 48) of
pixel lambda / 3 spanning +-8 lambda in x and y and +-4 lambda in z; k = 256. Measured side by side
in one run, in float32:

(a) precompute: the exact model's build (``MatrixPSF``) plus the fast path's build
    (``MatrixFastPSF``, its check against the exact path included), and the resident peak after it;
(b) steady evaluate: ms a mask of ``planes`` without gradient for batches of random 256-element
    masks (``--batches``; one warm-up call per batch size, not timed);
(c) one ste-like gradient step: forward + backward of a scalar of the planes for a batch of 1 and of
    8 soft weight vectors (median of ``--repeats``);
(d) fidelity: SI-MSE of every plane against PyMUST (``tests/pymust_pipeline3.py``) for the full
    array, the uniform mask (every second element in x and y), a random 256-element mask and the
    Fermat-spiral layout (``fermat_spiral_layout``), and the fast path's relative squared error
    against the exact path on the same masks;
(e) PyMUST: the first mask (full) builds its 27 DAS matrices (timed apart); the three other
    fidelity masks are timed after it, a mask each; the ratio to (b).

Usage::

    python benchmarks/bench_matrix_fast.py [--threads 2] [--batches 1,16,64,128] [--replicas 0]

The last output line is a JSON record; everything before it is for people.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import load_tests_module, machine, peak_rss_gib, random_masks, set_threads  # noqa: E402

TARGETS = {"ms_per_mask": 10.0, "step_s": 0.5, "precompute_s": 600.0, "rss_gib": 6.0, "speedup": 80.0,
           "si_mse": 1e-4}


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--threads", type=int, default=2, help="torch / BLAS threads (default 2)")
    p.add_argument("--batches", default="1,16,64,128", help="batch sizes timed (default 1,16,64,128)")
    p.add_argument("--masks", type=int, default=128, help="masks timed per batch size, at least one batch (default 128)")
    p.add_argument("--repeats", type=int, default=3, help="gradient steps timed, median reported (default 3)")
    p.add_argument("--replicas", type=int, default=0, help="FastSettings.replicas (default 0)")
    a = p.parse_args(argv)
    set_threads(a.threads)
    import numpy as np
    import torch

    from arraysel.physics.probes import Acquisition, get_probe
    from arraysel.physics.volume import (PLANES, FastSettings, MatrixFastPSF, MatrixPSF, MatrixPSFSetup,
                                         diverging_delays3, fast_relative_error, tilt_grid)
    from arraysel.selectors.layouts import fermat_spiral_layout

    probe = get_probe("MATRIX-32x32")
    acq = Acquisition.for_probe(probe)
    lam = acq.c / probe.fc
    ax, ay = tilt_grid(3, 3, 10.0, 10.0)
    delays = diverging_delays3(probe, ax, ay, 10e-3, acq)
    setup = MatrixPSFSetup(probe, acq, delays, (0.0, 0.0, 30e-3), half_x=8 * lam, half_y=8 * lam,
                           half_z=4 * lam, pixel=lam / 3)
    rec = {"machine": machine(), "probe": probe.name, "n_tx": len(delays), "k": 256, "pixel_m": setup.pixel,
           "replicas": a.replicas}
    rec["load_avg_start"] = _load()

    # (a) precompute
    t = time.perf_counter()
    exact = MatrixPSF(setup, dtype=torch.float32)
    rec["exact_build_s"] = round(time.perf_counter() - t, 2)
    t = time.perf_counter()
    fast = MatrixFastPSF(exact, FastSettings(replicas=a.replicas), dtype=torch.float32)
    rec["fast_build_s"] = round(time.perf_counter() - t, 2)
    rec["precompute_s"] = round(rec["exact_build_s"] + rec["fast_build_s"], 2)
    rec["planes"] = {k: list(v.shape[:2]) for k, v in exact.coords.items()}
    rec["fast_sizes"] = dict(fast.sizes)
    rec["fast_check_max_relative_error"] = float(f"{fast.check['max_relative_error']:.3g}")
    rec["rss_after_build_gib"] = round(peak_rss_gib(), 2)
    print(f"scene: {probe.name}, {len(delays)} diverging waves, planes {rec['planes']} of lambda/3, k = 256, "
          f"{torch.get_num_threads()} threads, load average {rec['load_avg_start']}")
    print(f"precompute: exact model {rec['exact_build_s']} s + fast path {rec['fast_build_s']} s (its check "
          f"{rec['fast_check_max_relative_error']:.2e}) = {rec['precompute_s']} s; sizes {fast.sizes}")

    # (b) steady evaluate
    batches = [int(b) for b in a.batches.split(",")]
    ms = {}
    with torch.no_grad():
        for bs in batches:
            n = max(bs, a.masks // bs * bs)
            m = torch.tensor(random_masks(n + bs, 1024, 256, seed=bs), dtype=torch.float32)
            fast.planes(m[:bs])  # warm-up
            t = time.perf_counter()
            for i in range(bs, n + bs, bs):
                fast.planes(m[i:i + bs])
            ms[bs] = 1e3 * (time.perf_counter() - t) / n
    rec["evaluate_ms_per_mask"] = {str(k): round(v, 2) for k, v in ms.items()}
    rec["load_avg_evaluate"] = _load()
    best_bs = min(ms, key=ms.get)
    print("steady evaluate, no gradient (float32): " + ", ".join(f"batch {k}: {v:.2f} ms a mask" for k, v in ms.items())
          + f" (load average {rec['load_avg_evaluate']})")

    # (c) gradient steps
    steps = {}
    for bs in (1, 8):
        times = []
        for r in range(a.repeats):
            g = torch.Generator().manual_seed(r)
            w = torch.rand(bs, 1024, generator=g).requires_grad_(True)
            t = time.perf_counter()
            planes = fast.planes(w)
            sum((v.abs() ** 2).mean() for v in planes.values()).backward()
            times.append(time.perf_counter() - t)
        steps[bs] = statistics.median(times)
    rec["grad_step_s"] = {str(k): round(v, 3) for k, v in steps.items()}
    rec["rss_fast_gib"] = round(peak_rss_gib(), 2)
    print("one gradient step (forward + backward): " + ", ".join(f"batch {k}: {v:.3f} s" for k, v in steps.items())
          + f"; resident peak {rec['rss_fast_gib']} GiB")

    # (d) fidelity, (e) PyMUST
    uni = np.zeros((32, 32))
    uni[::2, ::2] = 1
    named = {"full": np.ones(1024), "uniform": uni.ravel(), "random": random_masks(1, 1024, 256, seed=5)[0],
             "spiral": probe.mask(fermat_spiral_layout((32, 32), 256))}
    w = torch.tensor(np.stack(list(named.values())), dtype=torch.float32)
    with torch.no_grad():
        got = fast.planes(w)
        ex = exact.planes(w)
    vs_exact = fast_relative_error({k: v.to(torch.complex128) for k, v in got.items()},
                                   {k: v.to(torch.complex128) for k, v in ex.items()})
    rec["fast_vs_exact"] = {name: float(f"{float(e):.3g}") for name, e in zip(named, vs_exact)}
    mod = load_tests_module("pymust_pipeline3")
    oracle = mod.PyMUSTScene3(probe, acq, delays, setup.scatterer, {k: v.numpy() for k, v in exact.coords.items()})
    t = time.perf_counter()
    refs = {"full": oracle.planes(named["full"])}
    rec["pymust_first_mask_s"] = round(time.perf_counter() - t, 2)
    rec["pymust_das_build_s"] = round(oracle.das_seconds, 2)
    t = time.perf_counter()
    for name in ("uniform", "random", "spiral"):
        refs[name] = oracle.planes(named[name])
    rec["pymust_s_per_mask"] = round((time.perf_counter() - t) / 3, 3)
    rec["rss_with_pymust_gib"] = round(peak_rss_gib(), 2)
    rec["load_avg_pymust"] = _load()
    fid = {}
    for i, name in enumerate(named):
        for plane in PLANES:
            fid[f"{name}/{plane}"] = float(f"{mod.si_mse(got[plane][i].to(torch.complex128).numpy(), refs[name][plane]):.3g}")
    rec["si_mse"] = fid
    rec["speedup_per_mask"] = {str(k): round(rec["pymust_s_per_mask"] * 1e3 / v, 1) for k, v in ms.items()}
    print(f"PyMUST: first mask {rec['pymust_first_mask_s']} s (its DAS matrices {rec['pymust_das_build_s']} s), "
          f"then {rec['pymust_s_per_mask']} s a mask (load average {rec['load_avg_pymust']}); resident peak "
          f"with it {rec['rss_with_pymust_gib']} GiB")
    print("fast vs exact path (worst plane, relative squared error): "
          + ", ".join(f"{k} {v:.2e}" for k, v in rec["fast_vs_exact"].items()))
    print("SI-MSE per plane against PyMUST (fast path, float32):")
    for name in named:
        print(f"  {name:8s} " + "  ".join(f"{plane} {fid[f'{name}/{plane}']:.2e}" for plane in PLANES))

    worst = max(fid.values())
    rows = [("steady evaluate (best batch: %d)" % best_bs, f"{ms[best_bs]:.2f} ms a mask", "<= 10 ms",
             ms[best_bs] <= TARGETS["ms_per_mask"]),
            ("one gradient step, batch 1 / 8", f"{steps[1]:.3f} s / {steps[8]:.3f} s", "<= 0.5 s",
             steps[1] <= TARGETS["step_s"]),
            ("precompute (exact + fast build)", f"{rec['precompute_s']:.1f} s", "<= 600 s",
             rec["precompute_s"] <= TARGETS["precompute_s"]),
            ("resident peak (arraysel only)", f"{rec['rss_fast_gib']:.2f} GiB", "<= 6 GiB",
             rec["rss_fast_gib"] <= TARGETS["rss_gib"]),
            ("vs PyMUST a mask (best batch)", f"{rec['speedup_per_mask'][str(best_bs)]:.0f}x", ">= 80x",
             rec["speedup_per_mask"][str(best_bs)] >= TARGETS["speedup"]),
            ("worst SI-MSE vs PyMUST (4 masks x 3 planes)", f"{worst:.2e}", "<= 1e-4", worst <= TARGETS["si_mse"])]
    rec["targets_met"] = {r[0]: bool(r[3]) for r in rows}
    print("\n| matrix-1024, k = 256 (fast path, float32) | measured | target | met |\n|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} | {'yes' if r[3] else 'no'} |")
    rec["load_avg_end"] = _load()
    print(json.dumps(rec))
    return rec


if __name__ == "__main__":
    main()
