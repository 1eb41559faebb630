"""The two-way beam-pattern objective (``arraysel.physics.beampattern`` and
``arraysel.objective.beam_objective``) on MATRIX-32x32, k = 256 of 1024, a +-30 degree sector.

``--part speed``: milliseconds a mask of ``BeamPatternScorer.metrics`` (every term) without
gradient, and with the gradient of ``PSL_dB + ISLR_dB + GLL_dB`` with respect to the weights, in
batches of 1, 16, 64 and 256 random masks, for each ``--n-freq``; the pattern alone too. Each
figure is the best of ``--repeat`` runs (the machine is shared: the best is the least disturbed).

``--part convergence``: the metrics of 12 fresh random masks, the uniform thinning (600 um
lattice), untapered and cosine-tapered Fermat spirals and the full array, with 2 to 32
frequencies and oversample 1 and 2, against a reference of 64 frequencies and oversample 3: the
largest difference of each metric over the masks and the Spearman rank correlation of PSL and
ISLR with the reference.

Usage::

    python benchmarks/bench_beampattern.py --part speed --threads 1 --n-freq 4,8
    python benchmarks/bench_beampattern.py --part convergence --threads 2

The last output line is a JSON record.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as C  # noqa: E402


def _masks(n_random: int, seed: int = 0):
    import numpy as np

    from arraysel.selectors.layouts import fermat_spiral_layout, uniform_layout

    rng = np.random.default_rng(seed)
    rows, names = [], []
    for i in range(n_random):
        m = np.zeros(1024)
        m[rng.choice(1024, 256, replace=False)] = 1
        rows.append(m)
        names.append(f"random{i}")
    for name, idx in (("uniform", uniform_layout(1024, 256, (32, 32))),
                      ("spiral", fermat_spiral_layout((32, 32), 256, taper="none")),
                      ("spiral-cosine", fermat_spiral_layout((32, 32), 256, taper="cosine")),
                      ("full", list(range(1024)))):
        m = np.zeros(1024)
        m[idx] = 1
        rows.append(m)
        names.append(name)
    return np.stack(rows), names


def speed(a) -> dict:
    import numpy as np
    import torch

    from arraysel.objective.beam_objective import BeamPatternScorer
    from arraysel.physics.beampattern import BeamPattern
    from arraysel.physics.probes import get_probe

    probe = get_probe("MATRIX-32x32")
    masks = torch.tensor(_masks(256)[0][:256], dtype=torch.float32)
    out = {}
    print(f"{'n_freq':>6} {'grid':>9} {'batch':>5} {'pattern':>9} {'metrics':>9} {'fwd+bwd':>9}   (ms a mask)")
    for nf in a.n_freq:
        t0 = time.perf_counter()
        sc = BeamPatternScorer(BeamPattern.from_probe(probe, n_freq=nf, sector_deg=(30, 30)))
        setup = time.perf_counter() - t0
        grid = tuple(sc.pattern.coverage.shape)
        sc.metrics(masks[:16])                   # compile and warm up
        for b in (1, 16, 64, 256):
            w = masks[:b]

            def best(fn):
                ts = []
                for _ in range(a.repeat):
                    t = time.perf_counter()
                    fn()
                    ts.append(time.perf_counter() - t)
                return 1e3 * min(ts) / b

            with torch.no_grad():
                t_pat = best(lambda: sc.pattern.pattern(w))
                t_met = best(lambda: sc.metrics(w))

            def grad():
                x = w.clone().requires_grad_()
                m = sc.metrics(x, terms=["PSL_dB", "ISLR_dB", "GLL_dB"])
                (m["PSL_dB"] + m["ISLR_dB"] + m["GLL_dB"]).sum().backward()
                assert bool(torch.isfinite(x.grad).all())

            t_grad = best(grad)
            print(f"{nf:>6} {grid[0]:>4}x{grid[1]:<4} {b:>5} {t_pat:>9.3f} {t_met:>9.3f} {t_grad:>9.3f}")
            out[f"n{nf}_b{b}"] = {"pattern_ms": round(t_pat, 4), "metrics_ms": round(t_met, 4),
                                  "grad_ms": round(t_grad, 4)}
        out[f"n{nf}_setup_s"] = round(setup, 2)
        out[f"n{nf}_grid"] = grid
    return out


def _metrics(masks, n_freq: int, oversample: float, chunk: int = 16):
    import torch

    from arraysel.objective.beam_objective import BeamPatternScorer
    from arraysel.physics.beampattern import BeamPattern
    from arraysel.physics.probes import get_probe

    sc = BeamPatternScorer(BeamPattern.from_probe(get_probe("MATRIX-32x32"), n_freq=n_freq, oversample=oversample,
                                                  sector_deg=(30, 30), chunk=chunk))
    with torch.no_grad():
        m = sc.metrics(torch.tensor(masks, dtype=torch.float32))
    return {k: v.double().numpy() for k, v in m.items()}, tuple(sc.pattern.coverage.shape)


def convergence(a) -> dict:
    import numpy as np
    from scipy.stats import spearmanr

    masks, names = _masks(12)
    ref, grid = _metrics(masks, 64, 3.0, chunk=2)
    print(f"reference: 64 frequencies, oversample 3, grid {grid[0]} x {grid[1]}")
    print("masks: " + ", ".join(names))
    print("reference PSL_dB: " + ", ".join(f"{v:.2f}" for v in ref["PSL_dB"]))
    print("reference ISLR_dB: " + ", ".join(f"{v:.2f}" for v in ref["ISLR_dB"]))
    print(f"\n{'n_freq':>6} {'over':>4} {'grid':>9} | max |difference| over the masks "
          f"{'PSL dB':>7} {'ISLR dB':>7} {'GLL dB':>7} {'w_u %':>6} {'w_v %':>6} | Spearman PSL  ISLR")
    out = {}
    for over in (1.0, 2.0):
        for nf in (2, 4, 6, 8, 12, 16, 32):
            m, g = _metrics(masks, nf, over)
            d = {k: float(np.max(np.abs(m[k] - ref[k]))) for k in ("PSL_dB", "ISLR_dB", "GLL_dB")}
            for k in ("width_u_6dB", "width_v_6dB"):
                d[k] = float(np.max(np.abs(m[k] / ref[k] - 1))) * 100
            rp = spearmanr(m["PSL_dB"], ref["PSL_dB"]).statistic
            ri = spearmanr(m["ISLR_dB"], ref["ISLR_dB"]).statistic
            print(f"{nf:>6} {over:>4.0f} {g[0]:>4}x{g[1]:<4} | {'':31}{d['PSL_dB']:>7.2f} {d['ISLR_dB']:>7.2f} "
                  f"{d['GLL_dB']:>7.2f} {d['width_u_6dB']:>6.2f} {d['width_v_6dB']:>6.2f} | {rp:>13.3f} {ri:>5.3f}")
            out[f"n{nf}_o{over:.0f}"] = {**{k: round(v, 4) for k, v in d.items()}, "spearman_psl": round(rp, 4),
                                        "spearman_islr": round(ri, 4)}
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--part", choices=("speed", "convergence"), default="speed")
    p.add_argument("--n-freq", default="4,8", help="frequencies to time, comma-separated (default 4,8)")
    p.add_argument("--repeat", type=int, default=3, help="runs of each timing, the best kept (default 3)")
    p.add_argument("--threads", type=int, default=1, help="torch and numba threads (default 1)")
    a = p.parse_args(argv)
    a.n_freq = [int(v) for v in a.n_freq.split(",")]
    C.set_threads(a.threads)
    load0 = os.getloadavg()[0]
    res = speed(a) if a.part == "speed" else convergence(a)
    info = C.machine()
    info["load_avg_1min_start"] = round(load0, 2)
    print(f"\nload average (1 min) at start {load0:.2f}, at end {info['load_avg_1min']}; "
          f"threads {info['torch_threads']}; torch {info['torch']}")
    print(json.dumps({"part": a.part, "results": res, "machine": info}))


if __name__ == "__main__":
    main()
