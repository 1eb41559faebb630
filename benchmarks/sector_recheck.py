"""Re-check selections of a sector comparison against an independent reference, on new points.

The reference is built here from PyMUST's public functions (``simus3``, ``rf2iq``, ``dasmtx3``;
PyMUST is called, never copied): the probe (``MATRIX-32x32``: 32 x 32 elements, 0.3 mm pitch,
0.25 mm square elements, 3 MHz, 70 % bandwidth, elements in row order, x fastest), the scene's
transmits (diverging waves from virtual sources ``source_distance`` behind the array centre,
steered on an ``n_tx_x`` x ``n_tx_y`` grid of tilts linspace(-max, max) in x and y, delays
``(|e - s| - min |e - s|) / c`` computed here), one point scatterer, the selection's elements
active on transmit (the others at zero transmit apodization) and on receive (the others' channels
zeroed), I/Q demodulation, delay-and-sum on a surface around the point with PyMUST's DAS matrix,
and the transmits summed coherently. The surface is the sphere of the point's range sampled on a
grid of direction cosines ``(u, v)`` that reaches ``sin(half_angle) + margin lambda0 / D`` on each
side in steps of ``lambda0 / (samples_per_lobe D)``.

The metrics are computed here too, independently of ``arraysel.objective.lobes``, as
``docs/sector.md`` defines them: the peak is the local maximum reached by climbing from the pixel
nearest the point's direction; the main lobe is read along 64 rays from the peak, uniform in
angle, sampled every half pixel (bilinear in amplitude): a ray's radius is its first null (the
lowest amplitude met before the amplitude first rises more than ``ripple_db``, 1 dB, above the
lowest met so far), at most 3 times the distance at which it first falls to -6 dB, and a pixel is
main lobe when it lies no further from the peak than the radius interpolated linearly in angle
between the rays either side (the documented rule, ``arraysel.objective.lobe_regions.MainLobeRule``'s
defaults); ``PSL_dB`` is the
strongest pixel outside it (``PSL_uncapped_dB``: outside a main lobe read along one ray through
every pixel, with no cap), ``ISLR_dB`` the energy outside over the energy inside, and the -6 dB
widths in x and y are read through the peak along the grid's rows and columns (``x = R u``,
``y = R v``), interpolated linearly in amplitude.

The same selections are scored on the same points and surfaces by arraysel itself (``--arraysel``,
the default): the scene (``run.json`` next to the selections' CSV, else the built-in
``matrix-1024-sector``) with its ``sector.points`` and ``sector.half_angle_deg`` replaced, on its
exact per-beam path (``SectorObjective.beam_metrics(..., exact=True)``).

    nice python benchmarks/sector_recheck.py \\
        --selections benchmarks/results/compare-matrix-sector/table1.csv \\
        --extra benchmarks/results/compare-matrix-sector/polished/polish.csv \\
        --configs full spiral uniform random anneal "anneal + polish" --out benchmarks/results/sector-recheck
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

#: points no issue names: (theta_x deg, theta_y deg, range mm)
DEFAULT_POINTS = "0,0,35; 0,0,95; 20,0,65; 0,-8,35; -14,14,65"
DEFAULT_CONFIGS = ("full", "spiral", "uniform", "random", "anneal", "anneal + polish")
COLUMNS = ("source", "config", "point", "theta_x_deg", "theta_y_deg", "range_mm", "PSL_dB", "PSL_uncapped_dB", "ISLR_dB",
           "width_x_mm", "width_y_mm", "seconds")


# --------------------------------------------------------------------------- input
def parse_points(text: str) -> list[tuple[float, float, float]]:
    """``"ax,ay,r; ..."`` (degrees, degrees, mm) -> [(ax, ay, r_mm)], checked."""
    out = []
    for i, item in enumerate(t for t in str(text).split(";") if t.strip()):
        parts = item.replace(" ", "").split(",")
        try:
            ax, ay, r = (float(p) for p in parts)
        except ValueError:
            raise ValueError(f"--points[{i}] = {item.strip()!r}: expected 'theta_x_deg,theta_y_deg,range_mm'") from None
        if not (abs(ax) < 80 and abs(ay) < 80 and 5.0 <= r <= 200.0):
            raise ValueError(f"--points[{i}] = {item.strip()!r}: angles must lie in (-80, 80) degrees and the range "
                             "in [5, 200] mm")
        if math.sin(math.radians(ax)) ** 2 + math.sin(math.radians(ay)) ** 2 >= 1:
            raise ValueError(f"--points[{i}] = {item.strip()!r}: the direction leaves the visible region")
        out.append((ax, ay, r))
    if not out:
        raise ValueError("--points: give at least one point 'theta_x_deg,theta_y_deg,range_mm'")
    return out


def read_selections(paths: list[Path], configs: list[str], n_elements: int) -> dict[str, np.ndarray]:
    """``{config: bool mask (Ne,)}`` of the rows named ``configs`` in CSV files with ``config`` and
    ``elements`` columns (space-separated element indices); the first file holding a name wins."""
    import pandas as pd

    found: dict[str, np.ndarray] = {}
    for path in paths:
        table = pd.read_csv(path, dtype={"elements": str}, keep_default_na=False)
        if not {"config", "elements"} <= set(table.columns):
            raise ValueError(f"{path}: a selections CSV needs the columns 'config' and 'elements'")
        for _, row in table.iterrows():
            name, text = str(row["config"]), str(row["elements"]).strip()
            if name in configs and name not in found and text:
                idx = np.array([int(t) for t in text.split()], dtype=np.int64)
                if idx.min() < 0 or idx.max() >= n_elements or len(set(idx.tolist())) != idx.size:
                    raise ValueError(f"{path}: config {name!r}: elements must be distinct indices in [0, {n_elements - 1}]")
                mask = np.zeros(n_elements, dtype=bool)
                mask[idx] = True
                found[name] = mask
    missing = [c for c in configs if c not in found]
    if missing:
        raise ValueError(f"--configs: {missing} not found (with elements) in {[str(p) for p in paths]}")
    return {c: found[c] for c in configs}


# --------------------------------------------------------------------------- geometry
def uv_grid(half: float, step: float) -> np.ndarray:
    """Direction cosines ``k step`` reaching at least ``half`` on each side, 0 on a sample."""
    n = int(math.ceil(half / step - 1e-9))
    return np.arange(-n, n + 1, dtype=np.float64) * step


def point_position(ax_deg: float, ay_deg: float, r: float) -> np.ndarray:
    u, v = math.sin(math.radians(ax_deg)), math.sin(math.radians(ay_deg))
    return r * np.array([u, v, math.sqrt(1.0 - u * u - v * v)])


def element_grid(nx: int = 32, ny: int = 32, pitch: float = 0.3e-3) -> np.ndarray:
    """Element centres (2, Ne) in row order, x fastest, centred on the origin."""
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny))
    return np.stack([(ix.ravel() - (nx - 1) / 2) * pitch, (iy.ravel() - (ny - 1) / 2) * pitch])


def surface_pixels(kind: str, point: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Pixels (Hv, Hu, 3) m of a point's surface: ``"sphere"``, the sphere of its range ``R`` at the
    direction cosines ``(u, v)``; ``"plane"``, the C-plane through the point (z = its depth) at the
    same ``x = R u``, ``y = R v``."""
    r = float(np.linalg.norm(point))
    U, V = np.meshgrid(u, v)
    if kind == "sphere":
        Z = r * np.sqrt(1.0 - U ** 2 - V ** 2)
    elif kind == "plane":
        Z = np.full(U.shape, float(point[2]))
    else:
        raise ValueError(f"--surface = {kind!r}: allowed 'sphere' or 'plane'")
    return np.stack([r * U, r * V, Z], axis=-1)


def virtual_source_delays(elements: np.ndarray, tilts_deg: list[tuple[float, float]], distance: float,
                          c: float) -> np.ndarray:
    """Delays (n_tx, Ne) s of diverging waves from sources ``distance`` behind the array centre
    opposite each steering direction."""
    out = []
    for ax, ay in tilts_deg:
        s = -point_position(ax, ay, distance)
        r = np.sqrt((elements[0] - s[0]) ** 2 + (elements[1] - s[1]) ** 2 + s[2] ** 2)
        out.append((r - r.min()) / c)
    return np.array(out)


# --------------------------------------------------------------------------- metrics
def _climb(a: np.ndarray, i: int, j: int) -> tuple[int, int]:
    """The local maximum reached from (i, j) by steepest ascent over the 8 neighbours."""
    h, w = a.shape
    while True:
        best = (a[i, j], i, j)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                p, q = i + di, j + dj
                if 0 <= p < h and 0 <= q < w and a[p, q] > best[0]:
                    best = (a[p, q], p, q)
        if best[1:] == (i, j):
            return i, j
        i, j = best[1], best[2]


def _ray_profiles(a: np.ndarray, peak: tuple[int, int], ui: np.ndarray, uj: np.ndarray):
    """Amplitude along rays from ``peak`` in directions (ui, uj) (pixel units, unit length),
    sampled every half pixel (bilinear) to the surface's edge: ``(s, prof)``, prof inf past the edge."""
    from scipy.ndimage import map_coordinates

    h, w = a.shape

    def reach(p0, u, n):
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(u > 1e-12, (n - 1 - p0) / u, np.where(u < -1e-12, -p0 / u, np.inf))

    edge = np.minimum(reach(peak[0], ui, h), reach(peak[1], uj, w))
    s = np.arange(0.0, edge.max() + 0.5, 0.5)
    valid = s[None, :] <= edge[:, None] + 1e-9
    ci = np.clip(peak[0] + ui[:, None] * s[None, :], 0, h - 1)
    cj = np.clip(peak[1] + uj[:, None] * s[None, :], 0, w - 1)
    prof = map_coordinates(a, [ci.ravel(), cj.ravel()], order=1).reshape(ci.shape)
    return s, np.where(valid, prof, np.inf)


def ray_radius(s: np.ndarray, prof: np.ndarray, ripple_db: float = 1.0, cap: float | None = 3.0) -> np.ndarray:
    """Each ray's main-lobe radius: its first null (the lowest amplitude met before the amplitude
    first rises more than ``ripple_db`` above the lowest met so far; inf when it never does),
    at most ``cap`` times the distance at which it first falls to -6 dB (interpolated linearly)."""
    low = np.minimum.accumulate(prof, axis=1)
    rises = np.zeros(prof.shape, dtype=bool)
    rises[:, 1:] = np.isfinite(prof[:, 1:]) & (prof[:, 1:] > low[:, :-1] * 10 ** (ripple_db / 20))
    has = rises.any(1)
    first = np.where(has, rises.argmax(1), prof.shape[1])
    before = np.where(np.arange(prof.shape[1])[None, :] < first[:, None], prof, np.inf)
    radius = np.where(has, s[before.argmin(1)], np.inf)
    if cap is None:
        return radius
    half = 10 ** (-6 / 20) * prof[:, :1]
    below = prof <= half
    k = np.where(below.any(1), below.argmax(1), 0)
    a0, a1 = prof[np.arange(len(k)), np.maximum(k - 1, 0)], prof[np.arange(len(k)), k]
    with np.errstate(divide="ignore", invalid="ignore"):
        r6 = np.where(below.any(1) & (k > 0), s[np.maximum(k - 1, 0)] + (a0 - half[:, 0]) / (a0 - a1) * 0.5, np.inf)
    return np.minimum(radius, cap * r6)


def main_lobe(a: np.ndarray, peak: tuple[int, int], ripple_db: float = 1.0, n_rays: int | None = 64,
              cap: float | None = 3.0) -> np.ndarray:
    """The main lobe, boolean (H, W): the pixels no further from ``peak`` than the main-lobe radius
    (:func:`ray_radius`) of their direction. ``n_rays`` rays uniform in angle, the radius
    interpolated linearly in angle between the two rays either side of a pixel (an infinite radius
    on either side: the pixel is main lobe); ``n_rays=None``: one ray through every pixel."""
    h, w = a.shape
    ii, jj = np.mgrid[0:h, 0:w]
    di, dj = (ii - peak[0]).ravel().astype(float), (jj - peak[1]).ravel().astype(float)
    dist = np.hypot(di, dj)
    far = dist > 0
    inside = np.ones(h * w, dtype=bool)
    if n_rays is None:
        s, prof = _ray_profiles(a, peak, di[far] / dist[far], dj[far] / dist[far])
        inside[far] = dist[far] <= ray_radius(s, prof, ripple_db, cap) + 1e-9
        return inside.reshape(h, w)
    theta = 2 * np.pi * np.arange(n_rays) / n_rays
    s, prof = _ray_profiles(a, peak, np.sin(theta), np.cos(theta))
    rad = ray_radius(s, prof, ripple_db, cap)
    phi = np.mod(np.arctan2(di[far], dj[far]), 2 * np.pi) / (2 * np.pi / n_rays)
    k = np.floor(phi).astype(int) % n_rays
    f = phi - np.floor(phi)
    r0, r1 = rad[k], rad[(k + 1) % n_rays]
    both = np.isfinite(r0) & np.isfinite(r1)
    r = np.where(both, (1 - f) * np.where(both, r0, 0) + f * np.where(both, r1, 0), np.inf)
    inside[far] = dist[far] <= r + 1e-9
    return inside.reshape(h, w)


def _width(profile: np.ndarray, pos: np.ndarray, k: int) -> float:
    """-6 dB width of ``profile`` through its sample ``k`` (linear in amplitude); inf if it never falls."""
    half = 10 ** (-6 / 20) * profile[k]
    ends = []
    for step in (1, -1):
        i = k
        while 0 <= i + step < len(profile) and profile[i + step] > half:
            i += step
        if not 0 <= i + step < len(profile):
            return math.inf
        a0, a1 = profile[i], profile[i + step]
        ends.append(pos[i] + (a0 - half) / (a0 - a1) * (pos[i + step] - pos[i]))
    return abs(ends[0] - ends[1])


def lobe_metrics(image: np.ndarray, u: np.ndarray, v: np.ndarray, r: float, target_uv: tuple[float, float],
                 ripple_db: float = 1.0) -> dict[str, float]:
    """PSL, ISLR (dB) and -6 dB widths in x and y (m) of a point's image (Hv, Hu) on the sphere of
    range ``r`` sampled at direction cosines ``u`` (columns), ``v`` (rows)."""
    a = np.abs(np.asarray(image))
    if not np.isfinite(a).all() or a.max() <= 0:
        raise ValueError("the image is all zero or not finite")
    i0 = int(np.argmin(np.abs(v - target_uv[1])))
    j0 = int(np.argmin(np.abs(u - target_uv[0])))
    pk = _climb(a, i0, j0)
    main = main_lobe(a, pk, ripple_db)
    p = a ** 2
    side = p[~main]
    p0 = p[pk]
    psl = 10 * math.log10(max(side.max(), 1e-24 * p0) / p0) if side.size else -240.0
    free = p[~main_lobe(a, pk, ripple_db, n_rays=None, cap=None)]
    psl_free = 10 * math.log10(max(free.max(), 1e-24 * p0) / p0) if free.size else -240.0
    islr = 10 * math.log10(max(side.sum(), 1e-24 * p0) / p[main].sum())
    return {"PSL_dB": psl, "ISLR_dB": islr, "width_x": _width(a[pk[0]], r * u, pk[1]),
            "width_y": _width(a[:, pk[1]], r * v, pk[0]), "PSL_uncapped_dB": psl_free, "peak_uv": (float(u[pk[1]]), float(v[pk[0]]))}


# --------------------------------------------------------------------------- the PyMUST reference
class PyMUSTRecheck:
    """Compound images of one point on its sphere for a batch of selections, from PyMUST."""

    def __init__(self, scene: dict, point_deg: tuple[float, float, float], u: np.ndarray, v: np.ndarray,
                 kind: str = "sphere"):
        import logging

        import pymust

        logging.getLogger().setLevel(logging.ERROR)
        self.pm = pymust
        acq, tx = scene["acquisition"], scene["transmit"]
        p = pymust.utils.Param()
        p.elements = element_grid()
        p.Nelements = p.elements.shape[1]
        p.width = p.height = 0.25e-3
        p.fc, p.bandwidth, p.baffle = 3e6, 70.0, "soft"
        p.c = float(acq.get("c", 1540.0))
        p.fs = float(acq.get("fs_over_fc", 4.0)) * p.fc
        p.TXnow = float(acq.get("tx_cycles", 1.0))
        p.attenuation = float(acq.get("attenuation", 0.0))
        self.param = p
        mx = float(tx["max_tilt_deg"])
        my = float(tx.get("max_tilt_deg_y", mx))
        tilts = [(x, y) for y in np.linspace(-my, my, int(tx["n_tx_y"])) for x in np.linspace(-mx, mx, int(tx["n_tx_x"]))]
        self.delays = virtual_source_delays(p.elements, tilts, _length(tx["source_distance"]), p.c)
        self.r = point_deg[2] * 1e-3
        self.point = point_position(point_deg[0], point_deg[1], self.r)
        xyz = surface_pixels(kind, self.point, u, v)
        self.shape = xyz.shape[:2]
        self.pixels = [np.ascontiguousarray(xyz[..., i].ravel()) for i in range(3)]

    def images(self, masks: np.ndarray) -> np.ndarray:
        """Complex images (B, Hv, Hu) of bool masks (B, Ne)."""
        pm, p = self.pm, self.param
        out = np.zeros((len(masks),) + self.shape, dtype=np.complex128)
        x, y, z = (np.array([c]) for c in self.point)
        for t, dl in enumerate(self.delays):
            iqs = []
            for m in masks:
                p.TXapodization = m.astype(np.float64).reshape(1, -1)
                rf, _ = pm.simus3(x, y, z, np.array([1.0]), dl.reshape(1, -1), p)
                iqs.append(pm.rf2iq(rf * m.reshape(1, -1), p))
            nt = max(q.shape[0] for q in iqs)
            das = pm.dasmtx3(1j * np.array([nt, p.Nelements]), *self.pixels, dl.reshape(1, -1), p).tocsr()
            for b, q in enumerate(iqs):
                q = np.vstack([q, np.zeros((nt - q.shape[0], q.shape[1]), q.dtype)])
                out[b] += (das @ q.flatten(order="F")).reshape(self.shape)
            del das
        return out


def _length(text) -> float:
    """'8.05 mm' -> 0.00805 (m); a number is metres."""
    if isinstance(text, (int, float)):
        return float(text)
    value, unit = str(text).split()
    return float(value) * {"m": 1.0, "mm": 1e-3, "um": 1e-6}[unit]


# --------------------------------------------------------------------------- arraysel
def arraysel_metrics(scene: dict, points, half_angle: float, margin: float, samples: float,
                     masks: np.ndarray, kind: str = "sphere") -> list[dict]:
    """arraysel's exact per-beam metrics of ``masks`` on ``points``: one dict (B,) per point; on
    C-planes (``kind="plane"``) its exact PSF model on those pixels and its lobe metrics."""
    import arraysel as asel
    from arraysel.objective.sector_objective import SectorObjective

    tree = {k: dict(v) if isinstance(v, dict) else v for k, v in scene.items() if k != "cysts"}
    tree["sector"] = {**tree["sector"], "points": [[ax, ay, f"{r} mm"] for ax, ay, r in points],
                      "half_angle_deg": half_angle, "margin": margin, "samples_per_lobe": samples}
    if kind == "plane":
        return _arraysel_planes(asel.load_scene(tree), masks)
    obj = SectorObjective(asel.load_scene(tree), fast=False)
    out = []
    for i in range(len(points)):
        t = time.perf_counter()
        bm = obj.beam_metrics(masks, points=[i], exact=True)
        obj.beams.exact.release(i)       # one point's exact model held at a time
        sec = (time.perf_counter() - t) / len(masks)
        out.append({"PSL_dB": bm["PSL_dB"][:, 0], "ISLR_dB": bm["ISLR_dB"][:, 0], "width_x": bm["width_x_6dB"][:, 0],
                    "width_y": bm["width_y_6dB"][:, 0], "seconds": np.full(len(masks), sec)})
    return out


def _arraysel_planes(scene, masks: np.ndarray) -> list[dict]:
    import torch

    from arraysel.objective.lobes import lobe_metrics as asel_lobes
    from arraysel.physics.volume.psf import MatrixPSF

    setup = scene.sector_setup()
    out = []
    for i, point in enumerate(setup.points):
        t = time.perf_counter()
        coords = torch.as_tensor(surface_pixels("plane", np.array(point), setup.u, setup.v))
        model = MatrixPSF(setup.point_setup(i), dtype=torch.float32, coords={"c": coords})
        with torch.no_grad():
            img = model.planes(torch.as_tensor(masks, dtype=torch.float32))["c"]
            res = asel_lobes({"c": img}, {"c": coords}, target=point,
                             terms=("PSL_dB", "ISLR_dB", "width_x_6dB", "width_y_6dB"))
        sec = (time.perf_counter() - t) / len(masks)
        out.append({"PSL_dB": res["PSL_dB"].numpy(), "ISLR_dB": res["ISLR_dB"].numpy(),
                    "width_x": res["width_x_6dB"].numpy(), "width_y": res["width_y_6dB"].numpy(),
                    "seconds": np.full(len(masks), sec)})
        del model
    return out


def load_scene_tree(selections: Path) -> tuple[dict, str]:
    """The scene of ``run.json`` next to the selections' CSV, else the built-in matrix-1024-sector."""
    run = selections.parent / "run.json"
    if run.is_file():
        return json.loads(run.read_text(encoding="utf-8"))["scene"], str(run)
    import tomllib

    import arraysel

    path = Path(arraysel.__file__).parent / "scenes" / "matrix-1024-sector.toml"
    return tomllib.loads(path.read_text(encoding="utf-8")), "built-in matrix-1024-sector"


# --------------------------------------------------------------------------- main
def _arguments(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--selections", type=Path, default=Path("benchmarks/results/compare-matrix-sector/table1.csv"),
                    help="CSV with columns config, elements (a comparison's table1.csv)")
    ap.add_argument("--extra", type=Path, nargs="*", default=[], help="more CSVs of selections (config, elements)")
    ap.add_argument("--configs", nargs="+", default=list(DEFAULT_CONFIGS), help="the rows (config names) to score")
    ap.add_argument("--points", default=DEFAULT_POINTS,
                    help=f"'theta_x_deg,theta_y_deg,range_mm; ...' (default {DEFAULT_POINTS!r}); write "
                         "--points=... when the text starts with a minus sign")
    ap.add_argument("--half-angle", type=float, default=35.0,
                    help="the surfaces' half-angle in x and y, degrees, (0, 60] (default 35)")
    ap.add_argument("--surface", choices=("sphere", "plane"), default="sphere",
                    help="each point's surface: the sphere of its range (default) or the C-plane through it "
                         "(z = its depth) over the same x = R u, y = R v")
    ap.add_argument("--margin", type=float, default=1.0, help="lobes lambda0/D past the half-angle, [0, 5]")
    ap.add_argument("--samples-per-lobe", type=float, default=3.0, help="pixels per lambda0/D, [2, 8]")
    ap.add_argument("--max-pixels", type=int, default=8000, help="refuse surfaces with more pixels than this")
    ap.add_argument("--fresh", type=int, default=0, help="fresh random selections of k elements (seed 0), [0, 16]")
    ap.add_argument("--append", action="store_true", help="add to the rows of the folder's results.csv")
    ap.add_argument("--rescore", action="store_true",
                    help="recompute the PyMUST rows' metrics from the images saved in --out (pymust_*.npy)")
    ap.add_argument("--no-pymust", action="store_true", help="leave the PyMUST reference out")
    ap.add_argument("--no-arraysel", action="store_true", help="leave arraysel's scores out")
    ap.add_argument("--out", type=Path, required=True, help="folder for results.csv and summary.csv")
    args = ap.parse_args(argv)
    for name, val, lo, hi in (("--half-angle", args.half_angle, 1e-9, 60.0), ("--margin", args.margin, 0.0, 5.0),
                              ("--samples-per-lobe", args.samples_per_lobe, 2.0, 8.0), ("--fresh", args.fresh, 0, 16)):
        if not lo <= val <= hi:
            ap.error(f"{name} = {val} is out of range [{lo:g}, {hi:g}]")
    return args


def surfaces_grid(scene: dict, half_angle: float, margin: float, samples: float) -> tuple[np.ndarray, float]:
    """The grid of direction cosines of every point's surface and its step."""
    c = float(scene["acquisition"].get("c", 1540.0))
    lobe = c / 3e6 / (31 * 0.3e-3 + 0.25e-3)
    step = lobe / samples
    half = math.sin(math.radians(half_angle)) + margin * lobe
    if 2 * half * half >= 1:
        raise ValueError(f"--half-angle {half_angle} and --margin {margin}: the surface's corners leave the visible region")
    return uv_grid(half, step), step


def main(argv=None) -> None:
    args = _arguments(argv)
    import pandas as pd

    points = parse_points(args.points)
    scene, scene_from = load_scene_tree(args.selections)
    if scene.get("probe", {}).get("name") != "MATRIX-32x32" or len(scene["probe"]) != 1:
        raise SystemExit(f"the scene's probe must be the catalogue MATRIX-32x32 (got {scene.get('probe')!r}): the "
                         "reference builds that probe itself")
    sel = read_selections([args.selections, *args.extra], args.configs, 1024)
    names, masks = list(sel), np.array(list(sel.values()))
    if args.fresh:
        from arraysel.selection import random_masks

        k = int(scene["selection"]["k"])
        names += [f"random (fresh #{j})" for j in range(args.fresh)]
        masks = np.concatenate([masks, random_masks(1024, k, args.fresh, 0).astype(bool)])
    grid, step = surfaces_grid(scene, args.half_angle, args.margin, args.samples_per_lobe)
    if grid.size ** 2 > args.max_pixels:
        raise SystemExit(f"--max-pixels: the surfaces have {grid.size ** 2} pixels ({grid.size}^2) > {args.max_pixels}")
    print(f"scene from {scene_from}; {len(names)} selections; surfaces {grid.size} x {grid.size} "
          f"(|u|, |v| <= {grid[-1]:.4f}, step {step:.4f})", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    if args.append or args.rescore:
        if (args.out / "results.csv").is_file():
            rows = [tuple(r) for r in pd.read_csv(args.out / "results.csv").reindex(columns=list(COLUMNS))
                    .itertuples(index=False)]
    if not args.no_arraysel and not args.rescore:
        t = time.perf_counter()
        for (ax, ay, r), res in zip(points, arraysel_metrics(scene, points, args.half_angle, args.margin,
                                                                   args.samples_per_lobe, masks, args.surface)):
            rows += _rows("arraysel", names, (ax, ay, r), res)
        print(f"arraysel: {time.perf_counter() - t:.0f} s", flush=True)
        _write(rows, args.out)
    for point in [] if args.no_pymust else points:
        rows = _pymust_point(args, scene, point, grid, names, masks, rows)
        _write(rows, args.out)
    print(summarise(pd.DataFrame(rows, columns=list(COLUMNS))).to_string(index=False))


def _pymust_point(args, scene, point, grid, names, masks, rows) -> list[tuple]:
    """``rows`` with the PyMUST rows of ``point`` (simulated, or, with ``--rescore``, read back
    from the folder's saved images, keeping the rows' seconds) replaced."""
    ax, ay, r = point
    path = args.out / f"pymust_{ax:g}_{ay:g}_{r:g}.npy"
    label = _rows("pymust", names, point, None)[0][2]
    old = {row[1]: row[-1] for row in rows if row[0] == "pymust" and row[2] == label}
    t = time.perf_counter()
    if args.rescore:
        if not path.is_file():
            raise SystemExit(f"--rescore: no saved images {path.name} for the point {label}")
        imgs = np.load(path)
        sec = np.array([old.get(n, np.nan) for n in names])
    else:
        imgs = PyMUSTRecheck(scene, point, grid, grid, args.surface).images(masks)
        sec = np.full(len(masks), (time.perf_counter() - t) / len(masks))
        np.save(path, np.abs(imgs).astype(np.float32))
    uv0 = (math.sin(math.radians(ax)), math.sin(math.radians(ay)))
    res = [lobe_metrics(im, grid, grid, r * 1e-3, uv0) for im in imgs]
    res = {k: np.array([m[k] for m in res]) for k in ("PSL_dB", "PSL_uncapped_dB", "ISLR_dB", "width_x", "width_y")}
    res["seconds"] = sec
    print(f"pymust {label}: {time.perf_counter() - t:.0f} s", flush=True)
    return [row for row in rows if not (row[0] == "pymust" and row[2] == label)] + _rows("pymust", names, point, res)


def _rows(source: str, names: list[str], point, res: dict | None) -> list[tuple]:
    ax, ay, r = point
    label = f"({ax:g}, {ay:g}) deg, {r:g} mm"
    if res is None:
        return [(source, "", label)]
    free = res.get("PSL_uncapped_dB", np.full(len(names), np.nan))
    return [(source, n, label, ax, ay, r, float(res["PSL_dB"][b]), float(free[b]), float(res["ISLR_dB"][b]),
             float(res["width_x"][b]) * 1e3, float(res["width_y"][b]) * 1e3, float(res["seconds"][b]))
            for b, n in enumerate(names)]


def summarise(table) -> "object":
    """Per source and selection: the worst PSL over the points, the mean -6 dB width (x and y)."""
    g = table.groupby(["source", "config"], sort=False)
    out = g.agg(worst_PSL_dB=("PSL_dB", "max"), worst_PSL_uncapped_dB=("PSL_uncapped_dB", "max"), mean_ISLR_dB=("ISLR_dB", "mean"),
                mean_width_x=("width_x_mm", "mean"), mean_width_y=("width_y_mm", "mean")).reset_index()
    out["mean_width_mm"] = (out.pop("mean_width_x") + out.pop("mean_width_y")) / 2
    return out


def _write(rows, out: Path) -> None:
    import pandas as pd

    table = pd.DataFrame(rows, columns=list(COLUMNS))
    table.to_csv(out / "results.csv", index=False, float_format="%.4f")
    summarise(table).to_csv(out / "summary.csv", index=False, float_format="%.4f")


if __name__ == "__main__":
    sys.exit(main())
