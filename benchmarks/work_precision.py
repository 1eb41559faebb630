"""Work-precision report of the simulator's accuracy settings (error against run time).

Reference: the exact path (``PSFModel(fast=False).kernels_exact``: simulator
-> RF -> I/Q -> DAS on the whole grid) in float64 with the default
:class:`~arraysel.physics.simus.SimOptions`. Every other setting changes one knob
from that default and is scored by the SI-MSE of its kernels against the
reference, for 4 fixed masks (the uniform 32-of-64 array and 3 random ones;
the table reports the largest), and by its time per mask:

* ``db_thresh`` -60 / -40 / -20 dB, ``element_splitting`` 1 / 2 / 4
  (``auto`` is the default), ``frequency_step`` 1.5: exact path, float64,
  so the error is that of the knob alone;
* ``dtype`` float32: exact path, default options;
* precomputation strategy: the fast path (``PSFModel(fast=True).kernels``,
  default options) in each ``--fast-dtypes``; its time per mask is the
  batched time (``--fast-batch`` random 32-of-64 masks, after one warm-up
  batch) and its one-off precompute is reported separately (loaded from
  ``$ARRAYSEL_CACHE`` when present);
* ``rank_tol`` of the fast path's truncated SVD (``--fast-ranks``), float32:
  truncations of the one stored basis, each with its widened error bounds. ``--fast-knobs`` also runs every knob setting on the fast
  path (one precompute each: minutes per setting).

For the exact path, ``setup_s`` is the model construction plus the first
mask (which builds the whole-grid DAS plans); the time per mask is that of
the 4 scored masks in one batch afterwards.

Usage::

    python benchmarks/work_precision.py [--out benchmarks/results/work_precision.csv]
        [--fast-dtypes float32[,float64]] [--fast-knobs] [--threads N]

Writes the CSV, a log-log PNG next to it (``--plot``), prints a table and a
JSON line summarising the run.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import gc
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as C  # noqa: E402

#: one knob at a time from the default: (knob, label, SimOptions overrides)
KNOBS = [
    ("db_thresh", "-60 dB", {"db_thresh": -60.0}),
    ("db_thresh", "-40 dB", {"db_thresh": -40.0}),
    ("db_thresh", "-20 dB", {"db_thresh": -20.0}),
    ("element_splitting", "1", {"element_splitting": 1}),
    ("element_splitting", "2", {"element_splitting": 2}),
    ("element_splitting", "4", {"element_splitting": 4}),
    ("frequency_step", "1.5", {"frequency_step": 1.5}),
]
FIELDS = ["knob", "value", "path", "dtype", "max_si_mse", "median_si_mse", "s_per_mask", "setup_s",
          "n_freq", "n_time", "n_sub", "precompute_source"]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=os.path.join(C.HERE, "results", "work_precision.csv"), help="CSV file")
    p.add_argument("--plot", default=None, help="PNG file (default: the CSV's name with .png)")
    p.add_argument("--fast-dtypes", default="float32",
                   help="comma-separated dtypes of the fast-path rows (default float32; float64 needs its own "
                        "precompute)")
    p.add_argument("--fast-knobs", action="store_true",
                   help="also run every knob setting on the fast path (float32; one precompute per setting)")
    p.add_argument("--fast-batch", type=int, default=256,
                   help="random 32-of-64 masks in the fast-path timing batch (default 256)")
    p.add_argument("--fast-ranks", default="1e-7,3e-7,1e-6,3e-6",
                   help="comma-separated rank_tol values of the fast path's truncated SVD, float32 "
                        "(truncations of one stored basis; default 1e-7,3e-7,1e-6,3e-6)")
    p.add_argument("--seed", type=int, default=1, help="seed of the 3 random masks")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--replot", action="store_true", help="only redraw the PNG from an existing --out CSV")
    a = p.parse_args(argv)
    a.fast_dtypes = [d for d in a.fast_dtypes.split(",") if d]
    for d in a.fast_dtypes:
        if d not in ("float32", "float64"):
            p.error(f"--fast-dtypes: {d!r} is not float32 or float64")
    if a.fast_batch < 1:
        p.error("--fast-batch must be >= 1")
    try:
        a.fast_ranks = [float(v) for v in a.fast_ranks.split(",") if v.strip()]
    except ValueError:
        p.error(f"--fast-ranks: {a.fast_ranks!r} is not a comma-separated list of numbers")
    if any(not 0 < v < 1 for v in a.fast_ranks):
        p.error("--fast-ranks: every rank_tol must lie in (0, 1)")
    return a


def main(argv=None):
    args = parse_args(argv)
    if args.replot:
        with open(args.out, newline="") as fh:
            rows = [{k: (float(v) if k in ("max_si_mse", "median_si_mse", "s_per_mask", "setup_s") else v)
                     for k, v in r.items()} for r in csv.DictReader(fh)]
        plot = args.plot or os.path.splitext(args.out)[0] + ".png"
        make_plot(rows, plot)
        print(f"wrote {plot}")
        return
    C.set_threads(args.threads)
    import numpy as np
    import torch

    from arraysel.physics.psf import PSFModel
    from arraysel.scenes.schema import load_scene
    from arraysel.physics.simus import SimOptions, n_subelements

    dtypes = {"float32": torch.float32, "float64": torch.float64}
    base = load_scene("paper").psf_setup()
    masks = np.vstack([C.uniform_mask()[None], C.random_masks(3, seed=args.seed)])
    W = torch.as_tensor(masks)

    def describe(setup, model):
        t = model.transmits[len(model.transmits) // 2]
        p = setup.probe
        return dict(n_freq=int(t.grid.f.numel()), n_time=int(t.grid.n_time),
                    n_sub=n_subelements(p.width, p.fc, p.bandwidth, setup.acq.c, setup.options))

    def run_exact(setup, dtype):
        with C.Timer() as t_setup:
            model = PSFModel(setup, dtype=dtype, fast=False)
            model.kernels_exact(W[:1])
        with torch.no_grad(), C.Timer() as t_run:
            k = model.kernels_exact(W)
        info = describe(setup, model)
        del model
        gc.collect()
        return k.to(torch.complex128).numpy(), t_run.s / len(W), t_setup.s, info

    batch = torch.as_tensor(C.random_masks(args.fast_batch, seed=args.seed + 1000))

    def time_fast(model, dtype):
        with torch.no_grad():
            model.kernels(batch.to(dtype))  # warm-up: first-call allocations, block DAS plans
            with C.Timer() as t_run:
                model.kernels(batch.to(dtype))
            k = model.kernels(W)
        return k.to(torch.complex128).numpy(), t_run.s / len(batch)

    def run_fast(setup, dtype, rank_tols=()):
        before = C.cache_files()
        with C.Timer() as t_setup:
            model = PSFModel(setup, dtype=dtype, fast=True)
        source = C.basis_source(before)
        info = dict(describe(setup, model), precompute_source=source)
        k, s_mask = time_fast(model, dtype)
        ranked = []
        full = model.basis.finer or model.basis
        for tol in rank_tols:
            model.basis = full.truncated(full.rank_for(tol))
            kr, sr = time_fast(model, dtype)
            ranked.append((f"{tol:g} (rank {model.basis.rank})", kr, sr))
        del model
        gc.collect()
        return k, s_mask, t_setup.s, info, ranked

    rows = []

    def record(knob, value, path, dtype_name, kern, s_mask, setup_s, info, ref):
        errs = [C.si_mse(kern[i], ref[i]) for i in range(len(W))] if ref is not None else [0.0] * len(W)
        row = dict(knob=knob, value=value, path=path, dtype=dtype_name, max_si_mse=max(errs),
                   median_si_mse=float(np.median(errs)), s_per_mask=s_mask, setup_s=setup_s,
                   precompute_source=info.pop("precompute_source", ""), **info)
        rows.append(row)
        print(f"  {knob:<18} {value:<8} {path:<5} {dtype_name:<7} max SI-MSE {row['max_si_mse']:.2e}  "
              f"{s_mask:.4g} s/mask  setup {setup_s:.1f} s", flush=True)

    print("work_precision: paper scene; reference = exact path, float64, default SimOptions", flush=True)
    ref, s_mask, setup_s, info = run_exact(base, torch.float64)
    record("reference", "default", "exact", "float64", ref, s_mask, setup_s, info, None)
    k, s_mask, setup_s, info = run_exact(base, torch.float32)
    record("dtype", "float32", "exact", "float32", k, s_mask, setup_s, info, ref)
    for knob, value, over in KNOBS:
        setup = dataclasses.replace(base, options=dataclasses.replace(SimOptions(), **over))
        k, s_mask, setup_s, info = run_exact(setup, torch.float64)
        record(knob, value, "exact", "float64", k, s_mask, setup_s, info, ref)
    for name in args.fast_dtypes:
        tols = args.fast_ranks if name == "float32" else ()
        k, s_mask, setup_s, info, ranked = run_fast(base, dtypes[name], tols)
        record("precompute", "fast", "fast", name, k, s_mask, setup_s, info, ref)
        for value, kr, sr in ranked:
            record("rank_tol", value, "fast", name, kr, sr, 0.0, dict(info), ref)
    if args.fast_knobs:
        for knob, value, over in KNOBS:
            setup = dataclasses.replace(base, options=dataclasses.replace(SimOptions(), **over))
            k, s_mask, setup_s, info, _ = run_fast(setup, torch.float32)
            record(knob, value, "fast", "float32", k, s_mask, setup_s, info, ref)

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w", newline="") as fh:
        wr = csv.DictWriter(fh, fieldnames=FIELDS)
        wr.writeheader()
        for r in rows:
            wr.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    plot = args.plot or os.path.splitext(args.out)[0] + ".png"
    make_plot(rows, plot)

    print()
    print(C.table([[r["knob"], r["value"], r["path"], r["dtype"], f"{r['max_si_mse']:.2e}",
                    f"{r['s_per_mask']:.4g}", f"{r['setup_s']:.1f}", r["n_freq"], r["n_sub"]] for r in rows],
                  ["knob", "value", "path", "dtype", "max SI-MSE", "s/mask", "setup s", "n_freq", "n_sub"]))
    print("machine:", C.machine())
    print(f"wrote {args.out} and {plot}")
    C.emit_json({"csv": args.out, "png": plot, "settings": len(rows),
                 "reference_s_per_mask": rows[0]["s_per_mask"],
                 "fast_float32_s_per_mask": next((r["s_per_mask"] for r in rows
                                                  if r["path"] == "fast" and r["knob"] == "precompute"
                                                  and r["dtype"] == "float32"), None),
                 "fast_float32_max_si_mse": next((r["max_si_mse"] for r in rows
                                                  if r["path"] == "fast" and r["knob"] == "precompute"
                                                  and r["dtype"] == "float32"), None)})


def make_plot(rows, path, floor=1e-16):
    """Log-log scatter of max SI-MSE against seconds per mask; errors below ``floor`` drawn at it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    style = {"reference": ("k", "*"), "dtype": ("tab:purple", "s"), "db_thresh": ("tab:blue", "o"),
             "element_splitting": ("tab:green", "^"), "frequency_step": ("tab:orange", "D"),
             "precompute": ("tab:red", "P"), "rank_tol": ("tab:brown", "v")}
    fig, ax = plt.subplots(figsize=(7.5, 5))
    seen = set()
    at_floor = []
    nth: dict = {}
    for r in rows:
        color, marker = style.get(r["knob"], ("gray", "x"))
        if r["path"] == "fast" and r["knob"] not in ("precompute", "rank_tol"):
            marker = "x"
        y = max(r["max_si_mse"], floor)
        label = r["knob"] if r["knob"] not in seen else None
        seen.add(r["knob"])
        ax.scatter(r["s_per_mask"], y, c=color, marker=marker, s=70, label=label, zorder=3)
        prefix = {"element_splitting": "split ", "frequency_step": "df x", "db_thresh": "",
                  "rank_tol": "rank_tol "}.get(r["knob"], "")
        text = f"{r['path']} path, {r['dtype']}" + (" (reference)" if r["knob"] == "reference" else "") \
            if r["knob"] in ("precompute", "dtype", "reference") \
            else prefix + f"{r['value']}" + (" (fast)" if r["path"] == "fast" and r["knob"] != "rank_tol" else "")
        if y <= floor:  # one shared label for the points drawn at the floor (see below)
            at_floor.append((r["s_per_mask"], text))
            continue
        nth[r["knob"]] = nth.get(r["knob"], -1) + 1  # alternate above / below within a knob
        if r["knob"] == "rank_tol":  # a tight cluster: labels fanned out to the right, with leaders
            ax.annotate(text, (r["s_per_mask"], y), textcoords="axes fraction",
                        xytext=(0.16, 0.52 - 0.045 * nth["rank_tol"]), fontsize=7, va="center",
                        arrowprops=dict(arrowstyle="-", lw=0.4, color="gray"))
            continue
        if r["knob"] in ("precompute", "dtype"):
            left = r["knob"] == "precompute"
            ax.annotate(text, (r["s_per_mask"], y), textcoords="offset points", xytext=(4 if left else -6, 10),
                        ha="left" if left else "right", fontsize=8)
            continue
        ax.annotate(text, (r["s_per_mask"], y), textcoords="offset points",
                    xytext=(6, 4) if nth[r["knob"]] % 2 == 0 else (6, -12), fontsize=8)
    if at_floor:
        x_min = min(x for x, _ in at_floor)
        ax.annotate("at the floor (error < %g): " % floor + ", ".join(t for _, t in at_floor), (x_min, floor),
                    textcoords="offset points", xytext=(-8, -14), ha="right", fontsize=8)
        ax.set_ylim(bottom=floor / 30)
    ax.set_ylim(top=30 * max(max(r["max_si_mse"], floor) for r in rows))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.axhline(floor, color="gray", lw=0.6, ls=":")
    ax.set_xlabel("time per mask (s), CPU")
    ax.set_ylabel("max SI-MSE vs exact float64 reference (4 masks)")
    ax.set_title(f"Work-precision of the simulator settings (paper scene)\n"
                 f"errors below {floor:g} drawn at {floor:g}; the reference is exact float64", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
