"""The fast objective on the probes people use: one row per probe (issue 17's table).

For each scene, in a fresh process with an empty basis cache (so the first-run precompute is
measured): the precompute time, the steady ``Objective.evaluate`` time per mask (random
k-subsets, after a warm-up), the resident memory (peak RSS of the process after the
evaluations), straight-through gradient steps per minute (``selection_loss`` forward +
backward + Adam, one mask per step), the fallback fraction on the random masks, and the
fidelity: SI-MSE of the fast kernels against the exact path for the uniform, a random, the
'edges' (the k/2 outermost elements on each side) and the 'centre' (the k middle elements)
masks.

Usage::

    python benchmarks/bench_probes.py [--probes paper,l11-5v,c5-2v,linear-256] [--masks 1024]

``linear-256`` is the L11-5v scene with the probe extended to 256 elements (k = 128).
The last output line is a JSON record; everything before it is for people.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as C  # noqa: E402

PROBES = {
    "paper": ("paper", None),
    "l11-5v": ("l11-5v", None),
    "c5-2v": ("c5-2v", None),
    "linear-256": ("l11-5v", {"probe": {"n_elements": 256}, "selection": {"k": 128}}),
}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--probes", default=",".join(PROBES), help=f"comma-separated, from {list(PROBES)}")
    p.add_argument("--masks", type=int, default=1024, help="random masks timed per probe (default 1024)")
    p.add_argument("--steps", type=int, default=30, help="timed gradient steps per probe (default 30)")
    p.add_argument("--cache", help="basis cache folder to use and keep (default: a fresh temporary one, so the "
                                   "precompute column is the first run's; with a folder holding the basis it "
                                   "is the load time)")
    p.add_argument("--one", help=argparse.SUPPRESS)
    p.add_argument("--build", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    for name in a.probes.split(","):
        if name not in PROBES:
            p.error(f"--probes: unknown probe {name!r}; choose from {list(PROBES)}")
    return a


def _masks(n, ne, k):
    return C.named_masks(ne, k, random_seed=99), C.random_masks(n, ne, k, seed=0)


def build_one(name: str) -> dict:
    """Build the probe's basis into the (empty) cache: the first-run precompute time."""
    import resource
    import time

    from arraysel.objective.psf_objective import Objective
    from arraysel.scenes.schema import load_scene

    C.set_threads(None)
    base, over = PROBES[name]
    t0 = time.perf_counter()
    Objective(load_scene(base, overrides=over))
    return {"precompute_s": time.perf_counter() - t0,
            "build_peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20}


def run_one(name: str, masks: int, steps: int) -> dict:
    """Measure one probe in this process (called in a child process, the basis cached)."""
    import resource
    import time

    import numpy as np
    import torch

    from arraysel.objective.metrics import si_mse
    from arraysel.objective.psf_objective import Objective
    from arraysel.selectors.relax import sequential_selection
    from arraysel.scenes.schema import load_scene

    C.set_threads(None)
    base, over = PROBES[name]
    scene = load_scene(base, overrides=over)
    t0 = time.perf_counter()
    obj = Objective(scene)
    precompute = time.perf_counter() - t0
    ne, k = obj.n_elements, obj.k
    special, rand = _masks(masks, ne, k)
    warm = min(256, masks)
    obj.evaluate(rand[:warm])
    obj.fallbacks = 0
    basis = obj.psf.basis
    before = dict(basis.refinement.settled) if basis is not None else {}
    t0 = time.perf_counter()
    obj.evaluate(rand)
    per_mask = (time.perf_counter() - t0) / masks
    fallbacks = obj.fallbacks / masks
    settled = {key: (basis.refinement.settled[key] - before[key]) / masks for key in before}
    # gradient steps (as the ste selector takes them)
    logits = torch.zeros(ne, k, requires_grad=True)
    opt = torch.optim.Adam([logits], lr=1e-3)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        logits.normal_(0, 0.01, generator=gen)
    # untimed steps first: a loop of single masks switches to the compiled block bounds and
    # envelopes after Certificates.compiled_bound_warm of them, and loading those once takes up
    # to a second (256 elements); the column is the steady rate
    warm_steps = (basis.certificates.compiled_bound_warm if basis is not None else 0) + 2
    for i in range(steps + warm_steps):
        if i == warm_steps:
            t0 = time.perf_counter()
        r = sequential_selection(logits, 2.0)
        loss, _ = obj.selection_loss(r.P, r.P_soft)
        opt.zero_grad()
        loss.backward()
        opt.step()
    steps_per_min = 60 * steps / (time.perf_counter() - t0)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
    w = torch.tensor(np.stack(list(special.values())), dtype=obj.dtype)
    with torch.no_grad():
        kf, fb = obj.psf.kernels(w, return_info=True)
        ke = obj.psf.kernels_exact(w)
    fid = {n: float(si_mse(kf[i].to(torch.complex128), ke[i].to(torch.complex128)))
           for i, n in enumerate(special)}
    fast = obj.psf.basis
    return {"probe": name, "n_elements": ne, "k": k, "ms_per_mask": per_mask * 1e3, "rss_gib": rss,
            "load_s": precompute, "grad_steps_per_min": steps_per_min, "fallback_fraction": fallbacks,
            "si_mse_vs_exact": fid, "exact_path_for": [n for i, n in enumerate(special) if bool(fb[i])],
            "fast_path": fast is not None, "rank": getattr(fast, "rank", None),
            "strips": getattr(fast, "strips", None), "kernel_tol": fast.refinement.kernel_tol if fast is not None else None,
            "settled_fraction": settled}


def main(argv=None):
    args = parse_args(argv)
    if args.one:
        print(json.dumps(run_one(args.one, args.masks, args.steps)))
        return
    if args.build:
        print(json.dumps(build_one(args.build)))
        return
    rows = []
    for name in args.probes.split(","):
        with tempfile.TemporaryDirectory() as tmp:
            env = dict(os.environ, ARRAYSEL_CACHE=args.cache or tmp)
            outs = [subprocess.run([sys.executable, __file__, *flags], env=env, capture_output=True, text=True)
                    for flags in (["--build", name],
                                  ["--one", name, "--masks", str(args.masks), "--steps", str(args.steps)])]
        bad = [o for o in outs if o.returncode != 0]
        if bad:
            print(bad[0].stderr[-3000:], file=sys.stderr)
            rows.append({"probe": name, "error": bad[0].stderr.strip().splitlines()[-1:]})
            continue
        rows.append({**json.loads(outs[0].stdout.strip().splitlines()[-1]),
                     **json.loads(outs[1].stdout.strip().splitlines()[-1])})
        r = rows[-1]
        print(f"{r['probe']:>11} Ne {r['n_elements']:>3} k {r['k']:>3}: {r['ms_per_mask']:6.2f} ms/mask, "
              f"resident {r['rss_gib']:.2f} GiB (build peak {r['build_peak_rss_gib']:.2f}), "
              f"precompute {r['precompute_s']:6.1f} s, "
              f"{r['grad_steps_per_min']:7.0f} grad steps/min, fallbacks {100 * r['fallback_fraction']:.2f} %, "
              f"max SI-MSE vs exact {max(r['si_mse_vs_exact'].values()):.1e}, "
              f"rank {r['rank']}, kernel tol {r['kernel_tol']}, settled by "
              + ", ".join(f"{key} {100 * v:.1f} %" for key, v in r["settled_fraction"].items()) + " "
              f"(exact path for {r['exact_path_for'] or 'none'})", flush=True)
    print(json.dumps({"machine": C.machine(), "rows": rows}))


if __name__ == "__main__":
    main()
