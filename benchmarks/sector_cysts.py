"""CR and gCNR of anechoic cysts in speckle (``docs/sector.md``, ``arraysel.objective.cysts``) for
the selections of a finished sector comparison, a few more from CSV files and fresh random ones,
with each point's image at 40 and 60 dB.

The scene is the one ``run.json`` holds, with a ``[cysts]`` section (the options below: one cyst
on every point by default). Writes ``cysts.csv`` (one row per selection and cyst), ``summary.csv``
(per selection: the mean CR and gCNR over the cysts, the worst side lobe and the mean width over
the points), ``cysts.png`` (one phantom realisation through each selection, on the point
``--show``), ``points-40dB.png`` and ``points-60dB.png``, and the folder's per-depth table
(``depths.csv``, ``depths.png``, from its ``beams.csv``).

    python benchmarks/sector_cysts.py benchmarks/results/compare-matrix-sector \\
        --extra benchmarks/results/sector-polish/continued/polish.csv --out benchmarks/results/sector-cysts

``--no-points`` leaves the points' figures out (a second cyst setting on the same selections).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def _selections(folder: Path, extras: list[Path], n_elements: int) -> tuple[list[str], list[np.ndarray]]:
    """The listed selections of ``folder``'s ``table1.csv`` and the rows of ``extras`` (CSV files
    with ``config`` and ``elements``; rows without elements, or whose config ends a baseline's name
    already listed, are left out)."""
    import pandas as pd

    from arraysel.report.tables import compare_folder
    from arraysel.selection import Selection

    _, rows, _ = compare_folder(folder, "folder")
    labels, masks = [], []
    for r in rows:
        if r.get("elements"):
            labels.append(str(r["config"]))
            masks.append(Selection.from_text(r["elements"], n_elements).mask)
    for path in extras:
        t = pd.read_csv(path, dtype={"elements": str})
        for _, r in t.iterrows():
            if isinstance(r.get("elements"), str) and r["elements"].strip() and str(r["config"]) not in labels:
                labels.append(str(r["config"]))
                masks.append(Selection.from_text(r["elements"], n_elements).mask)
    return labels, masks


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path, help="the --out folder of a finished arraysel compare on a sector scene")
    ap.add_argument("--extra", type=Path, nargs="*", default=[], help="CSV files of more selections (config, elements)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--fresh", type=int, default=4, help="fresh random selections (seed 0)")
    ap.add_argument("--radius", default="4 mm")
    ap.add_argument("--density", type=float, default=10.0)
    ap.add_argument("--realisations", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-points", action="store_true", help="leave points-*.png out")
    ap.add_argument("--points", type=int, nargs="*", default=None, help="the cysts' points (default: all)")
    ap.add_argument("--show", type=int, default=1, help="the point whose cyst cysts.png shows")
    args = ap.parse_args(argv)

    import pandas as pd

    import arraysel as asel
    from arraysel.objective.cysts import CystPhantom, CystSettings, score_cysts
    from arraysel.objective.sector_objective import SectorObjective, point_label
    from arraysel.report import point_plots as pp
    from arraysel.report.plots import save_figure
    from arraysel.report.tables import compare_folder, write_csv

    scene_dict, _, _ = compare_folder(args.folder, "folder")
    scene_dict = {**scene_dict, "cysts": {"radius": args.radius, "density": args.density,
                                          "realisations": args.realisations, "seed": args.seed,
                                          **({"points": args.points} if args.points else {})}}
    scene = asel.load_scene(scene_dict)
    obj = SectorObjective(scene)
    labels, masks = _selections(args.folder, args.extra, obj.n_elements)
    fresh = obj.fresh_random_masks(args.fresh, seed=0)
    labels += [f"random (fresh #{j})" for j in range(len(fresh))]
    masks = np.array(masks + list(fresh), dtype=bool)
    t0 = time.perf_counter()
    images = {i: obj.point_images(masks, i).detach().cpu().numpy() for i in range(obj.n_points)}
    t_img = time.perf_counter() - t0
    st = CystSettings.from_scene(scene)
    t0 = time.perf_counter()
    met = score_cysts(obj, masks, st, images=images)
    t_cyst = time.perf_counter() - t0
    bm = obj.beam_metrics(masks)
    setup = obj.setup
    pts = [(point_label(obj, i), float(np.degrees(np.arcsin(setup.direction_of(i)[0]))),
            float(np.degrees(np.arcsin(setup.direction_of(i)[1]))), setup.range_of(i)) for i in range(obj.n_points)]
    rows = [row for b, lab in enumerate(labels) for row in pp.cyst_rows(lab, "", [pts[i] for i in st.points],
                                                                        st.radius, met, b)]
    args.out.mkdir(parents=True, exist_ok=True)
    write_csv(args.out / "cysts.csv", pd.DataFrame(rows, columns=list(pp.CYSTS_COLUMNS)))
    summary = pd.DataFrame({"config": labels, "mean_CR_dB": met["CR_dB"].mean(1), "mean_gCNR": met["gCNR"].mean(1),
                            "worst_PSL_dB": bm["PSL_dB"].max(1),
                            "mean_width_mm": (bm["width_x_6dB"].mean(1) + bm["width_y_6dB"].mean(1)) / 2 * 1e3})
    write_csv(args.out / "summary.csv", summary)
    # one realisation of the cyst of point --show through each selection
    i = int(args.show)
    ph = CystPhantom(setup.u, setup.v, setup.direction_of(i), setup.range_of(i), scene.sector_geometry()["lobe"], st,
                     index=i)
    env = np.stack([ph.images(images[i][b])[0] for b in range(len(labels))])
    R = setup.range_of(i) * 1e3
    u0, v0 = setup.direction_of(i)
    ext = (setup.u[0] * R, setup.u[-1] * R, setup.v[0] * R, setup.v[-1] * R)
    j = list(st.points).index(i)
    titles = [f"{lab}\nCR {met['CR_dB'][b, j]:.1f} dB, gCNR {met['gCNR'][b, j]:.2f}" for b, lab in enumerate(labels)]
    save_figure(pp.cyst_images_figure(labels, env, ext, st.radius * 1e3, (u0 * R, v0 * R), 40.0, titles),
                args.out / "cysts.png")
    stack = np.stack([images[k] for k in range(obj.n_points)], axis=1)
    exts = [(setup.u[0] * setup.range_of(k) * 1e3, setup.u[-1] * setup.range_of(k) * 1e3,
             setup.v[0] * setup.range_of(k) * 1e3, setup.v[-1] * setup.range_of(k) * 1e3) for k in range(obj.n_points)]
    keep = [b for b, lab in enumerate(labels) if not lab.startswith("random (fresh #") or lab.endswith("#0)")]
    for dr in () if args.no_points else (40.0, 60.0):
        save_figure(pp.point_images_figure([labels[b] for b in keep], [p[0] for p in pts], stack[keep], exts, dr),
                    args.out / f"points-{dr:g}dB.png")
    if not args.no_points and (args.folder / "beams.csv").is_file():   # the folder's per-depth table
        beams = pd.read_csv(args.folder / "beams.csv")
        write_csv(args.out / "depths.csv", pp.depth_table(beams))
        save_figure(pp.depth_figure(beams), args.out / "depths.png")
    print(summary.to_string(index=False))
    print(f"images {t_img:.1f} s ({len(labels)} selections x {obj.n_points} points); cysts {t_cyst:.1f} s")


if __name__ == "__main__":
    main()
