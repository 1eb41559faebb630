"""The u-v beam-pattern figure of sector scenes (arraysel.report.uv_plots): the lattice's grating
lobes where lambda / pitch puts them, the figure's panels and its input checks."""
from __future__ import annotations

import numpy as np
import pytest

from arraysel.errors import ParameterError
from arraysel.report.uv_plots import beam_pattern_figure, lattice_grating_lobes


def test_lattice_grating_lobes_at_lambda_over_pitch():
    lam, px, py = 0.385e-3, 0.3e-3, 0.6e-3          # lambda / p: 1.2833 in u, 0.6417 in v
    lobes = lattice_grating_lobes(lam, px, py, (1.5, 1.5))
    gx, gy = lam / px, lam / py
    want = {(m * gx, n * gy) for m in (-1, 0, 1) for n in (-2, -1, 0, 1, 2) if m or n}
    assert len(lobes) == len(want) == 14
    got = {tuple(v) for v in np.round(lobes, 12)}
    assert got == {tuple(np.round(v, 12)) for v in want}
    assert lattice_grating_lobes(lam, lam / 0.9, lam / 0.9, (0.8, 0.8)).shape == (0, 2)   # half-wave-ish: none


@pytest.mark.parametrize("bad", [0.0, -1e-3, float("nan")])
def test_lattice_grating_lobes_refuses_bad_lengths(bad):
    with pytest.raises(ParameterError, match="pitch_x"):
        lattice_grating_lobes(0.4e-3, bad, 0.3e-3, (1, 1))


def test_figure_panels_and_checks():
    du = np.linspace(-1.5, 1.5, 31)
    dv = np.linspace(-1.5, 1.5, 21)
    pats = np.random.default_rng(0).random((4, 21, 31))
    fig = beam_pattern_figure(["a", "b", "c", "d"], pats, du, dv, (0.5, 0.5),
                              lattice_grating_lobes(0.385e-3, 0.3e-3, 0.3e-3, (1.5, 1.5)),
                              [np.array([[[0.6, -1.0], [0.6, 1.0]]])] * 4)
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[:4] == ["a", "b", "c", "d"] and len(fig.axes) == 5      # four panels and the colour bar
    with pytest.raises(ParameterError, match="patterns must have shape"):
        beam_pattern_figure(["a"], pats, du, dv, (0.5, 0.5))
    with pytest.raises(ParameterError, match="dynamic_range"):
        beam_pattern_figure(["a"], pats[:1], du, dv, (0.5, 0.5), dynamic_range=0)
