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
