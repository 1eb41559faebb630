"""The two-way broadband beam pattern (arraysel.physics.beampattern) and its scorer
(arraysel.objective.beam_objective): against an explicit sum over elements and frequencies, both
paths, the band, the region and its weights, grating lobes, gradients and bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from arraysel.errors import ParameterError, SelectionError
from arraysel.objective.beam_objective import BEAM_TERMS, BeamPatternScorer
from arraysel.physics.beampattern import (BeamPattern, band_nodes, element_factor, grating_lobe_segments,
                                          lattice_of, lattice_periods, pulse_echo_spectrum, steering_coverage,
                                          steering_weights)
from arraysel.physics.probes import get_probe


def explicit(bp: BeamPattern, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The pattern by an explicit sum over elements and frequencies (complex128 numpy)."""
    pos = bp.positions.numpy()
    du, dv = bp.du.numpy(), bp.dv.numpy()
    out = np.zeros((a.shape[0], dv.size, du.size), dtype=complex)
    for fr, w in zip(bp.frequencies.numpy(), bp.freq_weights.numpy()):
        k = 2 * np.pi * fr / bp.c
        phase = np.exp(1j * k * (pos[:, 0, None, None] * du[None, None, :] + pos[:, 1, None, None] * dv[None, :, None]))
        t = np.einsum("be,evu->bvu", a, phase)
        r = np.einsum("be,evu->bvu", b, phase)
        out += w * (np.abs(t) ** 2 * np.abs(r) ** 2 if bp.combine == "energy" else t * r)
    return out if bp.combine == "coherent" else out.real


def layouts():
    probe = get_probe("MATRIX-32x32", nx=5, ny=4)
    rng = np.random.default_rng(1)
    keep = [0, 1, 2, 4, 6, 7, 9, 12, 13, 18, 19]
    return [("probe", probe, 20, "grid"),
            ("irregular", rng.normal(size=(13, 2)) * 1e-3, 13, "direct"),
            ("lattice with empty nodes, off centre", probe.element_positions()[keep] + [1e-3, -2e-3, 0], 11, "grid")]


@pytest.mark.parametrize("combine", ["energy", "coherent"])
@pytest.mark.parametrize("which", [0, 1, 2])
def test_pattern_matches_the_explicit_sum(combine, which):
    name, layout, ne, path = layouts()[which]
    kw = dict(n_freq=3, combine=combine, sector_deg=(20, 10), dtype=torch.float64)
    bp = (BeamPattern.from_probe(layout, element_factor=False, **kw) if name == "probe"
          else BeamPattern(layout, fc=3e6, bandwidth=70, **kw))
    assert bp.path == path
    same = (BeamPattern.from_probe(layout, step=bp.du[1] - bp.du[0], **{**kw, "n_freq": 5}) if name == "probe"
            else None)
    if same is not None:
        assert torch.equal(same.du, bp.du)
    rng = np.random.default_rng(0)
    a, b = rng.random((3, ne)), rng.random((3, ne))
    got = bp.pattern(torch.tensor(a), torch.tensor(b)).numpy()
    ref = explicit(bp, a, b)
    assert np.abs(got - ref).max() <= 1e-12 * np.abs(ref).max()
    shared = bp.pattern(torch.tensor(a)).numpy()
    assert np.abs(shared - explicit(bp, a, a)).max() <= 1e-12 * np.abs(shared).max()
    # the centre is (0, 0); a single element of weight 1 has energy 1 everywhere (its coherent
    # pattern is 1 at the centre only: off the centre its echo arrives early or late)
    assert float(bp.du[bp.du.numel() // 2]) == 0.0 and float(bp.dv[bp.dv.numel() // 2]) == 0.0
    one = torch.zeros(1, ne, dtype=torch.float64)
    one[0, 0] = 1
    p1 = bp.pattern(one).abs()
    c = (p1.shape[1] // 2, p1.shape[2] // 2)
    assert float(p1[0, c[0], c[1]]) == pytest.approx(1.0, abs=1e-12)
    if combine == "energy":
        assert torch.allclose(p1, torch.ones(()).double(), atol=1e-12)


def test_float32_matches_float64_and_chunks():
    probe = get_probe("MATRIX-32x32", nx=8, ny=8)
    w = (torch.rand(5, 64, generator=torch.Generator().manual_seed(0)) < 0.4).double()
    p64 = BeamPattern.from_probe(probe, n_freq=4, dtype=torch.float64).pattern(w)
    p32 = BeamPattern.from_probe(probe, n_freq=4, chunk=2).pattern(w.float())
    assert p32.dtype == torch.float32
    assert float((p32.double() - p64).abs().max()) <= 1e-5 * float(p64.abs().max())


def test_gradcheck_tiny_probe():
    probe = get_probe("MATRIX-32x32", nx=3, ny=2)
    g = torch.Generator().manual_seed(2)
    a = torch.rand(2, 6, generator=g, dtype=torch.float64).requires_grad_()
    b = torch.rand(2, 6, generator=g, dtype=torch.float64).requires_grad_()
    for combine in ("energy", "coherent"):
        bp = BeamPattern.from_probe(probe, n_freq=2, combine=combine, sector_deg=(0, 0), region="visible",
                                    oversample=0.5, dtype=torch.float64)
        f = (lambda x, y: bp.pattern(x, y)) if combine == "energy" else (lambda x, y: bp.pattern(x, y).abs())
        torch.autograd.gradcheck(f, (a, b), eps=1e-6, atol=1e-6, rtol=1e-4)
        torch.autograd.gradcheck(lambda x: bp.pattern(x), (a,), eps=1e-6, atol=1e-6, rtol=1e-4)
    direct = BeamPattern(np.array([[0, 0], [0.4e-3, 0.1e-3], [-0.2e-3, 0.5e-3]]), fc=3e6, bandwidth=70, n_freq=2,
                         sector_deg=(0, 0), region="visible", oversample=0.5, dtype=torch.float64)
    torch.autograd.gradcheck(lambda x, y: direct.pattern(x, y), (a[:, :3], b[:, :3]), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_scorer_gradients_and_values():
    probe = get_probe("MATRIX-32x32", nx=6, ny=6)
    bp = BeamPattern.from_probe(probe, n_freq=2, sector_deg=(10, 10), region="visible", dtype=torch.float64)
    sc = BeamPatternScorer(bp)
    g = torch.Generator().manual_seed(3)
    w = (0.3 + torch.rand(2, 36, generator=g, dtype=torch.float64)).requires_grad_()
    m = sc(w)
    assert set(m) == set(BEAM_TERMS) and all(bool(torch.isfinite(v).all()) for v in m.values())
    # the regions depend on the weights only through the detached rays: check with them frozen
    from arraysel.objective.lobes import lobe_metrics, main_lobe_regions
    img = bp.pattern(w.detach())
    reg = main_lobe_regions({"pattern": img}, {"pattern": bp.coords}, power=True, frame="uv", target=(0, 0, 0),
                            rule=sc.rule)

    def f(x, term):
        return lobe_metrics({"pattern": bp.pattern(x)}, {"pattern": bp.coords}, power=True, frame="uv",
                            weights={"pattern": bp.mean_weight}, peak_weights={"pattern": bp.peak_weight},
                            terms=[term], regions=reg)[term]

    for term in ("PSL_dB", "ISLR_dB"):
        torch.autograd.gradcheck(lambda x: f(x, term), (w,), eps=1e-6, atol=1e-5, rtol=1e-3)
        assert torch.allclose(f(w, term), m[term])


# --------------------------------------------------------------------------
# the band, the region, the weights
# --------------------------------------------------------------------------

def test_band_nodes():
    f, w = band_nodes(3e6, 70, 8)
    assert torch.allclose(w, torch.full((8,), 1 / 8, dtype=torch.float64))
    grid = torch.linspace(1.0, 9e6, 90001, dtype=torch.float64)
    s2 = pulse_echo_spectrum(grid, 3e6, 70) ** 2
    cdf = torch.cumsum(s2, 0) / s2.sum()
    at = cdf[torch.searchsorted(grid, f)]
    assert torch.allclose(at, (torch.arange(8, dtype=torch.float64) + 0.5) / 8, atol=2e-3)
    fc_, wc = band_nodes(3e6, 70, 16, "coherent")
    assert float(wc.sum()) == pytest.approx(1.0) and bool((torch.diff(fc_) > 0).all())
    with pytest.raises(ParameterError, match="n_freq"):
        band_nodes(3e6, 70, 0)


def test_energy_pattern_converges_with_frequencies():
    probe = get_probe("MATRIX-32x32", nx=8, ny=8)
    w = torch.zeros(1, 64, dtype=torch.float64)
    w[0, torch.randperm(64, generator=torch.Generator().manual_seed(0))[:24]] = 1
    ref = BeamPattern.from_probe(probe, n_freq=64, dtype=torch.float64)
    errs = []
    for n in (2, 4, 8, 16):
        bp = BeamPattern(probe, fc=probe.fc, bandwidth=probe.bandwidth, n_freq=n, dtype=torch.float64)
        bp.du, bp.dv = ref.du, ref.dv
        bp._build_grid(2 * math.pi * bp.frequencies / bp.c)
        errs.append(float((bp.pattern(w) - ref.pattern(w)).abs().max() / ref.pattern(w).max()))
    # the largest pixel error relative to the peak: 0.18, 0.11, 0.030, 0.019
    assert errs[-1] < 0.025 and errs[0] > 5 * errs[-1] and all(e2 < e1 for e1, e2 in zip(errs, errs[1:]))


def test_coverage_and_weights():
    du = torch.linspace(-1.5, 1.5, 61, dtype=torch.float64)
    cov = steering_coverage(du, du, 0.0, 0.0, "visible")
    r2 = du[None] ** 2 + du[:, None] ** 2
    assert bool((cov[r2 < 1 - 1e-9] == 1).all()) and bool((cov[r2 > 1 + 1e-9] == 0).all())
    sec = steering_coverage(du, du, 0.5, 0.5, "sector")
    tri = (1 - du.abs()).clamp(min=0)
    assert torch.allclose(sec, tri[:, None] * tri[None], atol=1e-12)
    vis = steering_coverage(du, du, 0.5, 0.5, "visible")
    mean, top = steering_weights(du, du, 0.5, 0.5, "visible")
    assert torch.equal(mean, vis) and torch.equal(top, (vis > 0).double())
    assert float(vis[30, 30]) == pytest.approx(1.0) and float(vis[0, 0]) == 0.0
    # coverage at a shift of (1.5, 0): only the steering (-0.5, 0) looks there: zero area
    assert float(vis[30, 60]) == pytest.approx(0.0, abs=0.02)
    # the element factor: each beam relative to its own peak, so the centre stays 1
    ef = lambda u, v: element_factor(u, v, 0.25e-3, 0.25e-3, "soft", 0.513e-3)  # noqa: E731
    mean_e, top_e = steering_weights(du, du, 0.5, 0.5, "visible", ef)
    assert float(mean_e[30, 30]) == pytest.approx(1.0) and float(top_e[30, 30]) == pytest.approx(1.0)
    assert bool((mean_e <= vis + 1e-12).all()) or float(mean_e.max()) < 1.5
    assert float(element_factor(torch.tensor(0.0), torch.tensor(0.0), 0.25e-3, 0.25e-3, "soft", 0.5e-3)) == 1.0


def test_grating_lobes_and_lattices():
    seg = grating_lobe_segments(0.6e-3, 0.6e-3, (0.4e-3, 0.7e-3), bounds=(-1.5, 1.5, -1.5, 1.5))
    assert seg.shape[1:] == (2, 2)
    first = seg[(seg[:, 0, 1] == 0) & (seg[:, 0, 0] > 0)]
    assert torch.allclose(first[0], torch.tensor([[0.4 / 0.6, 0.0], [0.7 / 0.6, 0.0]], dtype=torch.float64))
    probe = get_probe("MATRIX-32x32", nx=8, ny=8)
    thin = np.zeros((8, 8))
    thin[1::3, ::2] = 1
    assert lattice_periods(torch.tensor(thin.ravel()), 8, 8).tolist() == [[2, 3]]
    assert lattice_periods(torch.tensor(np.tile(np.eye(8)[0], 8)), 8, 8).tolist() == [[0, 1]]   # one column
    assert lattice_periods(torch.tensor(np.eye(8)[0].repeat(8)), 8, 8).tolist() == [[1, 0]]    # one row
    lat = lattice_of(probe.element_positions()[[0, 3, 17, 63]])
    assert lat is not None and lat[:2] == (8, 8) and list(lat[5]) == [0, 3, 17, 63]
    assert lattice_of(np.array([[0, 0], [1e-3, 0], [0.3712345e-3, 0.1e-3]])) is None
    bp = BeamPattern.from_probe(probe, n_freq=4, dtype=torch.float64)
    w = torch.tensor(np.stack([thin.ravel(), np.ones(64)]))
    g = bp.grating_directions(w)
    assert g[0].shape[0] > g[1].shape[0]
    assert bp.grating_directions(w)[0] is g[0]           # the same object on every call
    # every other column: a lattice of pitch 0.6 mm in x; with a blank row, empty nodes
    half = BeamPattern(probe.element_positions()[::2], fc=3e6, bandwidth=70, n_freq=2)
    assert half.path == "grid" and half.lattice[:4] == (4, 8, pytest.approx(0.6e-3), pytest.approx(0.3e-3))
    assert len(half.grating_directions(torch.ones(1, 32))[0]) > 0
    blank = BeamPattern(np.delete(probe.element_positions(), range(16, 24), axis=0), fc=3e6, bandwidth=70, n_freq=4)
    assert blank.path == "grid" and blank.lattice[:2] == (8, 8) and blank.lattice[5].size == 56
    assert len(blank.grating_directions(torch.ones(1, 56))[0]) == len(bp.grating_directions(torch.ones(1, 64))[0])


def test_periodic_thinning_scores_a_grating_lobe():
    probe = get_probe("MATRIX-32x32", nx=16, ny=16)
    sc = BeamPatternScorer(BeamPattern.from_probe(probe, n_freq=4, sector_deg=(30, 30)))
    thin = np.zeros((16, 16))
    thin[::2, ::2] = 1
    m = sc(torch.tensor(np.stack([thin.ravel(), np.ones(256)]), dtype=torch.float32))
    assert float(m["GLL_dB"][0]) > -9 and float(m["GLL_dB"][0]) > float(m["GLL_dB"][1]) + 10
    assert float(m["PSL_dB"][0]) >= float(m["GLL_dB"][0]) - 1e-6


# --------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------

def test_bad_input():
    probe = get_probe("MATRIX-32x32", nx=4, ny=4)
    bp = BeamPattern.from_probe(probe, n_freq=2)
    with pytest.raises(SelectionError, match="tx"):
        bp.pattern(torch.ones(2, 15))
    with pytest.raises(SelectionError, match="rx"):
        bp.pattern(torch.ones(2, 16), torch.ones(3, 16))
    with pytest.raises(SelectionError, match="finite"):
        bp.pattern(torch.full((1, 16), float("nan")))
    with pytest.raises(ParameterError, match="sector_deg"):
        BeamPattern.from_probe(probe, sector_deg=(95, 0))
    with pytest.raises(ParameterError, match="region 'sector'"):
        BeamPattern.from_probe(probe, region="sector", sector_deg=(0, 20))
    with pytest.raises(ParameterError, match="combine"):
        BeamPattern.from_probe(probe, combine="rms")
    with pytest.raises(ParameterError, match="plane"):
        BeamPattern(np.array([[0, 0, 0], [1e-3, 0, 1e-3]]), fc=3e6, bandwidth=70)
    with pytest.raises(ParameterError, match="element"):
        BeamPattern.from_probe(probe, element=(0.1e-3, -1, "soft"))
    with pytest.raises(ParameterError, match="oversample"):
        BeamPattern.from_probe(probe, oversample=100)
    with pytest.raises(ParameterError, match="step"):
        BeamPattern.from_probe(probe, step=(0.01, 0.02, 0.03))
    with pytest.raises(ParameterError, match="GLL_dB"):
        BeamPatternScorer(BeamPattern(np.array([[0, 0], [1e-3, 0], [0.3712345e-3, 0.1e-3]]), fc=3e6,
                                      bandwidth=70)).metrics(torch.ones(1, 3), terms=["GLL_dB"])


# --------------------------------------------------------------------------
# the far-field limit of the exact 3-D PSF (benchmarks/beampattern_farfield.py has the full runs)
# --------------------------------------------------------------------------

def _exact_on(setup, pixels):
    """MatrixPSF of ``setup`` on the given pixels (H, W, 3) instead of its planes."""
    from unittest import mock

    import arraysel.physics.volume.psf as psf

    with mock.patch.object(psf, "plane_axes", lambda s: {"xy": torch.as_tensor(pixels, dtype=torch.float64)}):
        return psf.MatrixPSF(setup, dtype=torch.float64)


@pytest.mark.slow
def test_focused_beam_far_field_is_the_coherent_pattern():
    """A beam focused at (0, 0, R) in transmit and receive, answering a scatterer moved along u on
    the sphere of radius R: in the far field, the coherent two-way pattern times the elements'
    factor squared."""
    from arraysel.physics.probes import Acquisition
    from arraysel.physics.volume import MatrixPSFSetup, focused_delays3

    probe = get_probe("MATRIX-32x32", nx=6, ny=6)
    acq = Acquisition.for_probe(probe)
    R, lam = 40e-3, acq.c / probe.fc
    step = lam / (4 * probe.aperture[0])
    bp = BeamPattern.from_probe(probe, acq, n_freq=128, combine="coherent", sector_deg=(0, 0), region="visible",
                                step=step, dtype=torch.float64)
    w = torch.ones(1, 36, dtype=torch.float64)
    pat = bp.pattern(w)[0, bp.dv.numel() // 2].abs()
    delays = focused_delays3(probe, 0.0, 0.0, R, acq.c)
    got, ref = [], []
    for j in range(bp.du.numel() // 2, bp.du.numel()):
        u = float(bp.du[j])
        if u > 0.7:
            break
        setup = MatrixPSFSetup(probe, acq, delays, (R * u, 0.0, R * math.sqrt(1 - u * u)), 1e-3, 1e-3, 1e-3, 1e-3,
                               planes=("xy",))
        got.append(abs(complex(_exact_on(setup, np.array([[[0.0, 0.0, R]]])).planes(w)["xy"][0, 0, 0])))
        ef = float(element_factor(torch.tensor(u), torch.tensor(0.0), probe.width, probe.height, probe.baffle, lam))
        ref.append(float(pat[j]) * ef ** 2)
    got_db = 20 * np.log10(np.array(got) / got[0])
    ref_db = 20 * np.log10(np.array(ref) / ref[0])
    # the main lobe and the first side lobe within 1 dB (0.03 and 0.07 dB at -2.5 and -10 dB, 0.8 dB
    # at -23 dB); from -30 dB the exact image levels off about 3 to 7 dB above the pattern
    # (benchmarks/results/beampattern/farfield.txt)
    assert np.abs(got_db - ref_db)[ref_db > -25].max() < 1.0
    keep = ref_db > -40
    assert np.corrcoef(got_db[keep], ref_db[keep])[0, 1] > 0.97


@pytest.mark.slow
def test_diverging_wave_psf_far_field_is_close_to_the_energy_pattern():
    """A point far from an 8 x 8 probe imaged with 5 x 5 diverging waves over +-30 degrees, its PSF
    on the sphere through it sampled in (u, v): the energy pattern's dB map and lobe metrics."""
    from arraysel.objective.lobes import lobe_metrics
    from arraysel.physics.beampattern import sphere_surface
    from arraysel.physics.probes import Acquisition
    from arraysel.physics.volume import MatrixPSFSetup, diverging_delays3, tilt_grid

    probe = get_probe("MATRIX-32x32", nx=8, ny=8)
    acq = Acquisition.for_probe(probe)
    R = 40e-3
    bp = BeamPattern.from_probe(probe, acq, n_freq=16, sector_deg=(0, 0), region="visible",
                                step=acq.c / probe.fc / (4 * probe.aperture[0]), dtype=torch.float64)
    keep_u, keep_v = bp.du.abs() <= 0.55, bp.dv.abs() <= 0.55
    du, dv = bp.du[keep_u], bp.dv[keep_v]
    tx, ty = tilt_grid(5, 5, 30.0, 30.0)
    setup = MatrixPSFSetup(probe, acq, diverging_delays3(probe, tx, ty, 0.84 * probe.aperture[0], acq.c),
                           (0.0, 0.0, R), 1e-3, 1e-3, 1e-3, 1e-3, planes=("xy",))
    w = torch.ones(1, 64, dtype=torch.float64)
    psf = _exact_on(setup, sphere_surface(R, du, dv)).planes(w)["xy"][0].abs() ** 2
    pat = bp.pattern(w)[0][keep_v][:, keep_u]
    a, b = ((10 * torch.log10(x / x.max())).numpy() for x in (psf, pat))
    keep = (a > -40) | (b > -40)
    assert np.corrcoef(np.maximum(a[keep], -40), np.maximum(b[keep], -40))[0, 1] > 0.98      # 0.992 measured
    coords = {"s": bp.coords[keep_v][:, keep_u]}
    m_psf = lobe_metrics({"s": psf[None]}, coords, power=True, frame="uv", target=(0, 0, 0))
    m_pat = lobe_metrics({"s": pat[None]}, coords, power=True, frame="uv", target=(0, 0, 0))
    assert abs(float(m_psf["PSL_dB"][0] - m_pat["PSL_dB"][0])) < 1.0                         # 0.6 dB
    assert abs(float(m_psf["ISLR_dB"][0] - m_pat["ISLR_dB"][0])) < 1.0                       # 0.4 dB
    assert float(m_pat["width_u_6dB"][0]) == pytest.approx(float(m_psf["width_u_6dB"][0]), rel=0.12)
