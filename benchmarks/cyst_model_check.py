"""Check the cysts' locally shift-invariant model (``arraysel.objective.cysts``) against a full
simulation, on a matrix probe small enough to simulate every scatterer.

The probe is ``MATRIX-32x32`` cut to 16 x 16 elements (k = 64 of 256), 3 x 3 diverging waves over
+-20 degrees, points at 20 mm on the axis and 10 degrees off it in x. For each point and selection:

* the model: the cyst phantom convolved with the point's exact PSF on its surface, ``--model``
  seeded realisations (``CystPhantom.metrics``);
* the full simulation: scatterers at uniform random directions over the same shifts (inside the
  visible region, outside the cyst, ``density`` per resolution cell, Gaussian amplitudes), at
  random ranges within a quarter wavelength of the point's (the echo's phase uniform), every
  one's echo simulated (SIMUS3), demodulated and beamformed onto the point's surface, the
  transmits summed: ``--full`` realisations.

The first lines check the full pipeline on the point alone against the scene's exact PSF.

    python benchmarks/cyst_model_check.py --out benchmarks/results/sector-cysts/model-check
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

TREE = {"name": "cyst-check", "probe": {"name": "MATRIX-32x32", "nx": 16, "ny": 16},
        "acquisition": {"fs_over_fc": 4.0},
        "transmit": {"n_tx_x": 3, "n_tx_y": 3, "max_tilt_deg": 20.0, "max_tilt_deg_y": 20.0,
                     "source_distance": "4 mm"},
        "sector": {"points": [[0.0, 0.0, "20 mm"], [10.0, 0.0, "20 mm"]], "samples_per_lobe": 3.0, "margin": 1.0,
                   "n_freq": 4, "fresh_random": 2},
        "cysts": {"radius": "2.7 mm", "density": 10.0, "realisations": 16},
        "selection": {"k": 64}, "weights": {"L_PSF": 10.0}}


def full_images(obj, i: int, masks: np.ndarray, pts: np.ndarray, amps: np.ndarray, chunk: int = 150) -> np.ndarray:
    """The compound images (B, H, W) on point ``i``'s surface of scatterers ``pts`` (N, 3) with
    amplitudes ``amps`` (N,), every echo simulated: SIMUS3, I/Q, DAS, the transmits summed. Every
    transmit is simulated on one frequency grid (the finest of the transmits'), so that the
    elements' responses to a scatterer are formed once for all transmits."""
    from arraysel.physics.beamform import das_apply, iq_matrix
    from arraysel.physics.simus import spectra_to_rf
    from arraysel.physics.volume.beamform import das_plan3
    from arraysel.physics.volume.simus import element_responses3, grid_for_points3, rx_spectra3

    st = obj.setup
    probe, acq = st.probe, st.acq
    pix = st.surface(i).reshape(-1, 3)
    H, W = st.v.size, st.u.size
    w = torch.as_tensor(masks, dtype=torch.float64)
    P = torch.as_tensor(pts, dtype=torch.float64)
    rc = torch.as_tensor(amps, dtype=torch.float64)
    bw = probe.bandwidth if st.iq_bandwidth is None else st.iq_bandwidth
    delays = [torch.as_tensor(d, dtype=torch.float64) for d in st.delays]
    grid = max((grid_for_points3(P, d, probe, acq, st.options) for d in delays), key=lambda g: (g.n_fft, g.n_time))
    f = grid.f
    spectra = [0] * len(delays)
    for a in range(0, len(P), chunk):
        resp = element_responses3(P[a:a + chunk], f, probe, acq.c, acq.attenuation, st.options)
        if a == 0:   # the batched products below are rx_spectra3's
            ref = rx_spectra3(resp, rc[:chunk], f, delays[0], w, w, probe, acq.tx_cycles)
            got = _spectra(resp.permute(2, 0, 1).contiguous(), rc[:chunk], f, delays[0], w, probe, acq.tx_cycles)
            assert torch.allclose(got, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max())), "batched spectra"
        resp_f = resp.permute(2, 0, 1).contiguous()                 # (F, P, Ne)
        for n, d in enumerate(delays):
            spectra[n] = spectra[n] + _spectra(resp_f, rc[a:a + chunk], f, d, w, probe, acq.tx_cycles)
    out = 0
    for n, d in enumerate(delays):
        rf = spectra_to_rf(spectra[n], grid)                    # (B, Ne, n_t)
        n_t = rf.shape[-1]
        Q = iq_matrix(n_t, acq.fs, probe.fc, bw)
        iq = torch.einsum("st,bet->bes", Q, rf.to(torch.complex128))
        plan = das_plan3(pix, st.delays[n], probe, acq.fs, acq.c, n_t, probe.fc)
        out = out + das_apply(iq, plan.i0, plan.w, plan.rot)
    return out.reshape(-1, H, W).numpy()


def _spectra(resp_f, rc, f, delays, w, probe, tx_cycles) -> torch.Tensor:
    """``rx_spectra3(resp, rc, f, delays, w, w, ...)`` (B, Ne, F) as two batched matrix products
    over the frequencies, from ``resp_f`` (F, P, Ne), the responses with frequency first."""
    from arraysel.physics.simus import probe_response, pulse_spectrum

    cdt = resp_f.dtype
    om = 2 * math.pi * f.to(torch.float64)
    steer = torch.polar(torch.ones_like(delays[:, None] * om), delays[:, None] * om)      # (Ne, F)
    wt = (w.to(cdt)[:, :, None] * steer[None]).permute(2, 1, 0)                            # (F, Ne, B)
    tx = torch.bmm(resp_f, wt)                                                             # (F, P, B)
    H = probe_response(f, probe.fc, probe.bandwidth).to(torch.float64)
    pulse = pulse_spectrum(f, probe.fc, tx_cycles).to(cdt)
    tx = tx * (pulse * H)[:, None, None] * rc.to(cdt)[None, :, None]
    rx = torch.bmm(tx.transpose(1, 2), resp_f) * H[:, None, None]                         # (F, B, Ne)
    return rx.permute(1, 2, 0) * w.to(cdt)[:, :, None]


def phantom(ph, lam: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One realisation of the full simulation's phantom for :class:`CystPhantom` ``ph``."""
    H, W = ph.v.size, ph.u.size
    hu, hv = (W - 1) * ph.du, (H - 1) * ph.dv
    area = 4 * hu * hv
    n = rng.poisson(ph.per_sample * area / abs(ph.du * ph.dv))
    u = ph.centre[0] + rng.uniform(-hu, hu, n)
    v = ph.centre[1] + rng.uniform(-hv, hv, n)
    keep = (u * u + v * v < 1) & (ph.range * np.hypot(u - ph.centre[0], v - ph.centre[1]) > ph.settings.radius)
    u, v = u[keep], v[keep]
    r = ph.range + rng.uniform(-lam / 4, lam / 4, u.size)
    pts = np.stack([r * u, r * v, r * np.sqrt(1 - u * u - v * v)], 1)
    return pts, rng.standard_normal(u.size)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--full", type=int, default=4, help="realisations of the full simulation")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--points", type=int, nargs="*", default=None, help="the points checked (default: both)")
    args = ap.parse_args(argv)

    import pandas as pd

    from arraysel.objective.cysts import CystPhantom, CystSettings, contrast_ratio, gcnr
    from arraysel.objective.sector_objective import SectorObjective, point_label
    from arraysel.report.tables import write_csv
    from arraysel.scenes.schema import load_scene

    scene = load_scene(TREE)
    obj = SectorObjective(scene, dtype=torch.float64)
    n = obj.n_elements
    full = np.ones(n, bool)
    uni = np.zeros((16, 16), bool)
    uni[::2, ::2] = True
    masks = {"full": full, "uniform": uni.ravel(), **{f"random #{j}": m for j, m in
                                                      enumerate(obj.fresh_random_masks(2, seed=0))}}
    labels, M = list(masks), np.array(list(masks.values()))
    st = CystSettings.from_scene(scene)
    lobe = scene.sector_geometry()["lobe"]
    lam = scene.wavelength
    rows = []
    for i in (st.points if args.points is None else args.points):
        psf = obj.point_images(M, i, exact=True).numpy()
        u0, v0 = obj.setup.direction_of(i)
        R = obj.setup.range_of(i)
        alone = full_images(obj, i, M, np.array([[R * u0, R * v0, R * math.sqrt(1 - u0 * u0 - v0 * v0)]]), np.ones(1))
        for b, lab in enumerate(labels):
            a = np.vdot(alone[b], psf[b]) / np.vdot(alone[b], alone[b])
            err = np.linalg.norm(a * alone[b] - psf[b]) ** 2 / np.linalg.norm(psf[b]) ** 2
            print(f"point {point_label(obj, i)} {lab}: full pipeline on the point alone against the exact PSF, "
                  f"SI-MSE {err:.2e}", flush=True)
        ph = CystPhantom(obj.setup.u, obj.setup.v, (u0, v0), R, lobe, st, index=i)
        rng = np.random.default_rng(np.random.SeedSequence([args.seed, i, 1]))
        envs, t0 = [], time.perf_counter()
        for _ in range(args.full):
            pts, amps = phantom(ph, lam, rng)
            envs.append(np.abs(full_images(obj, i, M, pts, amps)))
        secs = (time.perf_counter() - t0) / args.full
        env = np.stack(envs, 1)                                     # (B, realisations, H, W)
        for b, lab in enumerate(labels):
            model = ph.metrics(psf[b])
            fi, fo = env[b][:, ph.inside], env[b][:, ph.ring]
            rows.append({"point": point_label(obj, i), "selection": lab, "model_CR_dB": model["CR_dB"],
                         "full_CR_dB": contrast_ratio(fi, fo), "model_gCNR": model["gCNR"], "full_gCNR": gcnr(fi, fo),
                         "scatterers": len(amps), "full_seconds": secs})
            print(rows[-1], flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    t = pd.DataFrame(rows)
    write_csv(args.out / "model_check.csv", t)
    print(t.round(3).to_string(index=False))


if __name__ == "__main__":
    main()
