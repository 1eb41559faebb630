"""The beam pattern (``arraysel.physics.beampattern``) against the exact 3-D PSF
(``arraysel.physics.volume.MatrixPSF``) of a small matrix probe far from the array.

Two comparisons, on an 8 x 8 cut of MATRIX-32x32 (2.1 mm aperture, far field beyond about 9 mm),
at 40 mm (``--range``):

* ``beam``: a beam focused at (0, 0, R) in transmit and receive (one focused transmit, the pixel
  at the focus and a line of pixels along the range through it) answering a scatterer moved over
  the sphere of radius R, along u (v = 0) and along the diagonal u = v. In the far field its
  value at the focus is the coherent two-way pattern times the elements' factor at the
  scatterer's direction (squared: transmit and receive), and its energy summed along the range
  line is the energy pattern times that factor to the fourth power. One exact model a direction.
* ``sector``: a point at (0, 0, R) (and one 13 degrees off axis in x, ``--off-axis``) imaged with
  5 x 5 diverging waves steered over +-30 degrees (sources 0.84 apertures behind the array, the
  published setting scaled to this aperture), its PSF on the sphere of radius R sampled in
  (u, v) on the pattern's grid around the point (an angle-sampled surface). Compounded diverging
  waves only approximate the two-way pattern (their transmit focusing comes from the spread of
  the sources, not from the aperture): this is the quality of the proxy for one point.

Printed: the Pearson correlation of the dB patterns above ``--floor-db``, the largest and median
dB difference there, and the lobe metrics (``arraysel.objective.lobes``) of both.

Usage::

    python benchmarks/beampattern_farfield.py --threads 2

The last output line is a JSON record.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from unittest import mock

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as C  # noqa: E402


def _model(setup, pixels):
    """The exact model of ``setup`` on the given pixels (H, W, 3) instead of its planes."""
    import torch

    import arraysel.physics.volume.psf as psf

    with mock.patch.object(psf, "plane_axes", lambda s: {"xy": torch.as_tensor(pixels, dtype=torch.float64)}):
        return psf.MatrixPSF(setup, dtype=torch.float64)


def _compare(a, b, floor_db: float) -> dict:
    """dB maps a, b (same shape, 0 dB at their peaks): correlation and differences above the floor."""
    import numpy as np

    keep = (a > floor_db) | (b > floor_db)
    x, y = np.maximum(a[keep], floor_db), np.maximum(b[keep], floor_db)
    d = np.abs(x - y)
    return {"pixels": int(keep.sum()), "corr_db": float(np.corrcoef(x, y)[0, 1]), "max_diff_db": float(d.max()),
            "median_diff_db": float(np.median(d))}


def beam(a, probe, acq, w) -> dict:
    import numpy as np
    import torch

    from arraysel.physics.beampattern import BeamPattern, element_factor
    from arraysel.physics.volume import MatrixPSFSetup, focused_delays3

    R = a.range
    lam = acq.c / probe.fc
    step = acq.c / probe.fc / (8 * probe.aperture[0])            # a quarter of the Nyquist step at fc
    pats = {c: BeamPattern.from_probe(probe, acq, n_freq=a.n_coherent if c == "coherent" else 16, combine=c,
                                      sector_deg=(0, 0), region="visible", step=step, dtype=torch.float64)
            for c in ("coherent", "energy")}
    bp = pats["coherent"]
    vals = {c: p.pattern(torch.as_tensor(w[None]))[0].abs() for c, p in pats.items()}
    du = bp.du.numpy()
    keep = np.nonzero(np.abs(du) <= a.extent)[0]
    delays = focused_delays3(probe, 0.0, 0.0, R, acq.c)
    zline = R + (np.arange(-32, 33) * lam / 8)
    pixels = np.stack([np.zeros_like(zline), np.zeros_like(zline), zline], -1)[None]     # (1, 65, 3)
    out = {}
    for cut in ("u", "diagonal"):
        coh, en, ref_c, ref_e = [], [], [], []
        t0 = time.perf_counter()
        for j in keep:
            u = du[j]
            v = 0.0 if cut == "u" else u
            if u * u + v * v >= 1:
                continue
            s = (R * u, R * v, R * math.sqrt(1 - u * u - v * v))
            setup = MatrixPSFSetup(probe, acq, delays, s, 1e-3, 1e-3, 1e-3, 1e-3, planes=("xy",))
            img = _model(setup, pixels).planes(torch.as_tensor(w[None]))["xy"][0, 0]
            coh.append(abs(complex(img[32])))
            en.append(float((img.abs() ** 2).sum()))
            ef = float(element_factor(torch.tensor(u), torch.tensor(v), probe.width, probe.height, probe.baffle, lam))
            i = bp.dv.numel() // 2 + (0 if cut == "u" else int(j) - bp.du.numel() // 2)
            pc = float(vals["coherent"][i, j])
            pe = float(vals["energy"][i, j])
            ref_c.append(pc * ef ** 2)
            ref_e.append(pe * ef ** 4)
        db = lambda x: 20 * np.log10(np.asarray(x) / np.max(x))  # noqa: E731
        dbp = lambda x: 10 * np.log10(np.asarray(x) / np.max(x))  # noqa: E731
        out[cut] = {"directions": len(coh), "seconds": round(time.perf_counter() - t0, 1),
                    "coherent": _compare(db(coh), db(ref_c), a.floor_db),
                    "energy": _compare(dbp(en), dbp(ref_e), a.floor_db)}
    return out


def sector(a, probe, acq, w, off_deg: float) -> dict:
    import numpy as np
    import torch

    from arraysel.objective.lobes import lobe_metrics
    from arraysel.physics.beampattern import BeamPattern, sphere_surface
    from arraysel.physics.volume import MatrixPSFSetup, diverging_delays3, tilt_grid

    R = a.range
    tx, ty = tilt_grid(5, 5, 30.0, 30.0)
    delays = diverging_delays3(probe, tx, ty, 0.84 * probe.aperture[0], acq.c)
    us = math.sin(math.radians(off_deg))
    scat = (R * us, 0.0, R * math.cos(math.radians(off_deg)))
    res = {}
    step = acq.c / probe.fc / (4 * probe.aperture[0])            # half the Nyquist step at fc
    bps = {c: BeamPattern.from_probe(probe, acq, n_freq=16 if c == "energy" else a.n_coherent, combine=c,
                                     sector_deg=(0, 0), region="visible", step=step, dtype=torch.float64)
           for c in ("energy", "coherent")}
    bp = bps["energy"]
    cu = np.abs(bp.du.numpy()) <= a.extent_sector
    cv = np.abs(bp.dv.numpy()) <= a.extent_sector
    du, dv = bp.du.numpy()[cu], bp.dv.numpy()[cv]
    U, V = np.meshgrid(du + us, dv, indexing="xy")
    ok = U * U + V * V < 0.999
    surf = sphere_surface(R, du + us, dv).numpy() if ok.all() else None
    if surf is None:
        raise SystemExit("the surface leaves the visible region: lower --extent-sector")
    t0 = time.perf_counter()
    setup = MatrixPSFSetup(probe, acq, delays, scat, 1e-3, 1e-3, 1e-3, 1e-3, planes=("xy",))
    img = _model(setup, surf).planes(torch.as_tensor(w[None]))["xy"][0]
    res["seconds"] = round(time.perf_counter() - t0, 1)
    psf_db = (10 * torch.log10(img.abs() ** 2 / (img.abs() ** 2).max())).numpy()
    coords = {"s": np.stack([np.meshgrid(du, dv)[0], np.meshgrid(du, dv)[1], np.zeros((dv.size, du.size))], -1)}
    m_psf = lobe_metrics({"s": img.abs()[None] ** 2}, coords, power=True, frame="uv", target=(0, 0, 0))
    res["psf"] = {k: round(float(v[0]), 4) for k, v in m_psf.items()}
    for comb, p in bps.items():
        pat = p.pattern(torch.as_tensor(w[None]))[0][np.ix_(cv, cu)]
        pw = pat if comb == "energy" else pat.abs() ** 2
        pat_db = (10 * torch.log10(pw / pw.max())).numpy()
        m = lobe_metrics({"s": pw[None]}, coords, power=True, frame="uv", target=(0, 0, 0))
        res[comb] = {**_compare(psf_db, pat_db, a.floor_db), **{k: round(float(v[0]), 4) for k, v in m.items()}}
    return res


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--range", type=float, default=40e-3, help="distance of the point (m, default 0.04)")
    p.add_argument("--extent", type=float, default=0.8, help="largest |du| of the beam scans (default 0.8)")
    p.add_argument("--extent-sector", type=float, default=0.55,
                   help="largest |du|, |dv| of the sector PSF surfaces (default 0.55)")
    p.add_argument("--floor-db", type=float, default=-40.0, help="dB floor of the comparison (default -40)")
    p.add_argument("--n-coherent", type=int, default=128, help="frequencies of the coherent pattern (default 128)")
    p.add_argument("--off-axis", type=float, default=13.0, help="angle in x of the second point (deg, default 13)")
    p.add_argument("--parts", default="beam,sector", help="beam, sector or both (default)")
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args(argv)
    C.set_threads(a.threads)
    import numpy as np

    from arraysel.physics.probes import Acquisition, get_probe

    probe = get_probe("MATRIX-32x32", nx=8, ny=8)
    acq = Acquisition.for_probe(probe)
    rng = np.random.default_rng(0)
    masks = {"full": np.ones(64)}
    sparse = np.zeros(64)
    sparse[rng.choice(64, 24, replace=False)] = 1
    masks["random 24 of 64"] = sparse
    out = {}
    for name, w in masks.items():
        if "beam" in a.parts:
            out[f"beam {name}"] = r = beam(a, probe, acq, w)
            for cut, v in r.items():
                for comb in ("coherent", "energy"):
                    c = v[comb]
                    print(f"beam scan, {name}, along {cut}, {comb}: {v['directions']} directions, corr of dB "
                          f"{c['corr_db']:.4f}, |diff| max {c['max_diff_db']:.2f} dB, "
                          f"median {c['median_diff_db']:.3f} dB")
        if "sector" in a.parts:
            for off in (0.0, a.off_axis):
                out[f"sector {name} {off:g} deg"] = r = sector(a, probe, acq, w, off)
                print(f"sector PSF, {name}, point at {off:g} deg: PSF "
                      + ", ".join(f"{k} {v:.4g}" for k, v in r["psf"].items()))
                for comb in ("energy", "coherent"):
                    c = r[comb]
                    print(f"   {comb} pattern: corr of dB {c['corr_db']:.3f}, |diff| max {c['max_diff_db']:.1f} dB, "
                          f"median {c['median_diff_db']:.2f} dB; " + ", ".join(
                              f"{k} {c[k]:.4g}" for k in ("PSL_dB", "ISLR_dB", "width_u_6dB", "width_v_6dB")))
    info = C.machine()
    print(json.dumps({"results": out, "machine": info}))


if __name__ == "__main__":
    main()
