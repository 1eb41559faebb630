"""The masks of benchmarks/results/compare-matrix-1024-mux drawn with their mux-1024-4 channel groups
(masks_channels.png in each folder): python scripts/plot_channel_masks.py"""
import csv
import numpy as np
from arraysel.constraints import mux_groups
from arraysel.report.layout_plots import group_masks_figure
from arraysel.scenes import load_scene

root = "benchmarks/results/compare-matrix-1024-mux"
pos = load_scene("matrix-1024").probe().element_positions()
groups = mux_groups("mux-1024-4", 1024)
for scene in ("matrix-1024", "matrix-1024-mux"):
    rows = [r for r in csv.DictReader(open(f"{root}/{scene}/table1.csv")) if r["config"] != "full"]
    masks = np.zeros((len(rows), 1024), dtype=bool)
    for i, r in enumerate(rows):
        masks[i, [int(e) for e in r["elements"].split()]] = True
    group_masks_figure([r["config"] for r in rows], masks, pos, groups).savefig(f"{root}/{scene}/masks_channels.png")
