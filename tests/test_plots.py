"""One plotting module (arraysel.report.plots): figures are returned, never shown or saved behind the
caller's back, one dB range, axes in mm, and no backend is switched on import (notebooks)."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("matplotlib")

from arraysel.report import plots  # noqa: E402


def _kernel(n=32, width=3.0):
    z, x = np.mgrid[:n, :n] - n // 2
    return np.exp(-(x ** 2 + z ** 2) / (2 * width ** 2)).astype(np.complex64)


def test_importing_and_drawing_keeps_the_callers_backend():
    code = ("import matplotlib; matplotlib.use('svg')\n"
            "import arraysel.report.plots as p, arraysel.cli.psf, arraysel.run.compare, arraysel.api\n"
            "import numpy as np\n"
            "p.psf_figure(np.ones((8, 8)), np.ones((8, 8)), 1e-4, [0, 2], 4)\n"
            "print(matplotlib.get_backend())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "svg"


def test_psf_figure_is_in_mm_with_the_shared_db_range():
    from matplotlib.figure import Figure

    fig = plots.psf_figure(_kernel(), _kernel(width=2.0), 1e-4, [0, 2, 4], 8)
    assert isinstance(fig, Figure)
    ax = fig.axes[0]
    assert "mm" in ax.get_xlabel() and "mm" in ax.get_ylabel()
    im = ax.get_images()[0]
    assert im.get_clim() == (-plots.DYN_RANGE_DB, 0)
    left, right, bottom, top = im.get_extent()
    assert right - left == pytest.approx(32 * 1e-4 * 1e3)   # 32 pixels of 0.1 mm


def test_compare_figures_return_figures_in_one_style():
    from matplotlib.figure import Figure

    kern = np.stack([_kernel(), _kernel(width=2.0)])
    masks = np.array([[1, 0, 1, 0], [0, 1, 0, 1]], dtype=bool)
    trace = pd.DataFrame({"config": ["a", "a"], "seed": [0, 0], "seconds": [0.1, 1.0], "evaluations": [1, 5],
                          "gradient_steps": [0, 0], "best_Mean": [0.5, 0.2], "event": ["improvement", "end"]})
    figs = [plots.masks_figure(["a", "b"], masks), plots.psfs_figure(["a", "b"], kern, _kernel(), 1e-4),
            plots.profiles_figure(["a", "b"], kern, _kernel(), 1e-4), plots.trace_figure(trace, 0.1),
            plots.plot_anytime(trace, full_mean=0.1)]
    assert all(isinstance(f, Figure) for f in figs)
    for im in figs[1].axes[0].get_images():
        assert im.get_clim() == (-plots.DYN_RANGE_DB, 0)
    assert figs[2].axes[0].get_ylim()[0] == plots.PROFILE_FLOOR_DB
    assert "mm" in figs[2].axes[0].get_xlabel()
    # without a pitch (the toy objective's synthetic kernels) the axes say pixel
    assert "pixel" in plots.profiles_figure(["a"], kern[:1], _kernel(), None).axes[0].get_xlabel()


def test_save_figure_is_atomic_png_and_collected(tmp_path):
    fig = plots.masks_figure(["a"], np.array([[1, 0, 1]], dtype=bool))
    with plots.collect_figures() as got:
        plots.save_figure(fig, tmp_path / "masks.png")
    assert (tmp_path / "masks.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert got == {"masks": fig}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["masks.png"]


# ---------------------------------------------------------------- matrix probes


def _three_planes(n=21, pitch=1e-4, z0=0.03):
    a = (np.arange(n) - n // 2) * pitch
    out = {}
    yy, xx = np.meshgrid(a, a, indexing="ij")
    out["xy"] = np.stack([xx, yy, np.full_like(xx, z0)], -1)
    zz, xx = np.meshgrid(z0 + a, a, indexing="ij")
    out["xz"] = np.stack([xx, np.zeros_like(xx), zz], -1)
    zz, yy = np.meshgrid(z0 + a, a, indexing="ij")
    out["yz"] = np.stack([np.zeros_like(yy), yy, zz], -1)
    return out


def _psf(coords, sx, sy, sz=2e-4, z0=0.03):
    return np.exp(-0.5 * ((coords[..., 0] / sx) ** 2 + (coords[..., 1] / sy) ** 2
                          + ((coords[..., 2] - z0) / sz) ** 2)).astype(np.complex64)


def test_matrix_masks_figure_is_one_grid_image_per_selection():
    from matplotlib.figure import Figure

    masks = np.zeros((3, 12), dtype=bool)
    masks[0, [0, 5, 11]] = True
    masks[1, :6] = True
    masks[2, ::2] = True
    fig = plots.matrix_masks_figure(["a", "b", "c"], masks, (3, 4))
    assert isinstance(fig, Figure)
    axes = [ax for ax in fig.axes if ax.get_images()]
    assert len(axes) == 3
    img = axes[0].get_images()[0].get_array()
    assert img.shape == (3, 4)
    # element index iy * nx + ix: element 5 is row 1, column 1; element 11 is row 2, column 3
    assert img[1, 1] == 1 and img[2, 3] == 1 and img[0, 0] == 1 and img.sum() == 3
    assert axes[0].get_xlabel() == "element column ix" and axes[0].get_ylabel() == "element row iy"
    assert "3 of 12" in axes[0].get_title() and "6 of 12" in axes[1].get_title()


def test_planes_figure_in_mm_at_the_shared_db_range_each_row_at_its_own_peak():
    from matplotlib.figure import Figure

    c = _three_planes()
    ref = {k: _psf(v, 2e-4, 3e-4) for k, v in c.items()}
    planes = {k: np.stack([_psf(v, 3e-4, 3e-4), 0.5 * _psf(v, 2e-4, 4e-4)]) for k, v in c.items()}
    fig = plots.planes_figure(["sparse", "spiral"], planes, c, ref)
    assert isinstance(fig, Figure)
    axes = [ax for ax in fig.axes if ax.get_images()]
    assert len(axes) == 9                               # (full + 2 selections) x 3 planes
    labels = [(ax.get_xlabel(), ax.get_ylabel()) for ax in axes[:3]]
    assert labels == [("x (mm)", "y (mm)"), ("x (mm)", "z (mm)"), ("y (mm)", "z (mm)")]
    for ax in axes:
        assert ax.get_images()[0].get_clim() == (-plots.DYN_RANGE_DB, 0)
    left, right, bottom, top = axes[1].get_images()[0].get_extent()
    assert (left, right) == pytest.approx((-1.05, 1.05))          # 21 pixels of 0.1 mm around x = 0
    assert (top, bottom) == pytest.approx((28.95, 31.05))         # depth grows downwards
    assert "full array" in axes[0].get_title() and "spiral: yz" in axes[8].get_title()
    # each row in dB of its own peak: the half-amplitude selection still peaks at 0 dB
    data = axes[6].get_images()[0].get_array()
    assert float(data.max()) == pytest.approx(0.0, abs=1e-9)
    # without a reference each row has its own peak
    fig = plots.planes_figure(["spiral"], {k: v[1:] for k, v in planes.items()}, c)
    assert float([ax for ax in fig.axes if ax.get_images()][0].get_images()[0].get_array().max()) == pytest.approx(0)


def test_lateral_profiles_figure_against_the_full_array():
    from matplotlib.figure import Figure

    c = _three_planes(41)
    ref = _psf(c["xy"], 2e-4, 3e-4)
    sel = np.stack([_psf(c["xy"], 4e-4, 3e-4)])
    fig = plots.lateral_profiles_figure(["spiral"], sel, c["xy"], ref)
    assert isinstance(fig, Figure)
    ax_x, ax_y = fig.axes[:2]
    assert ax_x.get_xlabel() == "x (mm)" and ax_y.get_xlabel() == "y (mm)"
    assert ax_x.get_ylim()[0] == plots.PROFILE_FLOOR_DB
    lines = [ln for ln in ax_x.get_lines() if ln.get_label().startswith(("full", "spiral"))]
    assert [ln.get_label().split(" ")[0] for ln in lines] == ["full", "spiral"]
    assert lines[0].get_color() == "k"
    np.testing.assert_allclose(lines[0].get_xdata(), (np.arange(41) - 20) * 0.1)
    # the -6 dB widths in the legend: 2 sigma sqrt(2 ln 2) about, 0.47 mm and 0.94 mm along x
    assert "0.47 mm" in lines[0].get_label() and "0.94 mm" in lines[1].get_label()
    assert max(lines[0].get_ydata()) == pytest.approx(0.0)


def test_every_figure_draws_into_the_callers_axes():
    """ax=: one Axes for a one-panel figure, as many as its panels otherwise; the caller's Figure is
    returned, no new figure made, and a wrong count of Axes is refused by name."""
    from matplotlib.figure import Figure

    from arraysel.errors import ParameterError

    kern = np.stack([_kernel(), _kernel(width=2.0)])
    masks = np.array([[1, 0, 1, 0], [0, 1, 0, 1]], dtype=bool)
    trace = pd.DataFrame({"config": ["a", "a"], "seed": [0, 0], "seconds": [0.1, 1.0], "evaluations": [1, 5],
                          "gradient_steps": [0, 0], "best_Mean": [0.5, 0.2], "event": ["improvement", "end"]})
    c = _three_planes()
    planes = {k: np.stack([_psf(v, 3e-4, 3e-4)]) for k, v in c.items()}
    calls = [  # (panels, draw(ax))
        (1, lambda ax: plots.masks_figure(["a", "b"], masks, ax=ax)),
        (1, lambda ax: plots.trace_figure(trace, 0.1, ax=ax)),
        (3, lambda ax: plots.psfs_figure(["a", "b"], kern, _kernel(), 1e-4, ax=ax)),
        (2, lambda ax: plots.profiles_figure(["a", "b"], kern, _kernel(), 1e-4, ax=ax)),
        (3, lambda ax: plots.psf_figure(_kernel(), _kernel(width=2.0), 1e-4, [0, 2], 4, ax=ax)),
        (3, lambda ax: plots.plot_anytime(trace, full_mean=0.1, ax=ax)),
        (2, lambda ax: plots.matrix_masks_figure(["a", "b"], masks, (2, 2), ax=ax)),
        (3, lambda ax: plots.planes_figure(["s"], planes, c, ax=ax)),
        (2, lambda ax: plots.lateral_profiles_figure(["s"], planes["xy"], c["xy"], ax=ax)),
    ]
    for panels, draw in calls:
        fig = Figure()
        axes = fig.subplots(1, panels, squeeze=False).ravel()
        got = draw(axes[0] if panels == 1 else list(axes))
        assert got is fig
        drawn = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
        assert len(drawn) == panels and all(ax.has_data() for ax in axes), draw
    with pytest.raises(ParameterError, match="draws 2 panel"):
        plots.profiles_figure(["a", "b"], kern, _kernel(), 1e-4, ax=Figure().subplots())
