"""Ablation of the end-to-end training (issue 15): which selection reconstructs best?

For each seed, one ``arraysel train --scene paper-e2e`` run (the quick profile,
the library call :func:`arraysel.e2e.pipeline.run_training`) with two more
selections scored and reconstructed like its baselines:

* ``ste``: the PSF-only ``ste`` selector's result for that seed,
* ``best_random``: the best of N random selections (the ``random`` selector
  under the same time budget, N = its number of evaluations),

both read from an ``arraysel compare --selectors ste,random`` folder
(``--psf-dir``; made first when it does not exist). Every selection gets a
fresh reconstructor (same initialisation, same batches, ``recon_steps``
steps), so the rows differ by the selection alone. Then the rows are
aggregated over the seeds (mean and sample standard deviation) into
``ablation.csv`` and ``ablation.md`` in ``--out``.

Commands (docs/training.md)::

    arraysel compare --selectors ste,random --seeds 0,1,2 --budget-s 120 \\
        --out runs/ablation_psf --no-figures
    python benchmarks/e2e_ablation.py --seeds 0 --out runs/e2e_ablation   # one process per seed,
    python benchmarks/e2e_ablation.py --seeds 1 --out runs/e2e_ablation   # in parallel if cores allow
    python benchmarks/e2e_ablation.py --seeds 2 --out runs/e2e_ablation
    python benchmarks/e2e_ablation.py --aggregate --seeds 0,1,2 --out runs/e2e_ablation
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import subprocess
import sys

ROWS = ("learned", "ste", "uniform", "random", "best_random", "full")
LABELS = {"learned": "learned end to end", "ste": "PSF-only `ste` + reconstructor",
          "uniform": "uniform", "random": "random (one draw)", "best_random": "best-of-N random",
          "full": "full (64 elements)"}


def psf_masks(psf_dir: str, seed: int) -> dict[str, list[int]]:
    with open(os.path.join(psf_dir, "runs.csv")) as fh:
        rows = list(csv.DictReader(fh))
    out, evals = {}, {}
    for r in rows:
        if r["selector"] in ("ste", "random") and r["seed"] == str(seed) and not r["error"]:
            name = "ste" if r["selector"] == "ste" else "best_random"
            out[name] = [int(v) for v in r["elements"].split()]
            evals[name] = int(float(r["evaluations"]))
    missing = {"ste", "best_random"} - set(out)
    if missing:
        raise SystemExit(f"{psf_dir}/runs.csv has no {sorted(missing)} row for seed {seed}")
    print(f"seed {seed}: best_random is the best of {evals['best_random']} random selections; "
          f"ste used {evals['ste']} evaluations")
    return out


def run_seed(seed: int, out: str, psf_dir: str) -> None:
    from arraysel.e2e.pipeline import run_training

    if not os.path.isfile(os.path.join(psf_dir, "runs.csv")):
        subprocess.run([sys.executable, "-m", "arraysel.cli.main", "compare", "--selectors", "ste,random",
                        "--seeds", "0,1,2", "--budget-s", "120", "--out", psf_dir, "--no-figures",
                        "--no-progress"], check=True)
    run_training("paper-e2e", out_dir=os.path.join(out, f"seed{seed}"), seed=seed,
                 extra_masks=psf_masks(psf_dir, seed))


def _read(path: str) -> dict[str, dict[str, str]]:
    with open(path) as fh:
        return {r["config"]: r for r in csv.DictReader(fh)}


def _ms(vals: list[float], fmt: str) -> str:
    m = sum(vals) / len(vals)
    sd = math.sqrt(sum((v - m) ** 2 for v in vals) / (len(vals) - 1)) if len(vals) > 1 else 0.0
    return f"{m:{fmt}} ± {sd:{fmt}}"


def aggregate(seeds: list[int], out: str) -> str:
    cols = [("Mean", "table1", "Mean", ".4f"), ("PSNR (dB)", "rec", "psnr", ".2f"),
            ("SSIM", "rec", "ssim", ".3f"), ("blurred PSNR (dB)", "rec", "psnr_blurred", ".2f"),
            ("blurred SSIM", "rec", "ssim_blurred", ".3f")]
    data = {s: {"table1": _read(os.path.join(out, f"seed{s}", "table1.csv")),
                "rec": _read(os.path.join(out, f"seed{s}", "reconstruction.csv"))} for s in seeds}
    lines = ["| selection | " + " | ".join(c[0] for c in cols) + " |",
             "|---" * (len(cols) + 1) + "|"]
    rows = []
    for name in ROWS:
        cells, row = [], {"config": name}
        for label, table, key, fmt in cols:
            vals = [float(data[s][table][name][key]) for s in seeds]
            cells.append(_ms(vals, fmt))
            row[key] = cells[-1]
        lines.append(f"| {LABELS[name]} | " + " | ".join(cells) + " |")
        rows.append(row)
    per_seed = ["", "Per seed (learned vs uniform vs one-draw random: Mean / PSNR / SSIM):", ""]
    for s in seeds:
        t, r = data[s]["table1"], data[s]["rec"]
        per_seed.append(f"- seed {s}: " + "; ".join(
            f"{n} {float(t[n]['Mean']):.4f} / {float(r[n]['psnr']):.2f} dB / {float(r[n]['ssim']):.3f}"
            for n in ("learned", "uniform", "random")))
    text = "\n".join(lines + per_seed) + "\n"
    with open(os.path.join(out, "ablation.md"), "w") as fh:
        fh.write(f"seeds {','.join(map(str, seeds))}, mean ± sd\n\n" + text)
    with open(os.path.join(out, "ablation.csv"), "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return text


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--out", default="runs/e2e_ablation")
    p.add_argument("--psf-dir", default="runs/ablation_psf")
    p.add_argument("--aggregate", action="store_true", help="only aggregate the seeds' folders")
    a = p.parse_args(argv)
    seeds = [int(s) for s in a.seeds.split(",")]
    if not a.aggregate:
        for s in seeds:
            run_seed(s, a.out, a.psf_dir)
    print(aggregate(seeds, a.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
