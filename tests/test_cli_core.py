"""``arraysel psf`` and ``arraysel evaluate`` (run through the installed entry point's main)."""
import numpy as np
import pandas as pd
import pytest

from arraysel.cli.main import main


def test_psf_command_writes_kernel_and_png(tmp_path, paper_objective):
    out = tmp_path / "psf.npz"
    assert main(["psf", "--elements", ",".join(map(str, range(0, 64, 2))), "--out", str(out), "--plot"]) == 0
    data = np.load(out)
    assert data["psf"].shape == (128, 128) and np.iscomplexobj(data["psf"])
    assert np.isclose(np.linalg.norm(data["psf"]), 1.0, atol=1e-5)
    assert abs(float(data["L_PSF"]) - 0.0522) / 0.0522 < 0.1
    assert (tmp_path / "psf.png").stat().st_size > 1000


def test_evaluate_command(tmp_path, paper_objective):
    masks = tmp_path / "masks.txt"
    uni = " ".join(map(str, range(0, 64, 2)))
    full_half = ",".join(map(str, range(32)))
    masks.write_text(f"# two masks\n{uni}\n\n{full_half}  # contiguous\n")
    out = tmp_path / "metrics.csv"
    psf = tmp_path / "k.npz"
    assert main(["evaluate", "--masks", str(masks), "--out", str(out), "--psf-out", str(psf)]) == 0
    df = pd.read_csv(out)
    assert list(df.columns) == ["elements", "L_PSF", "L_contrast", "L_SLR_q", "L_SLR_i", "L_SLR", "Mean"]
    assert len(df) == 2
    assert df["L_PSF"].iloc[0] == pytest.approx(0.0522, rel=0.1)
    d = np.load(psf)
    assert d["psf"].shape == (2, 128, 128) and d["psf_ref"].shape == (128, 128)


@pytest.mark.parametrize("line,msg", [
    ("0 1 1" + "".join(f" {i}" for i in range(2, 31)), "repeated"),
    ("-1" + "".join(f" {i}" for i in range(1, 32)), "in \\[0, 63\\]"),
    ("0 1 64" + "".join(f" {i}" for i in range(2, 31)), "in \\[0, 63\\]"),
    ("0 1 2", "expected k = 32"),
    ("0 1 x", "not an integer"),
])
def test_evaluate_rejects_bad_masks_with_line_number(tmp_path, capsys, line, msg):
    masks = tmp_path / "masks.txt"
    masks.write_text(" ".join(map(str, range(32))) + "\n# comment\n" + line + "\n")
    out = tmp_path / "metrics.csv"
    assert main(["evaluate", "--masks", str(masks), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "line 3" in err
    import re
    assert re.search(msg, err)
    assert not out.exists()


def test_malloc_tuning_is_optional_and_idempotent(monkeypatch):
    from arraysel.io import allocator

    monkeypatch.setattr(allocator, "_state", {})
    monkeypatch.setenv("ARRAYSEL_MALLOC_TUNE", "off")
    assert allocator.malloc_tuning_enabled() is False
    assert allocator.tune_malloc() is False
    monkeypatch.setattr(allocator, "_state", {})
    monkeypatch.setenv("ARRAYSEL_MALLOC_TUNE", "1")
    first = allocator.tune_malloc()
    assert first is (allocator._glibc() is not None)  # in effect exactly where glibc is present
    assert allocator.tune_malloc() is first


def test_malloc_tuned_applies_the_settings_for_a_block_only(monkeypatch):
    """The basis build's scoped tuning: the settings inside the block, glibc's defaults and a
    trim after it (also after an error); nothing where tune_malloc is in effect or tuning is
    disabled."""
    from arraysel.io import allocator

    calls = []

    class FakeLibc:
        def mallopt(self, key, value):
            calls.append(("mallopt", key, value))
            return 1

        def malloc_trim(self, pad):
            calls.append(("trim", pad))
            return 1

    fake = FakeLibc()
    monkeypatch.setattr(allocator, "_glibc", lambda: fake)
    monkeypatch.setattr(allocator, "_state", {})
    monkeypatch.setenv("ARRAYSEL_MALLOC_TUNE", "1")
    with pytest.raises(RuntimeError):
        with allocator.malloc_tuned():
            assert calls == [("mallopt", allocator._M_MMAP_MAX, 0),
                             ("mallopt", allocator._M_TRIM_THRESHOLD, allocator._TRIM_BYTES)]
            raise RuntimeError("the build failed")
    assert calls[2:] == [("mallopt", allocator._M_MMAP_MAX, allocator._DEFAULT_MMAP_MAX),
                         ("mallopt", allocator._M_TRIM_THRESHOLD, allocator._DEFAULT_TRIM_BYTES),
                         ("trim", 0)]
    calls.clear()
    monkeypatch.setattr(allocator, "_state", {"done": True})  # tune_malloc in effect: kept
    with allocator.malloc_tuned():
        pass
    monkeypatch.setattr(allocator, "_state", {})
    monkeypatch.setenv("ARRAYSEL_MALLOC_TUNE", "0")
    with allocator.malloc_tuned():
        pass
    assert calls == []


def test_default_time_budget_is_a_share_of_the_total():
    """Without --budget-s the runs share DEFAULT_TOTAL_S (7 min): 38 s each for the main job's 11
    runs (ste and random x 5 seeds, uniform once), 120 s at most, 10 s at least."""
    from arraysel.cli.compare import DEFAULT_TOTAL_S, default_budget_s

    assert DEFAULT_TOTAL_S == 420
    assert default_budget_s(11) == 38
    assert default_budget_s(1) == default_budget_s(3) == 120
    assert default_budget_s(10 * 5) == 10
    assert default_budget_s(0) == 120


def test_compare_default_budget_recorded_and_kept_on_resume(tmp_path, monkeypatch, capsys):
    """The default budget is announced, written to run.json, and a --resume without --budget-s
    takes the resumed runs' budget (adding a seed would otherwise change the share and be refused)."""
    import json

    import arraysel.cli.compare as cc

    monkeypatch.setattr(cc, "DEFAULT_TOTAL_S", 6.0)
    monkeypatch.setattr(cc, "DEFAULT_MIN_S", 0.5)
    out = tmp_path / "cmp"
    args = ["compare", "--selectors", "random,uniform", "--scene", "toy", "--out", str(out),
            "--budget-evals", "50", "--no-figures", "--no-progress", "--in-process"]
    assert main(args + ["--seeds", "0,1"]) == 0
    assert "3 run(s) of 2 s each" in capsys.readouterr().err
    meta = json.loads((out / "run.json").read_text())
    assert meta["budget"]["seconds"] == cc.default_budget_s(3) == 2
    assert cc.default_budget_s(5) == 1                               # a new share would differ
    first = meta["budget"]["seconds"]
    assert main(args + ["--seeds", "0,1,2,3", "--resume"]) == 0
    assert "run(s) of" not in capsys.readouterr().err                # the resumed budget, not a new share
    meta = json.loads((out / "run.json").read_text())
    assert meta["budget"]["seconds"] == first
    runs = pd.read_csv(out / "runs.csv")
    assert sorted(runs.loc[runs.config == "random", "seed"]) == [0, 1, 2, 3]
