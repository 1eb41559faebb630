"""Gradient steps per minute of the PSF-only straight-through (STE) training loss.

One step, as the ``ste`` selector takes it on the paper scene: draw the
(Ne, k) straight-through matrix from the logits
(:func:`arraysel.selectors.relax.sequential_selection`, cosine temperature), evaluate
``Objective.selection_loss(P, P_soft)`` (PSF terms + L_ent + L_row; no data
term), ``backward()`` and an Adam update of the logits. Forward (draw +
loss) and backward (+ update) are timed separately for every step, after
``--warmup`` untimed steps and the one-off precompute (timed and reported
separately). A step whose mask is not certified by the fast path goes
through the exact simulator with gradients; such steps are counted (after
the timing, without gradients) and their times reported apart.

Usage::

    python benchmarks/bench_grad.py [--steps 200] [--relax ste|gumbel] [--threads N]

The last output line is a JSON record; everything before it is for people.
"""
from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as C  # noqa: E402


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--steps", type=int, default=200, help="timed gradient steps (default 200)")
    p.add_argument("--warmup", type=int, default=5, help="untimed steps first (default 5)")
    p.add_argument("--relax", choices=("ste", "gumbel"), default="ste",
                   help="ste: arg-max draw (the ste selector); gumbel: fresh Gumbel noise every step")
    p.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (ste's default 1e-3)")
    p.add_argument("--threads", type=int, default=None, help="torch / BLAS threads (default: library default)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    a = p.parse_args(argv)
    if a.steps < 1 or a.warmup < 0:
        p.error("--steps must be >= 1 and --warmup >= 0")
    return a


def main(argv=None):
    args = parse_args(argv)
    C.set_threads(args.threads)
    import numpy as np
    import torch

    from arraysel.objective.psf_objective import build_objective
    from arraysel.selectors.relax import cosine_temperature, gumbel_noise, sequential_selection

    dtype = torch.float32 if args.dtype == "float32" else torch.float64
    with C.Timer() as t_pre:
        obj = build_objective("paper", device=args.device, dtype=dtype)
        obj.reference_kernel()
        obj.psf.kernels_exact(torch.ones(1, obj.n_elements, dtype=dtype))  # exact-path DAS plans
    n, k = obj.n_elements, obj.k
    gen = torch.Generator(device=obj.device).manual_seed(args.seed)
    logits = (torch.randn((n, k), generator=gen, device=obj.device, dtype=dtype) * 0.01).requires_grad_(True)
    opt = torch.optim.Adam([logits], lr=args.lr)

    def step(i):
        """One training step; returns (forward s, backward s, mask)."""
        tau = cosine_temperature(i)
        with C.Timer() as tf:
            noise = None
            if args.relax == "gumbel":
                noise = gumbel_noise((n, k), gen, device=obj.device, dtype=dtype)
            rel = sequential_selection(logits, tau, noise=noise, hard=True)
            total, _ = obj.selection_loss(rel.P, rel.P_soft, step=i)
        with C.Timer() as tb:
            opt.zero_grad(set_to_none=True)
            total.backward()
            opt.step()
        return tf.s, tb.s, rel.P_hard.detach().sum(1)

    for i in range(args.warmup):
        step(i)
    fwd, bwd, masks = [], [], []
    with C.Timer() as t_all:
        for i in range(args.warmup, args.warmup + args.steps):
            f, b, m = step(i)
            fwd.append(f)
            bwd.append(b)
            masks.append(m)
    fwd, bwd = np.array(fwd), np.array(bwd)
    tot = fwd + bwd

    # which steps needed the exact path (measured after the timing, no gradients)
    fb = np.zeros(len(masks), dtype=bool)
    fast = obj.psf.basis
    if fast is not None and hasattr(fast, "kernels"):
        with torch.no_grad():
            W = torch.stack(masks).to(obj.device, dtype)
            fb = ~fast.kernels(W)[1].numpy()
    distinct = len({tuple(m.nonzero().flatten().tolist()) for m in masks})

    per_step = t_all.s / args.steps
    rows = [["precompute (load/build basis, reference, DAS plans)", f"{t_pre.s:.1f} s", ""],
            [f"{args.steps} steps ({args.relax}, {args.dtype}, {args.device})", f"{t_all.s:.2f} s",
             f"{60 / per_step:.0f} steps/min"],
            ["  forward (draw + selection_loss), median", f"{np.median(fwd) * 1e3:.1f} ms", ""],
            ["  backward + Adam, median", f"{np.median(bwd) * 1e3:.1f} ms", ""],
            ["  step, mean / median / max", f"{tot.mean() * 1e3:.1f} ms",
             f"{np.median(tot) * 1e3:.1f} / {tot.max() * 1e3:.1f} ms"],
            ["  steps on the exact fallback", f"{int(fb.sum())} / {args.steps}",
             f"median {np.median(tot[fb]) * 1e3:.0f} ms" if fb.any() else ""],
            ["  distinct masks visited", str(distinct), ""]]
    if fb.any() and (~fb).any():
        rows.append(["  certified steps only, median", f"{np.median(tot[~fb]) * 1e3:.1f} ms",
                     f"{60 / np.median(tot[~fb]):.0f} steps/min"])
    print("bench_grad: paper scene, PSF-only STE loss, k = %d of %d" % (k, n))
    print("machine:", C.machine())
    print(C.table(rows, ["step", "time", "rate / note"]))
    C.emit_json({"forward_ms": float(np.median(fwd) * 1e3), "backward_ms": float(np.median(bwd) * 1e3),
                 "step_ms": per_step * 1e3, "steps_per_min": 60 / per_step,
                 "fallback_steps": int(fb.sum()), "steps": args.steps, "relax": args.relax,
                 "dtype": args.dtype, "device": args.device, "precompute_s": t_pre.s,
                 "threads": torch.get_num_threads()})


if __name__ == "__main__":
    main()
