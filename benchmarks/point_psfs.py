"""The PSFs of each field point of a finished comparison, for scenes with several points.

``arraysel compare`` draws ``psfs.png`` and ``profiles.png`` for a one-point scene; for a scene
with several field points (``medium.points``) this script draws them per point from the
selections ``table1.csv`` lists (each selector's best run), with the full array's first:
``psfs_p<i>.png`` and ``profiles_p<i>.png`` in the folder (or ``--out``). Not a timing
benchmark; it scores nothing but the listed selections.

    python benchmarks/point_psfs.py benchmarks/results/compare-p4-2v-depths
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path, help="the --out folder of a finished arraysel compare")
    ap.add_argument("--out", type=Path, default=None, help="where the figures go (default: the folder)")
    args = ap.parse_args(argv)
    out = args.out or args.folder

    import numpy as np
    import pandas as pd

    import arraysel as asel
    from arraysel.report import plots
    from arraysel.selection import Selection

    scene = json.loads((args.folder / "run.json").read_text(encoding="utf-8"))["scene"]
    obj = asel.build_objective(asel.load_scene(scene))
    table = pd.read_csv(args.folder / "table1.csv", keep_default_na=False)
    rows = table[(table["config"] != "full") & (table["elements"] != "")]
    labels = list(rows["config"])
    masks = np.array([Selection.from_text(t, obj.n_elements).mask for t in rows["elements"]], dtype=bool)
    pitch = obj.setup.pitch
    for point in range(obj.n_points):
        kern = obj.kernels(masks, point=point).cpu().numpy()
        ref = obj.reference_kernel(point=point).cpu().numpy()
        plots.save_figure(plots.psfs_figure(labels, kern, ref, pitch), out / f"psfs_p{point}.png")
        plots.save_figure(plots.profiles_figure(labels, kern, ref, pitch), out / f"profiles_p{point}.png")
        print(f"wrote {out / f'psfs_p{point}.png'} and profiles_p{point}.png")


if __name__ == "__main__":
    main()
