"""Per-beam metrics of 1-D scenes (arraysel.objective.beams1d): each point's own main lobe on a
case with a known answer (a sinc across, a Gaussian along the beam), the per-beam view of a 1-D
objective, and beams.csv / pareto.csv from compare on a 1-D scene with metrics.per_beam."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch

from arraysel.errors import ParameterError
from arraysel.objective.beams1d import BEAM_NAMES, PSFBeams, kernel_lobe_metrics, main_lobe_band
from arraysel.objective.build import build_objective
from arraysel.scenes.schema import load_scene
from arraysel.selection import random_masks

#: |sinc| first side lobe (amplitude 0.21723 at 1.4303 a): -13.26 dB in power
SINC_PSL_DB = 20 * math.log10(0.217234)
#: sinc(x / a) falls to 0.5 at x = 0.60335 a
SINC_HALF = 0.603355


def _sinc_gauss(a=1e-3, s=0.3e-3, n=241, p=0.04e-3, shift=(0, 0)):
    x = (np.arange(n) - (n - 1) / 2) * p
    Z, X = np.meshgrid(x, x, indexing="ij")
    amp = np.sinc((X - shift[1] * p) / a) * np.exp(-(((Z - shift[0] * p) / s) ** 2))
    return torch.tensor(amp * np.exp(1j * 0.3), dtype=torch.complex128)[None], p


@pytest.mark.parametrize("shift", [(0, 0), (7, -11)])
def test_sinc_across_gaussian_along(shift):
    a, s = 1e-3, 0.3e-3
    k, p = _sinc_gauss(a, s, shift=shift)
    r = kernel_lobe_metrics(k, p)
    assert abs(float(r["PSL_dB"][0]) - SINC_PSL_DB) < 0.1
    assert float(r["width_x_6dB"][0]) == pytest.approx(2 * SINC_HALF * a, rel=5e-3)
    assert float(r["width_z_6dB"][0]) == pytest.approx(2 * s * math.sqrt(math.log(2)), rel=5e-3)   # Gaussian at 0.5
    # the columns past the sinc's first nulls (|x| > a) over those within them, on the same samples
    # (separable: the Gaussian factor cancels; on an infinite line the ratio would be 9.72 / 90.28)
    xs = (np.arange(241) - 120) * p - shift[1] * p
    s2 = np.sinc(xs / a) ** 2
    inside = np.abs(xs) <= a + 1e-12
    want = 10 * math.log10(s2[~inside].sum() / s2[inside].sum())
    assert float(r["ISLR_dB"][0]) == pytest.approx(want, abs=0.05)


def test_the_pulse_lobes_along_the_beam_belong_to_the_main_lobe():
    # an echo of the pulse 1 mm deeper at half the amplitude (-6 dB), in the main lobe's columns:
    # not a side lobe across the beam, which stays the sinc's
    a, s, n, p = 1e-3, 0.2e-3, 241, 0.04e-3
    x = (np.arange(n) - (n - 1) / 2) * p
    Z, X = np.meshgrid(x, x, indexing="ij")
    amp = np.sinc(X / a) * (np.exp(-((Z / s) ** 2)) + 0.5 * np.exp(-(((Z - 1e-3) / s) ** 2)))
    r = kernel_lobe_metrics(torch.tensor(amp)[None], p)
    assert abs(float(r["PSL_dB"][0]) - SINC_PSL_DB) < 0.1


def test_main_lobe_band_first_nulls_and_ripple():
    prof = np.array([0.5, 0.1, 0.3, 1.0, 0.4, 0.2, 0.21, 0.05, 0.6])
    assert main_lobe_band(prof, 3) == (1, 7)      # 0.2 -> 0.21 is ripple (< 1 dB), 0.05 -> 0.6 is not
    assert main_lobe_band(np.array([1.0, 0.5, 0.2]), 0) == (0, 2)     # edges: no null on either side


def test_a_wider_main_lobe_is_not_counted_as_side_lobe():
    # a sinc 2.4 times wider: a fixed guard of one narrow main lobe would call its flank a side lobe
    k, p = _sinc_gauss(a=2.4e-3, n=401)
    r = kernel_lobe_metrics(k, p)
    assert abs(float(r["PSL_dB"][0]) - SINC_PSL_DB) < 0.15


def test_kernel_lobe_metrics_checks_its_inputs():
    k, p = _sinc_gauss(n=41)
    with pytest.raises(ParameterError, match="pitch"):
        kernel_lobe_metrics(k, 0.0)
    with pytest.raises(ParameterError, match="kernels"):
        kernel_lobe_metrics(k[0], p)


def test_random_masks():
    m = random_masks(10, 3, 5, seed=2)
    assert m.shape == (5, 10) and (m.sum(1) == 3).all()
    assert np.array_equal(m, random_masks(10, 3, 5, seed=2))


@pytest.fixture(scope="module")
def paper_beams():
    scene = load_scene("paper", overrides={"metrics": {"per_beam": True, "fresh_random": 3}})
    return build_objective(scene)


def test_psf_beams_on_the_paper_scene(paper_beams):
    from arraysel.run.sector_report import beam_source

    b = beam_source(paper_beams)
    assert isinstance(b, PSFBeams) and b.n_points == 1 and b.fresh_random == 3
    assert beam_source(build_objective("paper")) is None              # per_beam is off by default
    (label, tx, ty, r), = b.point_info()
    (x, z), = paper_beams.points
    assert x == 0 and label == f"0,0@{z * 1e3:.4g}mm" and tx == 0 and ty == 0 and r == pytest.approx(z)
    masks = np.zeros((2, 64), dtype=bool)
    masks[0] = True
    masks[1, ::2] = True
    met = b.beam_metrics(masks)
    assert set(met) == set(BEAM_NAMES) and all(v.shape == (2, 1) for v in met.values())
    assert np.isnan(met["GLL_dB"]).all() and np.isnan(met["width_y_6dB"]).all()
    assert np.isfinite(met["PSL_dB"]).all() and (met["PSL_dB"] < 0).all()
    # the lateral -6 dB width of the full aperture: the span of the pixels at or above half the peak
    # amplitude on the peak's row, to within a pixel; every second element keeps the aperture: the
    # same width to 10 %
    kern = paper_beams.kernels(masks[:1].astype(np.float32))[0].abs().numpy()
    zi, xi = np.unravel_index(kern.argmax(), kern.shape)
    above = np.flatnonzero(kern[zi] >= 0.5 * kern[zi, xi])
    pitch = paper_beams.metric_kw["pitch"]
    wx = met["width_x_6dB"][:, 0]
    assert abs(wx[0] - (above.max() - above.min()) * pitch) <= pitch
    assert wx[1] == pytest.approx(wx[0], rel=0.1)
    assert (met["width_z_6dB"] > 0).all()
    fresh = b.fresh_random_masks()
    assert fresh.shape == (3, 64) and (fresh.sum(1) == 32).all()


def test_compare_writes_beams_and_pareto_on_a_1d_scene(paper_beams, tmp_path):
    from arraysel.run.compare import compare
    from arraysel.selectors.contract import Budget

    compare(paper_beams, ["random", "uniform"], out_dir=tmp_path, seeds=[0], budget=Budget(evaluations=20),
            progress=False)
    beams = pd.read_csv(tmp_path / "beams.csv")
    assert set(beams["config"]) == {"full", "random", "uniform", "random (fresh median)"}
    assert beams["width_z_mm"].notna().all() and beams["GLL_dB"].isna().all()
    pareto = pd.read_csv(tmp_path / "pareto.csv")
    assert pareto["mean_width_mm"].notna().all() and pareto["on_front"].any()
    assert (tmp_path / "pareto.png").stat().st_size > 1000
