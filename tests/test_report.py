"""``arraysel report``: Markdown and LaTeX tables of a finished comparison, its errors."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pandas as pd
import pytest

from arraysel import cli
from arraysel.report.summary import load_comparison, render, summary_rows
from arraysel.run.compare import compare
from arraysel.selectors.contract import Budget
from arraysel.selectors.registry import build_plugin_manager, get_registry
from arraysel.testing import ToyObjective

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    out = tmp_path_factory.mktemp("cmp")
    reg = get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))
    compare(ToyObjective(16, 8), ["uniform", "random", "ste"], out_dir=out, seeds=[0, 1, 2],
            budget=Budget(evaluations=40), registry=reg, progress=False, figures=False)
    return out


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_markdown_table(finished, capsys):
    assert cli.main(["report", str(finished)]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].startswith("Scene toy, k = 8 of 16 elements, budget 40 evaluations per run")
    header = next(i for i, l in enumerate(lines) if l.startswith("| selector |"))
    assert lines[header] == ("| selector | L_PSF | L_contrast | L_SLR_q | L_SLR_i | Mean | seeds | "
                             "median Mean [IQR] | CI of median (coverage) | p vs random (Holm) | A vs random |")
    body = lines[header + 2:]
    assert [l.split(" | ")[0] for l in body] == ["| full", "| uniform", "| random", "| ste"]
    comp = load_comparison(finished)
    t1 = comp.table.set_index("config")
    st = comp.stats.set_index("config")
    best = t1.drop("full")["Mean"].idxmin()
    row = next(l for l in body if l.startswith(f"| {best} |"))
    assert f"**{float(t1.loc[best, 'Mean']):.4g}**" in row             # the best listed Mean in bold
    ste = next(l for l in body if l.startswith("| ste |")).split(" | ")
    assert ste[6] == "3"
    assert ste[7] == f"{st.loc['ste', 'Mean_median']:.4g} [{st.loc['ste', 'Mean_iqr']:.2g}]"
    assert ste[8] == "n/a"                                              # 3 seeds: too few for 90 %
    assert ste[9] == f"{st.loc['ste', 'p_vs_random_holm']:.2g}"
    assert ste[10].rstrip(" |") == f"{st.loc['ste', 'A_vs_random']:.2g}"
    uniform = next(l for l in body if l.startswith("| uniform |")).split(" | ")
    assert uniform[6] == "1 (deterministic)" and uniform[8:10] == ["-", "-"]   # no interval, no test


def test_latex_table_written_to_a_file(finished, tmp_path, capsys):
    out = tmp_path / "sub" / "table.tex"
    assert cli.main(["report", str(finished), "--format", "latex", "--out", str(out)]) == 0
    cap = capsys.readouterr()
    assert cap.out == "" and f"wrote {out}" in cap.err
    tex = out.read_text()
    assert tex.startswith("\\begin{table}\n\\centering\n\\caption{Scene toy, k = 8 of 16")
    assert "at least 90 \\%" in tex and tex.rstrip().endswith("\\end{table}")
    lines = tex.splitlines()
    assert lines[lines.index("\\toprule") - 1] == "\\begin{tabular}{lrrrrrrrrrr}"
    head = lines[lines.index("\\toprule") + 1]
    assert head.startswith("selector & $\\mathcal{L}_{\\mathrm{PSF}}$ & $\\mathcal{L}_{\\mathrm{contrast}}$ & "
                           "$\\mathcal{L}_{\\mathrm{SLR},q}$ & $\\mathcal{L}_{\\mathrm{SLR},i}$ & Mean")
    rows = lines[lines.index("\\midrule") + 1:lines.index("\\bottomrule")]
    assert [r.split(" & ")[0] for r in rows] == ["full", "uniform", "random", "ste"]
    assert all(r.endswith("\\\\") and r.count(" & ") == 10 for r in rows)
    assert sum("\\textbf{" in r for r in rows) == 1
    assert tex == render(finished, "latex")


def test_latex_escapes_and_powers_of_ten(finished):
    comp = load_comparison(finished)
    comp.table.loc[0, "L_PSF"] = 5.4864e-10
    comp.table.loc[1, "config"] = "my_sel(a=1%)"
    comp.stats.loc[1, "config"] = "my_sel(a=1%)"
    from arraysel.report.summary import to_latex

    tex = to_latex(comp)
    assert "$5.486\\times10^{-10}$" in tex and "my\\_sel(a=1\\%)" in tex
    assert summary_rows(comp)[0]["L_PSF"] == "5.486e-10"


def test_rebuild_writes_the_tables(finished, tmp_path, capsys):
    folder = _copy(finished, tmp_path / "c")
    (folder / "stats.csv").unlink()
    (folder / "table1.csv").write_text("config\nstale\n")
    assert cli.main(["report", str(folder), "--rebuild"]) == 0
    assert f"wrote {folder / 'stats.csv'}" in capsys.readouterr().err
    assert (folder / "table1.csv").read_text() == (finished / "table1.csv").read_text()
    assert (folder / "stats.csv").read_text() == (finished / "stats.csv").read_text()


def _error(argv, capsys) -> str:
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("arraysel report: error: ")
    return err


def test_errors_for_folders_that_are_not_finished_comparisons(finished, tmp_path, capsys):
    assert "is not a folder" in _error(["report", str(tmp_path / "nope")], capsys)
    assert "has no run.json" in _error(["report", str(tmp_path)], capsys)
    running = _copy(finished, tmp_path / "running")
    meta = json.loads((running / "run.json").read_text())
    (running / "run.json").write_text(json.dumps({**meta, "status": "interrupted"}))
    assert "is not finished (run.json status: 'interrupted')" in _error(["report", str(running)], capsys)
    bad = _copy(finished, tmp_path / "bad")
    (bad / "run.json").write_text("{not json")
    assert "run.json cannot be read" in _error(["report", str(bad)], capsys)
    (bad / "run.json").write_text(json.dumps({"status": "finished"}))
    assert "is not the run.json of `arraysel compare`" in _error(["report", str(bad)], capsys)
    norows = _copy(finished, tmp_path / "norows")
    (norows / "runs.csv").unlink()
    assert "has no runs.csv" in _error(["report", str(norows)], capsys)
    pd.read_csv(finished / "runs.csv").drop(columns=["Mean"]).to_csv(norows / "runs.csv", index=False)
    assert "lacks the column(s) Mean" in _error(["report", str(norows)], capsys)
    assert "--out" in _error(["report", str(finished), "--out", str(tmp_path)], capsys)  # a folder
    with pytest.raises(SystemExit):
        cli.main(["report", str(finished), "--format", "html"])


def test_the_interval_is_labelled_with_its_exact_coverage(tmp_path, capsys):
    reg = get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))
    compare(ToyObjective(16, 8), ["random", "ste"], out_dir=tmp_path, seeds=[0, 1, 2, 3, 4],
            budget=Budget(evaluations=30), registry=reg, progress=False, figures=False)
    assert cli.main(["report", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| 93.8 % CI of median |" in out                    # 5 seeds: [min, max], 1 - 2/32
    st = load_comparison(tmp_path).stats.set_index("config")
    runs = pd.read_csv(tmp_path / "runs.csv")
    means = runs.loc[runs["config"] == "ste", "Mean"]
    assert (st.loc["ste", "Mean_median_ci_low"], st.loc["ste", "Mean_median_ci_high"]) == (means.min(), means.max())
    assert cli.main(["report", str(tmp_path), "--ci-level", "0.95"]) == 0
    assert "| CI of median (coverage) |" in capsys.readouterr().out   # 6 seeds needed: n/a
    assert "between 0 and 1" in _error(["report", str(tmp_path), "--ci-level", "95"], capsys)


def test_an_older_folder_reports_with_todays_statistics(finished, tmp_path, capsys):
    """A folder written before the deterministic flag and the order-statistic interval: an older
    stats.csv, run.json without 'deterministic', uniform run once per seed."""
    old = _copy(finished, tmp_path / "old")
    meta = json.loads((old / "run.json").read_text())
    for d in meta["selectors"]:
        d.pop("deterministic")
    (old / "run.json").write_text(json.dumps(meta))
    runs = pd.read_csv(old / "runs.csv", keep_default_na=False)
    uni = runs[runs["config"] == "uniform"]
    runs = pd.concat([runs] + [uni.assign(seed=s) for s in (1, 2)])
    runs.to_csv(old / "runs.csv", index=False)
    pd.read_csv(old / "stats.csv").drop(columns=["deterministic", "Mean_median_ci_level", "p_vs_random_holm",
                                                 "A_vs_random"]).to_csv(old / "stats.csv", index=False)
    assert cli.main(["report", str(old)]) == 0
    uniform = next(l for l in capsys.readouterr().out.splitlines() if l.startswith("| uniform |")).split(" | ")
    assert uniform[6] == "3 (deterministic)" and uniform[8:10] == ["-", "-"]
    assert cli.main(["report", str(old), "--rebuild"]) == 0
    assert pd.read_csv(old / "stats.csv").set_index("config").loc["uniform", "deterministic"]


@pytest.mark.parametrize("name", ["compare-60s", "compare-20s"])
def test_committed_comparisons_report(name):
    """The committed example folders read as finished comparisons; their statistics are those of
    runs.csv (the medians their README quotes)."""
    folder = RESULTS / name
    comp = load_comparison(folder)
    runs = comp.runs
    for config, s in comp.stats.set_index("config").iterrows():
        means = runs.loc[runs["config"] == config, "Mean"].dropna()
        assert s["Mean_median"] == pytest.approx(means.median())
    committed = pd.read_csv(folder / "table1.csv", keep_default_na=False)
    assert list(committed.columns) == list(comp.table.columns)
    assert committed["Mean"].to_numpy() == pytest.approx(comp.table["Mean"].to_numpy().astype(float))
    assert "| swap |" in render(folder, "md")


# ---------------------------------------------------------------------------
# one figure style for compare, psf --plot and train figures
# ---------------------------------------------------------------------------

def _all_figures():
    import numpy as np

    from arraysel.e2e import figures as e2e
    from arraysel.report import plots

    rng = np.random.default_rng(0)
    k = rng.normal(size=(3, 17, 17)) + 1j * rng.normal(size=(3, 17, 17))
    ref = k[0] * 2
    masks = np.zeros((2, 8), dtype=bool)
    masks[0, ::2] = masks[1, :4] = True
    trace = pd.DataFrame({"config": ["a"] * 3 + ["b"] * 2, "seed": [0, 0, 0, 0, 0],
                          "seconds": [0.1, 1.0, 2.0, 0.2, 2.0], "evaluations": [1, 10, 20, 1, 20],
                          "gradient_steps": 0, "best_Mean": [0.5, 0.3, 0.3, 0.4, 0.4],
                          "event": ["improvement", "improvement", "end", "improvement", "end"]})
    return {
        "masks": plots.masks_figure(["a", "b"], masks),
        "psfs": plots.psfs_figure(["a", "b"], k[1:], ref, 1e-4),
        "profiles": plots.profiles_figure(["a", "b"], k[1:], ref, 1e-4),
        "trace": plots.trace_figure(trace, 0.1),
        "anytime": plots.plot_anytime(trace, 0.1),
        "psf --plot": plots.psf_figure(k[1], ref, 1e-4, [0, 2, 4], 8),
        "train fig_mask": e2e.fig_mask({"learned": [0, 2, 5], "uniform": [0, 3, 6]}, 8),
        "train fig_psf": e2e.fig_psf({"learned": k[1], "uniform": k[2], "full": ref}, ref, 1e-4),
        "train fig_loss": e2e.fig_loss([{"total": 1.0, "psf": 0.5}, {"total": 0.5, "psf": 0.2}]),
    }


def test_every_figure_has_the_one_style_whatever_the_callers_settings():
    import matplotlib
    from matplotlib.image import AxesImage

    from arraysel.report import plots

    loud = {"font.size": 20.0, "axes.titlesize": 21.0, "xtick.labelsize": 19.0, "ytick.labelsize": 19.0,
            "legend.fontsize": 18.0, "image.cmap": "viridis"}
    with matplotlib.rc_context(loud):
        figs = _all_figures()
        assert matplotlib.rcParams["axes.titlesize"] == 21.0  # the caller's settings are left alone
    style = plots.STYLE
    for name, fig in figs.items():
        fig.canvas.draw()  # ticks and legends laid out (outside the style context)
        for ax in fig.axes:
            if ax.get_title():
                assert ax.title.get_fontsize() == style["axes.titlesize"], name
            labels = [t for t in ax.get_xticklabels() if t.get_text()]
            if labels and ax.get_label() != "<colorbar>":
                assert labels[0].get_fontsize() == style["xtick.labelsize"], name
                assert labels[0].get_fontfamily() == [style["font.family"]], name
            if ax.get_legend() is not None:
                assert ax.get_legend().get_texts()[0].get_fontsize() == style["legend.fontsize"], name
            for im in ax.get_images():
                assert isinstance(im, AxesImage)
                if im.get_cmap().name == plots.IMAGE_CMAP:  # a PSF: the one dB range
                    assert im.get_clim() == (-plots.DYN_RANGE_DB, 0), name
                else:
                    assert im.get_cmap().name == plots.MASK_CMAP and im.get_clim() == (0, 1), name
    for name in ("psfs", "psf --plot", "train fig_psf"):  # PSF images in mm
        assert "x (mm)" in [ax.get_xlabel() for ax in figs[name].axes], name
    for name in ("profiles", "train fig_psf"):
        assert "lateral distance from the peak (mm)" in [ax.get_xlabel() for ax in figs[name].axes], name


def test_compare_psf_and_train_figures_are_saved_alike(tmp_path):
    from PIL import Image

    from arraysel.e2e import figures as e2e
    from arraysel.report import plots

    assert e2e.save_figure is plots.save_figure
    figs = _all_figures()
    for i, fig in enumerate((figs["psfs"], figs["psf --plot"], figs["train fig_psf"])):
        e2e.save_figure(fig, tmp_path / f"{i}.png")
        with Image.open(tmp_path / f"{i}.png") as im:
            assert im.info["dpi"] == pytest.approx((plots.DPI, plots.DPI), abs=0.01)
