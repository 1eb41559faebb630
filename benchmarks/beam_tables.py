"""Per-beam tables of a finished comparison: ``beams.csv``, ``pareto.csv`` and ``pareto.png`` from
the selections a folder's ``table1.csv`` lists (each configuration's best run), for a folder
written before its scene was read per beam, or with the scene read per beam now.

The scene is the one ``run.json`` holds; a 1-D scene is scored with ``metrics.per_beam`` set (each
point's main lobe from its own PSF, ``docs/sector.md``), a sector scene as ``compare`` scores it.
Only the listed selections are scored (and ``--fresh`` fresh random ones), so the Pareto front is
that of the listed selections, not of every run as ``compare`` draws it.

    python benchmarks/beam_tables.py benchmarks/results/compare-p4-2v-depths
"""
from __future__ import annotations

import argparse
from pathlib import Path


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path, help="the --out folder of a finished arraysel compare")
    ap.add_argument("--out", type=Path, default=None, help="where the files go (default: the folder)")
    ap.add_argument("--fresh", type=int, default=16, help="fresh random selections for the median rows")
    args = ap.parse_args(argv)
    out = args.out or args.folder

    import arraysel as asel
    from arraysel.report.beams import pareto_figure
    from arraysel.report.plots import save_figure
    from arraysel.report.tables import compare_folder, write_csv
    from arraysel.run.sector_report import beam_source, sector_tables
    from arraysel.selection import Selection

    scene, rows, _ = compare_folder(args.folder, "folder")
    if "sector" not in scene:
        scene = {**scene, "metrics": {**scene.get("metrics", {}), "per_beam": True, "fresh_random": args.fresh}}
    obj = asel.build_objective(asel.load_scene(scene))
    source = beam_source(obj)
    for r in rows:
        r["elements"] = Selection.from_text(r["elements"], obj.n_elements) if r.get("elements") else None
        r["Mean"] = float(r["Mean"]) if r.get("Mean") not in (None, "") else float("nan")
    beams, pareto = sector_tables(source, rows)
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "beams.csv", beams)
    write_csv(out / "pareto.csv", pareto)
    save_figure(pareto_figure(pareto), out / "pareto.png")
    print(beams.to_string(index=False))
    print(f"wrote {out / 'beams.csv'}, pareto.csv, pareto.png")


if __name__ == "__main__":
    main()
