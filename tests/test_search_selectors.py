"""Issue 13: the runner's bookkeeping (BudgetedObjective), the combinatorial selectors on a
planted problem, polish, seeds over selectors, table statistics, IOHprofiler output, figures."""
from __future__ import annotations

import itertools
import json
import math
import warnings

import numpy as np
import pandas as pd
import pytest

from arraysel.errors import ParameterError
from arraysel.selectors.registry import build_plugin_manager, get_registry
from arraysel.report.plots import plot_anytime
from arraysel.run.compare import DEFAULT_SEEDS, compare
from arraysel.run.experiment import Experiment
from arraysel.selectors.contract import Budget, BudgetedObjective, BudgetExhausted, Recorder, Selector, numpy_rng
from arraysel.testing import ToyObjective
from support import PLAIN



@pytest.fixture(scope="module")
def reg():
    return get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))


def brute_force_optimum(n: int, k: int) -> tuple[list[int], float]:
    obj = ToyObjective(n, k)
    combos = np.array(list(itertools.combinations(range(n), k)))
    masks = np.zeros((len(combos), n), dtype=bool)
    np.put_along_axis(masks, combos, True, axis=1)
    means = obj.evaluate(masks)["Mean"]
    i = int(np.argmin(means))
    return combos[i].tolist(), float(means[i])


# ---------------------------------------------------------------------------
# the budgeted objective
# ---------------------------------------------------------------------------

def _view(evaluations=None, seconds=None, k=4, n=8):
    obj = ToyObjective(n, k)
    budget = Budget(seconds=seconds, evaluations=evaluations).start(obj)
    rec = Recorder(obj, budget)
    return obj, BudgetedObjective(obj, budget, rec, k), rec


def test_budgeted_objective_scores_the_allowed_part_then_raises():
    obj, view, rec = _view(evaluations=5)
    masks = np.zeros((8, 8), dtype=bool)
    for i in range(8):
        masks[i, [(i + j) % 8 for j in range(4)]] = True
    with pytest.raises(BudgetExhausted, match="5 of 8 masks"):
        view.evaluate(masks)
    assert obj.evaluations == 5
    assert rec.best is not None and rec.reports >= 1
    means = obj.evaluate(masks[:5])["Mean"]
    assert rec.best_mean == pytest.approx(float(np.min(means)))
    # the trace row sits at the evaluation that found the best, not at the end of the batch
    assert rec.rows[-1]["evaluations"] == int(np.argmin(means)) + 1
    with pytest.raises(BudgetExhausted):
        view.evaluate(masks[:1])
    with pytest.raises(BudgetExhausted):
        view.mask_loss(np.ones((1, 8)))


def test_budgeted_objective_records_only_k_selections_and_passes_attributes():
    obj, view, rec = _view(evaluations=100)
    view.evaluate(np.ones((2, 8), dtype=bool))  # 8 active elements, k = 4: not a selection
    assert rec.best is None and obj.evaluations == 2
    assert view.n_elements == 8 and view.device == obj.device and view.scene is obj.scene
    assert view.evaluations == 2 and view.remaining() == 98
    assert view.score_indices([[0, 2, 4, 6]]).shape == (1,)
    assert view.best == [0, 2, 4, 6]


class Endless(Selector):
    name = "endless"
    description = "scores random selections until the runner stops it"

    def select(self, objective, k, seed):
        rng = np.random.default_rng(seed)
        while True:
            masks = np.zeros((7, objective.n_elements), dtype=bool)
            for m in masks:
                m[rng.choice(objective.n_elements, k, replace=False)] = True
            objective.evaluate(masks)


def test_new_style_selector_holds_only_its_search():
    exp = Experiment(ToyObjective(12, 6), Endless, budget=Budget(evaluations=50), seed=1)
    row = exp.run()
    assert row["error"] == "" and row["evaluations"] == 50       # clipped exactly, no overrun
    assert exp.trace[-1]["event"] == "end" and exp.trace[-1]["evaluations"] == 50
    best = min(t["best_Mean"] for t in exp.trace)
    assert row["Mean"] == pytest.approx(best, rel=1e-6)           # the best recorded is returned


def test_time_budget_stops_a_large_batch():
    obj = ToyObjective(12, 6, delay=0.05, chunk=4)
    row = Experiment(obj, Endless, budget=Budget(seconds=0.5), seed=0).run()
    assert row["error"] == "" and row["seconds"] < 2.0


# ---------------------------------------------------------------------------
# the combinatorial selectors find the planted optimum
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("name,options,seeds", [
    ("swap", {}, (0, 1)),
    ("swap", {"start": "random", "mode": "best"}, (0,)),
    ("swap", {"elements": "0 1 2 3 4 5 6"}, (0,)),
    ("swap", {"start": "chirp", "fresh": "chirp"}, (0, 1)),
    ("swap", {"race": 4, "race_quota": 50}, (0, 1)),
    ("swap", {"lead": 2, "chunk": 16}, (0, 1)),
    ("swap", {"race": 6, "race_quota": 20, "fresh": "mixed", "race_chirps": 4}, (0,)),
    ("swap", {"race": 3, "race_quota": 20, "fresh": "chirp", "max_perturb": 4}, (0,)),
    ("swap", {"race": 5, "race_quota": 20, "fresh": "mixed", "restart_after": 3}, (0, 1)),
    ("ils", {"fresh": "mixed"}, (0, 1)),
    ("ils", {}, (0, 1, 2)),
    ("ils", {"mode": "best", "relink": 1.0}, (0, 1)),
    ("ils", {"start": "chirp", "fresh": "chirp"}, (0, 1, 2)),
    ("anneal", {}, (0, 1)),
    ("genetic", {}, (0, 1)),
    ("memetic", {}, (0, 1, 2)),
    ("memetic", {"scan": 1.0, "guide": 0.0}, (0,)),
    ("memetic", {"init": "chirp"}, (0, 1)),
    ("genetic", {"init": "chirp"}, (0,)),
    ("swap", {"model": "quadratic"}, (0, 1)),
    ("swap", {"model": "quadratic", "refresh": 1, "scan": 0.2, "guide": 0.875, "race": 3, "race_quota": 40}, (0, 1)),
    ("nevergrad", {}, (0,)),
    ("nevergrad", {"encoding": "binary", "optimizer": "DiscreteOnePlusOne"}, (0, 1, 2)),
    ("uniform", {"polish": 0.9}, (0,)),
])
def test_selector_finds_the_planted_optimum(reg, name, options, seeds):
    if name == "nevergrad":
        pytest.importorskip("nevergrad")
    best, best_mean = brute_force_optimum(14, 7)
    for seed in seeds:
        row = Experiment(ToyObjective(14, 7), name, options=options, budget=Budget(evaluations=1500),
                         seed=seed, registry=reg).run()
        assert row["error"] == ""
        assert row["elements"] == " ".join(map(str, best)), (seed, row["Mean"], best_mean)


def test_nevergrad_binary_lamarck_repair_tells_exact_k_points(reg, monkeypatch):
    ng = pytest.importorskip("nevergrad")
    told = []
    tell = ng.optimizers.base.Optimizer.tell

    def spy(self, candidate, loss, *args, **kwargs):
        told.append(int(np.sum(np.asarray(candidate.value) > 0)))
        return tell(self, candidate, loss, *args, **kwargs)

    monkeypatch.setattr(ng.optimizers.base.Optimizer, "tell", spy)
    row = Experiment(ToyObjective(14, 7), "nevergrad", options={"encoding": "binary",
                     "optimizer": "DiscreteOnePlusOne"}, budget=Budget(evaluations=200), seed=0,
                     registry=reg).run()
    assert row["error"] == "" and len(told) >= 150
    assert set(told) == {7}  # every point told holds exactly k elements
    told.clear()
    row = Experiment(ToyObjective(14, 7), "nevergrad", options={"encoding": "binary", "repair": "random",
                     "optimizer": "DiscreteOnePlusOne"}, budget=Budget(evaluations=200), seed=0,
                     registry=reg).run()
    assert row["error"] == "" and len(set(told)) > 1  # the asked points, not repaired


def test_search_selectors_are_reproducible_per_seed(reg):
    for name in ("swap", "ils", "anneal", "genetic", "memetic"):
        rows = [Experiment(ToyObjective(16, 8), name, budget=Budget(evaluations=300), seed=s,
                           registry=reg).run() for s in (5, 5)]
        assert rows[0]["elements"] == rows[1]["elements"] and rows[0]["Mean"] == rows[1]["Mean"]


def test_swap_s_search_is_the_one_its_runs_use_with_its_options(reg):
    """``SwapSelector.search`` (what ``benchmarks/bench_race_funnels.py`` descends with) carries
    the selector's options, and a run through it is the selector's run."""
    from arraysel.selectors.localsearch import SwapSearch
    from arraysel.selectors.starts import start_selection

    sel = reg["swap"](lead=4, race=3, chunk=16, start="random")
    _, view, rec = _view(evaluations=400, k=8, n=16)
    rng = numpy_rng(7)
    start = start_selection("random", view, 8, rng)  # the plugin draws its start first
    search = sel.search(view, 8, rng)
    assert isinstance(search, SwapSearch)
    assert (search.lead, search.race, search.chunk, search.fresh, search.shift) == (4, 3, 16, "mixed", 6)
    with pytest.raises(BudgetExhausted):
        search.run(start)
    row = Experiment(ToyObjective(16, 8), "swap", options={"lead": 4, "race": 3, "chunk": 16, "start": "random"},
                     budget=Budget(evaluations=400), seed=7, registry=reg).run()
    assert row["elements"] == " ".join(map(str, rec.best)) and row["Mean"] == pytest.approx(rec.best_mean)


def test_swap_settings_are_one_set_of_defaults_and_the_searches_are_presets_of_it(reg):
    """``SwapSettings()`` holds swap's measured defaults; swap, polish, memetic and ils are presets of
    it that differ where docs/selectors.md says; a selector's declared options default to its preset."""
    import dataclasses

    from arraysel.selectors.swapsettings import GROUPS, ILS, MEMETIC, POLISH, SWAP, SwapSettings, swap_options

    assert SWAP == SwapSettings() and dataclasses.asdict(SWAP) == dict(
        mode="first", chunk=64, lead=0, guide=0.875, scan=0.125, compound=0, model=None, refresh=8,
        gradient="update", shift=6, shift_len=24, shift_scan=512, pairs=0, guide_shifts=True, perturb=2,
        max_perturb=2, restart_after=30, fresh="mixed", race=16, race_quota=None, race_chirps=None)

    def changes(preset):
        return {k: v for k, v in dataclasses.asdict(preset).items() if getattr(SWAP, k) != v}

    assert changes(POLISH) == {"race": 1} and changes(MEMETIC) == {}
    assert changes(ILS) == {"max_perturb": 8, "restart_after": 40, "fresh": "random", "race": 1}
    grouped = [n for names in GROUPS.values() for n in names]
    assert sorted(grouped + ["guide_shifts"]) == sorted(dataclasses.asdict(SWAP))   # every setting, once
    for name, preset in (("swap", SWAP), ("ils", ILS), ("memetic", MEMETIC)):
        declared = {k: o.default for k, o in reg[name].options.items() if k in grouped}
        assert declared == {k: getattr(preset, k) for k in declared}, name
    assert set(swap_options(SWAP)) == set(grouped) and {k for k in reg["swap"].options if k in grouped} == set(grouped)
    with pytest.raises(ParameterError, match="no setting bogus"):
        SWAP.replace(bogus=1)
    with pytest.raises(ParameterError, match="scan"):
        SwapSettings(scan=0.0)


def test_bad_options_name_the_option(reg):
    # start elements are checked against Ne and k when the run starts: the message lands in the row
    row = Experiment(ToyObjective(14, 7), "swap", options={"elements": "0 1 2"}, registry=reg,
                     budget=Budget(evaluations=10)).run()
    assert "ParameterError: option elements: expected k = 7 elements, got 3" in row["error"]
    row = Experiment(ToyObjective(14, 7), "swap", options={"elements": "0 1 2 3 4 5 99"}, registry=reg,
                     budget=Budget(evaluations=10)).run()
    assert "option elements: element indices must be in [0, 13], got [99]" in row["error"]
    with pytest.raises(ParameterError, match=r"swap.polish = 2.0 is out of range; allowed: \[0.0, 0.9\]"):
        reg["swap"](polish=2.0)
    pytest.importorskip("nevergrad")
    with pytest.raises(ParameterError, match="nevergrad.optimizer = 'NoSuchOpt' is not a nevergrad optimizer"):
        reg["nevergrad"](optimizer="NoSuchOpt")


def test_a_start_is_the_run_s_fallback_when_the_budget_ends_first(reg):
    # the greedy start needs about Ne^2/2 evaluations: with 10, no selection of k elements is
    # scored, and the run returns the greedy start (finished from its last ranking) instead of failing
    for name in ("swap", "ils", "anneal"):
        row = Experiment(ToyObjective(14, 7), name, options={"start": "greedy"}, budget=Budget(evaluations=10),
                         seed=0, registry=reg).run()
        assert row["error"] == "" and len(row["elements"].split()) == 7, (name, row["error"])


def test_elite_search_keeps_distinct_elites_and_relinks_between_them():
    from arraysel.selectors.localsearch import EliteSearch
    from arraysel.selectors.contract import numpy_rng

    obj, view, rec = _view(evaluations=20000, k=10, n=20)
    search = EliteSearch(view, 10, numpy_rng(0), starts=4, elite=4, relink=0.5, max_rounds=40)
    best, value = search.run(list(range(10)))
    values = [v for v, _, _ in search.pool]
    keys = [k for _, k, _ in search.pool]
    assert 1 <= len(keys) == len(set(keys)) <= 4 and values == sorted(values)
    assert value == values[0] == rec.best_mean and best == rec.best
    # a path from a towards b: each step one swap of an element of a \ b for one of b \ a; the
    # result lies strictly between them (k elements, neither end), and it was scored
    rng = np.random.default_rng(1)
    a, b = np.zeros(20, bool), np.zeros(20, bool)
    a[rng.choice(20, 10, replace=False)] = True
    b[rng.choice(20, 10, replace=False)] = True
    mask, v = search.relink(a, b)
    assert mask.sum() == 10 and (mask != a).any() and (mask != b).any()
    assert (mask & a & b).sum() == (a & b).sum()  # what both ends share stays
    assert v == pytest.approx(float(obj.evaluate(mask[None])["Mean"][0]))
    assert search.relink(a, a) is None


def test_polish_improves_on_the_selector_within_the_same_budget(reg):
    plain = Experiment(ToyObjective(16, 8), "random", budget=Budget(evaluations=400), seed=2,
                       registry=reg).run()
    polished_exp = Experiment(ToyObjective(16, 8), "random", options={"polish": 0.5},
                              budget=Budget(evaluations=400), seed=2, registry=reg)
    polished = polished_exp.run()
    assert polished["config"] == "random(polish=0.5)" and polished["error"] == ""
    assert polished["evaluations"] <= 400
    assert polished["Mean"] < plain["Mean"]


# ---------------------------------------------------------------------------
# compare: seeds, statistics, IOHprofiler, figures
# ---------------------------------------------------------------------------

def test_default_seeds_run_deterministic_selectors_once(reg, tmp_path):
    compare(ToyObjective(12, 6), ["uniform", "random"], out_dir=tmp_path, budget=Budget(evaluations=30),
            registry=reg, progress=False, figures=False)
    runs = pd.read_csv(tmp_path / "runs.csv")
    assert list(runs[runs["config"] == "uniform"]["seed"]) == [DEFAULT_SEEDS[0]]
    assert list(runs[runs["config"] == "random"]["seed"]) == list(DEFAULT_SEEDS)
    t1 = pd.read_csv(tmp_path / "stats.csv").set_index("config")
    means = runs[runs["config"] == "random"]["Mean"].to_numpy()
    assert t1.loc["random", "Mean_median"] == pytest.approx(np.median(means))
    assert t1.loc["random", "Mean_best"] == pytest.approx(means.min())
    q25, q75 = np.percentile(means, [25, 75])
    assert t1.loc["random", "Mean_iqr"] == pytest.approx(q75 - q25)
    assert t1.loc["random", "n_seeds"] == 5 and t1.loc["uniform", "n_seeds"] == 1


def test_explicit_seeds_run_deterministic_selectors_once(reg, tmp_path):
    # identical rows per seed would only inflate the 'seeds' column and waste the budget
    compare(ToyObjective(12, 6), ["uniform", "greedy", "random"], out_dir=tmp_path, seeds=[3, 1],
            budget=Budget(evaluations=30), registry=reg, progress=False, figures=False)
    runs = pd.read_csv(tmp_path / "runs.csv")
    for det in ("uniform", "greedy"):
        assert list(runs[runs["config"] == det]["seed"]) == [3]
    assert sorted(runs[runs["config"] == "random"]["seed"]) == [1, 3]


def test_ioh_files_load_in_iohinspector_and_match_runs(reg, tmp_path):
    iohinspector = pytest.importorskip("iohinspector")
    compare(ToyObjective(16, 8), ["uniform", "ste", "swap", "greedy"], out_dir=tmp_path, seeds=[0, 1],
            budget=Budget(evaluations=200), registry=reg, progress=False, figures=False)
    runs = pd.read_csv(tmp_path / "runs.csv")
    runs = runs[runs["config"] != "full"]
    dm = iohinspector.DataManager()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dm.add_folder(str(tmp_path / "ioh"))
    ov = dm.overview.to_pandas()
    assert set(ov["algorithm_name"]) == {"uniform", "ste", "swap", "greedy"}
    assert len(ov) == len(runs)
    for config, g in runs.groupby("config"):
        o = ov[ov["algorithm_name"] == config]
        assert sorted(o["evals"]) == sorted(g["evaluations"])
        assert np.allclose(sorted(o["best_y"]), sorted(g["Mean"]), rtol=0, atol=0)
        assert set(o["dimension"]) == {16} and set(o["function_name"]) == {"toy"}
    data = dm.load(monotonic=True, include_meta_data=True).to_pandas()
    for (config, run_id), g in data.groupby(["algorithm_name", "run_id"]):
        assert g["evaluations"].min() == 1
    meta = json.loads(next((tmp_path / "ioh" / "swap").glob("IOHprofiler_*.json")).read_text())
    assert meta["maximization"] is False and len(meta["scenarios"][0]["runs"]) == 2


def test_configs_with_long_element_lists_get_short_distinct_ioh_folders(reg, tmp_path):
    # a config label that names its start elements is longer than a file name may be: its IOH
    # folder is cut and ends in a hash of the label, so two such configs keep their own folders
    n, k = 300, 150
    lists = [" ".join(map(str, range(0, 2 * k, 2))), " ".join(map(str, range(1, 2 * k, 2)))]
    configs = [("swap", {"start": "elements", "elements": e}) for e in lists]
    compare(ToyObjective(n, k), configs, out_dir=tmp_path, seeds=[0], budget=Budget(evaluations=30),
            registry=reg, progress=False, figures=False)
    runs = pd.read_csv(tmp_path / "runs.csv")
    assert set(runs["error"].fillna("")) == {""} and len(runs[runs["config"] != "full"]) == 2
    folders = sorted(p for p in (tmp_path / "ioh").iterdir())
    assert len(folders) == 2 and all(len(p.name) <= 96 for p in folders)
    names = {json.loads(next(p.glob("IOHprofiler_*.json")).read_text())["algorithm"]["name"] for p in folders}
    assert names == set(runs[runs["config"] != "full"]["config"])


def test_a_refused_ioh_export_keeps_the_runs_and_names_the_export(reg, tmp_path, monkeypatch):
    from arraysel.errors import ArrayselError
    from arraysel.report import tables

    def refuse(folder, rows, *args, **kwargs):
        if any(r.get("config") != "full" for r in rows):  # once a selector's run is there to save
            raise OSError(36, "File name too long", str(folder))
        return []

    monkeypatch.setattr(tables, "write_ioh", refuse)
    with pytest.raises(ArrayselError, match="IOHprofiler files could not be written"):
        compare(ToyObjective(12, 6), ["uniform"], out_dir=tmp_path, seeds=[0], budget=Budget(evaluations=10),
                registry=reg, progress=False, figures=False)
    runs = pd.read_csv(tmp_path / "runs.csv")
    assert list(runs["config"]) == ["full", "uniform"]
    assert (tmp_path / "table1.csv").exists() and (tmp_path / "stats.csv").exists()


def test_anytime_figure_shows_every_selector(reg, tmp_path):
    from matplotlib.figure import Figure

    compare(ToyObjective(16, 8), ["uniform", "random", "swap"], out_dir=tmp_path, seeds=[0, 1],
            budget=Budget(evaluations=100), registry=reg, progress=False)
    assert (tmp_path / "anytime.png").stat().st_size > 0
    trace = pd.read_csv(tmp_path / "trace.csv")
    fig = plot_anytime(trace, full_mean=0.01)
    assert isinstance(fig, Figure)
    ax_t, ax_e, ax_c = fig.axes[:3]
    for ax in (ax_t, ax_e, ax_c):
        labels = " ".join(line.get_label() for line in ax.get_lines())
        assert all(name in labels or name in " ".join(t.get_text() for t in (ax.get_legend().get_texts()
                                                                            if ax.get_legend() else []))
                   for name in ("uniform", "random", "swap")), labels
    # the one-evaluation run has a finite median curve
    uniform = [line for line in ax_e.get_lines() if line.get_label().startswith("uniform")]
    assert uniform and np.isfinite(uniform[0].get_ydata()).any()
    assert math.isfinite(float(np.nanmin(uniform[0].get_ydata())))


def _greedy_on(n, k, share, evaluations=None, backward=True):
    from arraysel.selectors.starts import greedy_selection

    obj, view, _ = _view(evaluations=evaluations, k=k, n=n)
    before = int(obj.evaluations)
    sel = greedy_selection(view, k, backward=backward, share=share)
    return sel, int(obj.evaluations) - before


def test_greedy_takes_one_element_a_step_when_the_budget_allows():
    from arraysel.selectors.starts import greedy_selection

    full, used = _greedy_on(24, 12, 1.0)  # no limits
    assert used == sum(range(13, 25))  # every step scores every removal
    for share in (0.5, 1.0):  # a budget with room for it changes nothing
        assert _greedy_on(24, 12, share, evaluations=10 * used) == (full, used)
    _, view, _ = _view(k=12, n=24)
    with pytest.raises(ParameterError, match="share"):
        greedy_selection(view, 12, share=0.0)


@pytest.mark.parametrize("backward", [True, False])
@pytest.mark.parametrize("evaluations", [300, 900])
def test_greedy_takes_several_elements_a_step_to_fit_its_share_of_the_budget(evaluations, backward):
    # one element a step costs (64 + 32 + 1) 32 / 2 = 1,552 evaluations (backward); with a share
    # of 0.5 the greedy must stay near half of the budget and still return k elements
    sel, used = _greedy_on(64, 32, 0.5, evaluations=evaluations, backward=backward)
    assert len(sel) == len(set(sel)) == 32 and all(0 <= i < 64 for i in sel)
    assert used <= 0.5 * evaluations + 64, used  # its share, give or take the last step
    assert _greedy_on(64, 32, 0.5, evaluations=evaluations, backward=backward) == (sel, used)  # reproducible


def test_a_greedy_start_leaves_the_search_its_share_of_the_budget(reg):
    # on 64 elements a one-a-step greedy start would use 1,552 of 1,000 evaluations and leave the
    # swap search nothing: paced, the start uses about half and the search the rest
    exp = Experiment(ToyObjective(64, 32), "swap", options={"start": "greedy"}, budget=Budget(evaluations=1000),
                     seed=0, registry=reg)
    row = exp.run()
    assert row["error"] == "" and row["evaluations"] == 1000
    first = exp.trace[0]["evaluations"]  # the first k-selection: the search's first neighbours
    assert first <= 0.5 * 1000 + 64, first
    start, _ = _greedy_on(64, 32, 0.5, evaluations=1000)
    start_mean = float(ToyObjective(64, 32).evaluate(np.isin(np.arange(64), start)[None])["Mean"][0])
    assert row["Mean"] <= start_mean


# ---------------------------------------------------------------------------
# gradient-guided neighbour order
# ---------------------------------------------------------------------------

def test_guided_chunks_cover_each_swap_once_predicted_best_first():
    from arraysel.selectors.localsearch import GuidedOrder

    rng = np.random.default_rng(0)
    a, b = rng.integers(0, 12, 40), rng.integers(0, 12, 40)
    g = rng.normal(size=12)
    pred = g[b] - g[a]                                        # the gradient's predicted change of each swap
    order = GuidedOrder(0.5)
    picks = list(order.chunks(a, b, pred, chunk=8, limit=40))
    seen = np.concatenate([p for p, _ in picks])
    assert sorted(seen.tolist()) == list(range(40))           # every swap once
    assert all(ng == 4 for _, ng in picks[:3])                # half of each chunk from the prediction
    first = picks[0][0][:4]
    assert first.tolist() == np.argsort(g[b] - g[a], kind="stable")[:4].tolist()
    # a limit stops the scan; no gradient: the random order alone
    assert sum(len(p) for p, _ in order.chunks(a, b, pred, chunk=8, limit=13)) == 13
    assert [p.tolist() for p, ng in order.chunks(a, b, None, chunk=16, limit=40)] == \
        [list(range(0, 16)), list(range(16, 32)), list(range(32, 40))]


def test_guided_chunks_with_a_lead_start_small_and_double_up_to_the_chunk():
    from arraysel.selectors.localsearch import GuidedOrder

    rng = np.random.default_rng(1)
    a, b = rng.integers(0, 30, 300), rng.integers(0, 30, 300)
    g = rng.normal(size=30)
    pred = g[b] - g[a]
    picks = list(GuidedOrder(0.5).chunks(a, b, pred, chunk=64, limit=250, lead=8))
    assert [len(p) for p, _ in picks] == [8, 16, 32, 64, 64, 64, 2]     # 250 in all
    seen = np.concatenate([p for p, _ in picks])
    assert len(set(seen.tolist())) == 250                                # no swap twice
    assert [ng for _, ng in picks[:4]] == [4, 8, 16, 32]                 # half of each from the prediction
    assert picks[0][0][:4].tolist() == np.argsort(pred, kind="stable")[:4].tolist()
    # without a prediction: the random order in the same sizes; a lead above the chunk is the chunk
    assert [p.tolist() for p, _ in GuidedOrder(0.5).chunks(a, b, None, chunk=16, limit=40, lead=4)] == \
        [list(range(0, 4)), list(range(4, 12)), list(range(12, 28)), list(range(28, 40))]
    assert [len(p) for p, _ in GuidedOrder(0.5).chunks(a, b, pred, chunk=16, limit=40, lead=32)] == [16, 16, 8]
    from arraysel.selectors.localsearch import SwapSearch
    obj = ToyObjective(12, 4)
    budget = Budget(evaluations=100).start(obj)
    with pytest.raises(ParameterError, match="lead"):
        SwapSearch(BudgetedObjective(obj, budget, Recorder(obj, budget), 4), 4, np.random.default_rng(0), PLAIN,
                   lead=-1)


def test_guided_share_follows_where_improvements_come_from_and_probes_at_zero():
    from arraysel.selectors.localsearch import GuidedOrder

    order = GuidedOrder(0.5, step=0.25, hi=0.75, probe=4)
    order.credit(True)
    order.credit(True)
    assert order.share == 0.75                                 # capped at hi
    for _ in range(3):
        order.credit(False)
    assert order.share == 0.0
    # at share 0 the gradient is asked for every probe-th move only, with the probe share
    wants = []
    for _ in range(8):
        wants.append(order.wants_gradient())
        order.credit(None)
    assert wants.count(True) == 2
    order.credit(True)                                         # a probe move found the improvement
    assert order.share == order.probe_share


class _LinearObjective(ToyObjective):
    """Mean = sum of the selected elements' costs: the first-order prediction of a swap is exact."""

    def __init__(self, n, k, cost):
        super().__init__(n, k)
        self.cost = np.asarray(cost, dtype=np.float64)

    def evaluate(self, masks):
        out = super().evaluate(masks)
        m = np.asarray(masks, dtype=np.float64).reshape(-1, self.n_elements)
        out["Mean"] = m @ self.cost
        return out

    def mask_loss(self, weights):
        import torch
        self.evaluations += int(weights.shape[0])
        if weights.requires_grad:
            self.gradient_steps += 1
        total = weights @ torch.as_tensor(self.cost, dtype=weights.dtype)
        return total, {"Mean": total}


def test_a_guided_descent_follows_an_exact_gradient_to_the_optimum_in_fewer_evaluations():
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.localsearch import SwapSearch

    n, k = 40, 10
    cost = np.random.default_rng(3).normal(size=n)
    used = {}
    for guide in (0.0, 0.5):
        obj = _LinearObjective(n, k, cost)
        budget = Budget(evaluations=100000).start(obj)
        view = BudgetedObjective(obj, budget, Recorder(obj, budget), k)
        search = SwapSearch(view, k, numpy_rng(0), PLAIN, chunk=8, guide=guide, max_rounds=0)
        start = np.zeros(n, dtype=bool)
        start[np.argsort(cost)[-k:]] = True                     # the worst selection
        mask, value = search.descend(start, float(start @ cost))
        assert sorted(np.flatnonzero(mask)) == sorted(np.argsort(cost)[:k])   # the optimum
        used[guide] = (obj.evaluations, search.moves)
        if guide:
            assert search.guide.guided_hits > 0 and search.guide.random_hits == 0
            assert search.guide.share == search.guide.hi
    # each guided move is the best swap (the worst selected element for the best other one): k
    # moves, then one scan of the whole neighbourhood shows the optimum; unguided takes more of both
    assert used[0.5][1] == k < used[0.0][1]
    assert used[0.5][0] < 0.7 * used[0.0][0]


def test_a_guided_descent_without_a_usable_gradient_scores_like_an_unguided_one():
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.localsearch import SwapSearch

    obj = _LinearObjective(20, 6, np.linspace(1, 2, 20))
    obj.mask_loss = lambda w: (w.sum(1) * 0, {})                # a zero gradient: no guidance
    plain = _LinearObjective(20, 6, np.linspace(1, 2, 20))
    plain.mask_loss = None
    got = []
    for o in (obj, plain):
        budget = Budget(evaluations=5000).start(o)
        view = BudgetedObjective(o, budget, Recorder(o, budget), 6)
        search = SwapSearch(view, 6, numpy_rng(1), PLAIN, chunk=4, guide=0.5, max_rounds=3)
        got.append(search.run(list(range(14, 20))))
    assert got[0] == got[1]


def test_perturbation_strength_grows_without_a_new_best_and_falls_back_after_one(monkeypatch):
    from arraysel.selectors import localsearch
    from arraysel.selectors.contract import numpy_rng

    calls = []  # (strength, best value before the round)
    real = localsearch.random_swaps
    holder = {}

    def recording(mask, m, rng):
        calls.append((m, holder["search"].best_value))
        return real(mask, m, rng)

    monkeypatch.setattr(localsearch, "random_swaps", recording)
    n, k = 24, 8

    class Rugged:  # a random landscape: local optima everywhere, so perturbations find new bests
        n_elements = n

        def score(self, masks):
            return np.array([np.random.default_rng(list(np.packbits(m))).random() for m in masks])

        def remaining(self):
            return math.inf

    for max_perturb in (2, 6):
        calls.clear()
        search = holder["search"] = localsearch.SwapSearch(Rugged(), k, numpy_rng(0), PLAIN, perturb=2,
                                                           max_perturb=max_perturb, restart_after=0,
                                                           max_rounds=60)
        search.run(list(range(k)))
        strengths = [m for m, _ in calls]
        assert strengths and strengths[0] == 2 and max(strengths) <= max_perturb
        # after a round that found a new best: back to perturb; after one that did not: one more
        for (a, before), (b, after) in zip(calls, calls[1:]):
            assert b == (2 if after < before else min(max_perturb, a + 1)), (a, b, before, after)
        assert max(strengths) == max_perturb                     # 2: a fixed strength; 6: grown to it
        assert sum(after < before for (_, before), (_, after) in zip(calls, calls[1:])) >= 2  # new bests
    obj = ToyObjective(n, k)
    budget = Budget(evaluations=1000).start(obj)
    view = BudgetedObjective(obj, budget, Recorder(obj, budget), k)
    # max_perturb at or below perturb: a fixed strength of perturb swaps (one meaning for every preset)
    assert localsearch.SwapSearch(view, k, numpy_rng(0), PLAIN, perturb=3, max_perturb=2).max_perturb == 3
    with pytest.raises(ParameterError, match="max_perturb"):
        localsearch.SwapSearch(view, k, numpy_rng(0), PLAIN, max_perturb=-1)


def test_a_race_keeps_the_better_half_after_each_turn_and_doubles_the_quota(monkeypatch):
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.localsearch import SwapSearch

    obj, view, _ = _view(evaluations=1000, k=4, n=8)
    search = SwapSearch(view, 4, numpy_rng(0), PLAIN, race=4, race_quota=20)
    starts = [np.array([c == "1" for c in bits]) for bits in ("11110000", "01111000", "00111100", "00011110")]
    paths = {"a": [5, 4, 3, 2, 1, 0.5], "b": [3, 2.5, 2.4, 2.3, 2.2, 2.1, 2.0], "c": [9, 8, 7], "d": [4, 1.0]}
    names = dict(zip((m.tobytes() for m in starts), "abcd"))
    steps = []

    def descent(self, mask, value):  # a descent that scores 10 selections a move
        name = names[mask.tobytes()]
        for v in paths[name]:
            self.scored += 10
            steps.append(name)
            yield mask, v

    monkeypatch.setattr(SwapSearch, "_descent", descent)
    winner = search.race_descents(starts)
    # turn 1 (20 = 2 moves each): a 4, b 2.5, c 8, d 1.0 -> d, b; turn 2 (4 moves): d is at its
    # local optimum (1.0, nothing scored), b 2.1 -> d wins; its descent is already finished
    assert steps == list("aabbccdd") + list("bbbb")
    assert winner is starts[3]


def test_a_raced_search_descends_from_fresh_starts_and_returns_its_best(monkeypatch):
    from arraysel.selectors import localsearch
    from arraysel.selectors.contract import numpy_rng

    obj, view, _ = _view(evaluations=400_000, k=10, n=40)
    fresh = []
    real = localsearch.SwapSearch._fresh_mask

    def counted(self, rng):
        fresh.append(1)
        return real(self, rng)

    monkeypatch.setattr(localsearch.SwapSearch, "_fresh_mask", counted)
    search = localsearch.SwapSearch(view, 10, numpy_rng(3), PLAIN, race=6, race_quota=40, max_rounds=6,
                                    restart_after=0)
    elements, value = search.run(list(range(10)))
    assert len(fresh) == 5 and len(elements) == 10
    mask = np.zeros(40, dtype=bool)
    mask[elements] = True
    assert value == search.best_value == pytest.approx(float(obj.evaluate(mask[None])["Mean"][0]))
    again = localsearch.SwapSearch(view, 10, numpy_rng(3), PLAIN, race=6, race_quota=40, max_rounds=6,
                                   restart_after=0).run(list(range(10)))
    assert again == (elements, value)  # reproducible per seed
    with pytest.raises(ParameterError, match="race"):
        localsearch.SwapSearch(view, 10, numpy_rng(0), PLAIN, race=0)
    with pytest.raises(ParameterError, match="race_quota"):
        localsearch.SwapSearch(view, 10, numpy_rng(0), PLAIN, race_quota=0)


def test_runs_that_score_neighbourhoods_get_a_prepared_objective_before_their_clock(reg, tmp_path):
    from arraysel.run.runners import PreparedForNeighbourhoods, RunSpec, make_runner, scores_neighbourhoods

    spec = lambda name, **o: RunSpec(name, reg[name], o, 0)
    assert all(scores_neighbourhoods(spec(n)) for n in ("swap", "ils", "anneal", "memetic"))
    assert not scores_neighbourhoods(spec("random")) and scores_neighbourhoods(spec("random", polish=0.3))

    class Prepared(ToyObjective):
        prepared = 0

        def prepare_neighbourhoods(self):
            type(self).prepared += 1

    obj = Prepared(12, 6)
    budget = Budget(evaluations=50)
    runner = make_runner(obj, budget, 5.0, 1.0, neighbourhoods=True)
    assert runner.prepare([spec("random")])["warm_steps"] and Prepared.prepared == 0
    warm = runner.prepare([spec("swap")])
    assert Prepared.prepared == 1 and warm["neighbourhoods_s"] >= 0
    # isolated or remote runs build the objective on the worker: the recipe prepares it there
    iso = make_runner(obj, budget, 5.0, 1.0, isolate=True, neighbourhoods=True,
                      objective_factory=lambda: Prepared(12, 6))
    assert isinstance(iso.factory, PreparedForNeighbourhoods)
    built = iso.factory()
    assert isinstance(built, Prepared) and Prepared.prepared == 2
    plain = make_runner(obj, budget, 5.0, 1.0, isolate=True, objective_factory=lambda: Prepared(12, 6))
    assert not isinstance(plain.factory, PreparedForNeighbourhoods)
    # compare prepares the objective when a run needs it
    Prepared.prepared = 0
    res = compare(Prepared(12, 6), ["swap", "random"], out_dir=tmp_path / "c", seeds=[0],
                  budget=Budget(evaluations=60), registry=reg, progress=False, figures=False)
    assert Prepared.prepared == 1 and not res.failures


# ---------------------------------------------------------------------------
# chirped starts, restarts and populations
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("grid", [None, (4, 6)])
def test_a_chirp_start_is_the_best_of_its_chirped_layouts(grid):
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.starts import CHIRP_CANDIDATES, chirp_masks, start_selection

    obj = ToyObjective(24, 9, grid=grid)
    budget = Budget(evaluations=10_000).start(obj)
    view = BudgetedObjective(obj, budget, Recorder(obj, budget), 9)
    start = start_selection("chirp", view, 9, numpy_rng(3))
    assert view.evaluations == CHIRP_CANDIDATES  # one call of the budget, counted
    masks = chirp_masks(obj, 9, numpy_rng(3), CHIRP_CANDIDATES)
    means = obj.evaluate(masks)["Mean"]
    assert start == np.flatnonzero(masks[int(np.argmin(means))]).tolist()


def test_a_chirp_start_whose_budget_ends_first_is_the_first_layout(reg):
    row = Experiment(ToyObjective(24, 9), "swap", options={"start": "chirp"}, budget=Budget(evaluations=10),
                     seed=0, registry=reg).run()
    assert row["error"] == "" and len(row["elements"].split()) == 9


@pytest.mark.parametrize("name", ["swap", "ils", "memetic", "genetic"])
@pytest.mark.parametrize("k", [1, 12])
def test_chirped_searches_run_at_k_1_and_k_equal_ne(reg, name, k):
    options = {"init": "chirp"} if name in ("memetic", "genetic") else {"start": "chirp", "fresh": "chirp"}
    if name == "swap":
        options["race"] = 3
    row = Experiment(ToyObjective(12, k), name, options=options, budget=Budget(evaluations=400), seed=0,
                     registry=reg).run()
    assert row["error"] == "" and len(row["elements"].split()) == k and np.isfinite(row["Mean"])


def test_fresh_chirp_restarts_are_the_best_of_their_layouts():
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.localsearch import FRESH_CHIRPS, SwapSearch
    from arraysel.selectors.starts import chirp_masks

    obj, view, _ = _view(evaluations=10_000, k=10, n=20)
    search = SwapSearch(view, 10, numpy_rng(0), PLAIN, fresh="chirp")
    mask = search._fresh_mask(numpy_rng(5))
    masks = chirp_masks(obj, 10, numpy_rng(5), FRESH_CHIRPS)
    assert (mask == masks[int(np.argmin(obj.evaluate(masks)["Mean"]))]).all()
    with pytest.raises(ParameterError, match="fresh"):
        SwapSearch(view, 10, numpy_rng(0), PLAIN, fresh="sometimes")


def _best_distinct(masks, values, m):
    """The ``m`` best distinct rows of ``masks`` by ``values`` (ties: the earlier first), found
    independently of ``arraysel.selection.survivors``."""
    distinct = {}
    for i in np.argsort(values, kind="stable"):
        distinct.setdefault(masks[i].tobytes(), masks[i])
    return list(distinct.values())[:m]


def test_chirped_race_starts_are_the_best_distinct_layouts_of_one_call():
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.localsearch import SwapSearch
    from arraysel.selectors.starts import CHIRP_CANDIDATES, chirp_masks

    obj, view, _ = _view(evaluations=100_000, k=10, n=20)
    starts = SwapSearch(view, 10, numpy_rng(7), PLAIN, fresh="chirp", race=4)._race_starts(3)
    masks = chirp_masks(obj, 10, numpy_rng(7), 3 * CHIRP_CANDIDATES)
    values = obj.evaluate(masks)["Mean"]
    expected = _best_distinct(masks, values, 3)
    assert len(starts) == 3 and all((a == b).all() for a, b in zip(starts, expected))
    randoms = SwapSearch(view, 10, numpy_rng(7), PLAIN, race=4)._race_starts(3)  # fresh = random
    assert len(randoms) == 3 and all(int(m.sum()) == 10 for m in randoms)


def test_race_chirps_sets_the_chirped_layouts_scored_for_each_chirped_race_start():
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.localsearch import SwapSearch
    from arraysel.selectors.starts import chirp_masks

    obj, view, _ = _view(evaluations=100_000, k=10, n=20)
    before = view.evaluations
    # fresh = mixed with 5 extra starts: 3 chirped, chosen from 3 x 6 layouts in one call, then 2 random
    starts = SwapSearch(view, 10, numpy_rng(4), PLAIN, fresh="mixed", race=6, race_chirps=6)._race_starts(5)
    assert view.evaluations - before == 3 * 6  # the chirped layouts' call, nothing else
    masks = chirp_masks(obj, 10, numpy_rng(4), 3 * 6)
    values = obj.evaluate(masks)["Mean"]
    expected = _best_distinct(masks, values, 3)
    assert len(starts) == 5 and all((a == b).all() for a, b in zip(starts[:3], expected))
    assert all(int(m.sum()) == 10 for m in starts)
    with pytest.raises(ParameterError, match="race_chirps"):
        SwapSearch(view, 10, numpy_rng(0), PLAIN, race_chirps=0)


def test_mixed_fresh_selections_are_chirped_and_random_in_turn():
    # fresh = mixed: a race's extra starts are the best distinct chirped layouts for half of them
    # (rounded up) and random selections for the rest; restarts alternate, chirped first
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.localsearch import FRESH_CHIRPS, SwapSearch
    from arraysel.selectors.starts import CHIRP_CANDIDATES, chirp_masks, random_mask

    obj, view, _ = _view(evaluations=100_000, k=10, n=20)
    starts = SwapSearch(view, 10, numpy_rng(7), PLAIN, fresh="mixed", race=6)._race_starts(5)
    chirped = SwapSearch(view, 10, numpy_rng(7), PLAIN, fresh="chirp", race=4)._race_starts(3)
    rng = numpy_rng(7)
    masks = chirp_masks(obj, 10, rng, 3 * CHIRP_CANDIDATES)
    randoms = [random_mask(rng, 20, 10) for _ in range(2)]
    assert len(starts) == 5 and all((a == b).all() for a, b in zip(starts, chirped + randoms))
    search = SwapSearch(view, 10, numpy_rng(0), PLAIN, fresh="mixed")
    first, second = search._fresh_mask(numpy_rng(5)), search._fresh_mask(numpy_rng(5))
    layouts = chirp_masks(obj, 10, numpy_rng(5), FRESH_CHIRPS)
    assert (first == layouts[int(np.argmin(obj.evaluate(layouts)["Mean"]))]).all()
    assert (second == random_mask(numpy_rng(5), 20, 10)).all()


def test_a_chirp_population_keeps_the_best_distinct_layouts():
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.population import CHIRP_POOL, POPULATION_OPTIONS, first_population
    from arraysel.selectors.starts import chirp_masks

    options = {name: opt.default for name, opt in POPULATION_OPTIONS.items()} | {"population": 6, "init": "chirp"}
    obj, view, _ = _view(evaluations=10_000, k=10, n=20)
    pop, fit = first_population(view, 10, numpy_rng(2), options)
    pool = chirp_masks(obj, 10, numpy_rng(2), CHIRP_POOL * 6)
    means = obj.evaluate(pool)["Mean"]
    assert pop.shape == (6, 20) and (pop.sum(axis=1) == 10).all()
    assert len({m.tobytes() for m in pop}) == 6 and (np.diff(fit) >= 0).all()
    assert fit[0] == pytest.approx(means.min())


# ---------------------------------------------------------------------------
# segment shifts: the second neighbourhood of a descent
# ---------------------------------------------------------------------------

def test_shift_moves_rotate_one_segment_and_keep_k():
    from arraysel.selectors.localsearch import shift_moves, shifted_masks

    n, longest, most = 11, 5, 2
    moves = shift_moves(n, longest, most)
    # length 2: d = +-1; lengths 3..5: d = +-1, +-2
    assert len(moves) == (n - 1) * 2 + sum((n - L + 1) * 4 for L in (3, 4, 5))
    assert len({tuple(m) for m in moves}) == len(moves)
    assert sorted(map(tuple, shift_moves(n, longest, most, np.random.default_rng(0)))) == sorted(map(tuple, moves))
    mask = np.array([c == "1" for c in "11010001101"])
    out = shifted_masks(mask, moves)
    assert (out.sum(1) == mask.sum()).all()
    for row, (s, length, d) in zip(out, moves):
        want = mask.copy()
        seg = list(mask[s:s + length])
        for i in range(length):  # element i of the segment goes to i + d (mod length)
            want[s + (i + d) % length] = seg[i]
        assert (row == want).all() and (row[:s] == mask[:s]).all() and (row[s + length:] == mask[s + length:]).all()
    assert "".join("1" if b else "0" for b in shifted_masks(mask, np.array([[0, 4, 1]]))[0]) == "11100001101"
    assert shift_moves(1, 24, 6).shape == (0, 3) and shift_moves(5, 24, 0).shape == (0, 3)


class _PhaseObjective(ToyObjective):
    """Mean = 10 x (gaps between consecutive active elements other than 2) + |centre - target|:
    the best selections are combs of pitch 2 centred on the target. From a comb of the wrong
    phase no single swap improves (each breaks a gap); one segment shift re-phases the comb."""

    def __init__(self, n, k, target):
        super().__init__(n, k)
        self.target = float(target)

    def evaluate(self, masks):
        out = super().evaluate(masks)
        m = np.asarray(masks, dtype=bool).reshape(-1, self.n_elements)
        vals = []
        for row in m:
            idx = np.flatnonzero(row)
            vals.append(10.0 * np.count_nonzero(np.diff(idx) != 2) + abs(idx.mean() - self.target))
        out["Mean"] = np.asarray(vals)
        return out


@pytest.mark.parametrize("mode", ["first", "best"])
def test_a_shift_descent_re_phases_a_comb_that_swaps_cannot(mode):
    from arraysel.selectors.contract import numpy_rng
    from arraysel.objective.neighbours import swap_masks, swap_pairs
    from arraysel.selectors.localsearch import SwapSearch, shift_moves, shifted_masks

    n, k = 20, 4
    start = np.zeros(n, dtype=bool)
    start[[6, 8, 10, 12]] = True   # centre 9; the optimum is 7 9 11 13 (centre 10, Mean 0)
    results = {}
    for shift in (0, 2):
        obj = _PhaseObjective(n, k, target=10)
        budget = Budget(evaluations=100_000).start(obj)
        view = BudgetedObjective(obj, budget, Recorder(obj, budget), k)
        search = SwapSearch(view, k, numpy_rng(0), PLAIN, mode=mode, chunk=8, guide=0.0, shift=shift, shift_len=8,
                            shift_scan=10_000)
        mask, value = search.descend(start, float(obj.evaluate(start[None])["Mean"][0]))
        results[shift] = (list(np.flatnonzero(mask)), value, search.shifts)
        # the end is a local optimum of every move the descent uses
        assert obj.evaluate(swap_masks(mask, *swap_pairs(mask)))["Mean"].min() >= value
        if shift:
            assert obj.evaluate(shifted_masks(mask, shift_moves(n, 8, shift)))["Mean"].min() >= value
    assert results[0] == ([6, 8, 10, 12], 1.0, 0)            # swaps alone: stuck at the wrong phase
    assert results[2][:2] == ([7, 9, 11, 13], 0.0) and results[2][2] >= 1


class _PhaseMoves(_PhaseObjective):
    """The comb problem with the move capability: scores moves as their masks, and notes each call's
    shape."""

    def __init__(self, n, k, target):
        super().__init__(n, k, target)
        self.calls = []

    def evaluate_moves(self, mask, out, into):
        from arraysel.objective.neighbours import move_masks

        self.calls.append(np.asarray(out).shape)
        return self.evaluate(move_masks(mask, out, into))


def test_a_shift_descent_scores_its_shifts_as_moves():
    # the same descent, values and count of evaluations whether the objective scores the shifts as
    # moves (one call a chunk, rows padded to its widest move) or as masks
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.localsearch import SwapSearch

    n, k = 20, 4
    start = np.zeros(n, dtype=bool)
    start[[6, 8, 10, 12]] = True
    results = []
    for cls in (_PhaseObjective, _PhaseMoves):
        obj = cls(n, k, target=10)
        budget = Budget(evaluations=100_000).start(obj)
        view = BudgetedObjective(obj, budget, Recorder(obj, budget), k)
        search = SwapSearch(view, k, numpy_rng(0), PLAIN, chunk=8, guide=0.0, shift=2, shift_len=8, shift_scan=10_000)
        mask, value = search.descend(start, float(obj.evaluate(start[None])["Mean"][0]))
        results.append((np.flatnonzero(mask).tolist(), value, obj.evaluations, search.scored))
    assert results[0] == results[1] and results[1][:2] == ([7, 9, 11, 13], 0.0)
    shapes = obj.calls
    assert shapes and all(b >= 1 and m >= 1 for b, m in shapes) and len({m for _, m in shapes}) >= 2


def test_swap_and_ils_with_shifts_find_the_planted_optimum_and_check_their_options(reg):
    best, best_mean = brute_force_optimum(14, 7)
    for name in ("swap", "ils"):
        for seed in (0, 1):
            row = Experiment(ToyObjective(14, 7), name, options={"shift": 3, "shift_len": 6}, seed=seed,
                             budget=Budget(evaluations=1500), registry=reg).run()
            assert row["error"] == "" and row["elements"] == " ".join(map(str, best)), (name, seed, row["Mean"])
    for key, bad in (("shift", -1), ("shift_len", 1), ("shift_scan", 0)):
        with pytest.raises(ParameterError, match=key):
            reg["swap"](**{key: bad})


@pytest.mark.parametrize("name", ["swap", "ils"])
@pytest.mark.parametrize("k", [1, 2, 11, 12])
def test_shifting_searches_run_at_the_extremes_of_k(reg, name, k):
    row = Experiment(ToyObjective(12, k), name, options={"shift": 4, "shift_scan": 50}, budget=Budget(evaluations=300),
                     seed=0, registry=reg).run()
    assert row["error"] == "" and len(row["elements"].split()) == k and np.isfinite(row["Mean"])


def test_automatic_race_chirps_spend_their_share_of_the_budget():
    # race_chirps = None: RACE_CHIRP_PROBE layouts a chirped start first, then as many more as
    # bring the total to RACE_CHIRP_SHARE of the budget, at most CHIRP_CANDIDATES a start
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.localsearch import RACE_CHIRP_PROBE, RACE_CHIRP_SHARE, SwapSearch
    from arraysel.selectors.starts import CHIRP_CANDIDATES

    for evaluations, expected in ((2000, int(RACE_CHIRP_SHARE * 2000)), (300, 3 * RACE_CHIRP_PROBE),
                                  (10 ** 6, 3 * CHIRP_CANDIDATES)):
        obj, view, _ = _view(evaluations=evaluations, k=10, n=20)
        search = SwapSearch(view, 10, numpy_rng(2), PLAIN, fresh="chirp", race=4, race_chirps=None)
        masks, values = search._race_chirps(3)
        assert masks.shape == (expected, 20) and masks.sum(axis=1).tolist() == [10] * expected
        assert view.budget.used_evaluations() == search.scored <= expected  # nothing else was scored
        np.testing.assert_allclose(values, obj.evaluate(masks)["Mean"])
    # without a limited budget: CHIRP_CANDIDATES a start
    _, unlimited, _ = _view(k=10, n=20)
    masks, _ = SwapSearch(unlimited, 10, numpy_rng(2), PLAIN, fresh="chirp", race=4, race_chirps=None)._race_chirps(2)
    assert masks.shape == (2 * CHIRP_CANDIDATES, 20)
    # the race's chirped starts are the best distinct of those layouts
    obj, view, _ = _view(evaluations=2000, k=10, n=20)
    starts = SwapSearch(view, 10, numpy_rng(2), PLAIN, fresh="chirp", race=4, race_chirps=None)._race_starts(3)
    _, again, _ = _view(evaluations=2000, k=10, n=20)
    masks, values = SwapSearch(again, 10, numpy_rng(2), PLAIN, fresh="chirp", race=4, race_chirps=None)._race_chirps(3)
    assert len(starts) == 3 and all((a == b).all() for a, b in zip(starts, _best_distinct(masks, values, 3)))


class _CountingRace:
    """A SwapSearch whose descents score one random selection a step: logs, step by step, which
    descent stepped and how many selections it scored (0 when the step's was cached)."""

    @staticmethod
    def make(view, race, race_quota, steps=10_000, modelled=()):
        from arraysel.selectors.contract import numpy_rng
        from arraysel.selectors.localsearch import SwapSearch
        from arraysel.selectors.starts import random_mask

        class Search(SwapSearch):
            def _descent(self, mask, value):
                who = self.started
                self.started += 1
                for _ in range(steps):
                    m = random_mask(self.rng, self.n, self.k)
                    if who in modelled:
                        self._model(m)
                    before = self.scored
                    v = float(self.score(m[None])[0])
                    self.log.append((who, self.scored - before))
                    yield m, v

        search = Search(view, view.k, numpy_rng(0), PLAIN, race=race, race_quota=race_quota, model="quadratic",
                        refresh=4)
        search.started, search.log = 0, []
        return search

    @staticmethod
    def turns(search) -> list[int]:
        """Selections scored in each stretch one descent moved in a row (its part of a turn)."""
        return [sum(d for _, d in g) for _, g in itertools.groupby(search.log, key=lambda e: e[0])]


@pytest.mark.slow   # 20 s: whole races on a real scene
def test_automatic_race_quota_gives_each_turn_its_part_of_the_race_share():
    # race_quota = None: ceil(log2(race)) turns, each RACE_SHARE / turns of the budget, split
    # evenly among the descents of the turn; under an evaluation budget that is a count
    from arraysel.selectors.localsearch import RACE_QUOTA, RACE_SHARE
    from arraysel.selectors.starts import random_mask

    evaluations, race = 24_000, 4
    starts = [random_mask(np.random.default_rng(i), 20, 10) for i in range(race)]
    search = _CountingRace.make(_view(evaluations=evaluations, k=10, n=20)[1], race, None)
    search.race_descents(starts)
    share = RACE_SHARE / 2 * evaluations / 4  # a descent's part of the first of two turns
    # (the last stretch may run on into the winner's finished descent)
    runs = _CountingRace.turns(search)
    assert [round(r / share, 3) for r in runs[:5]] == [1.0] * 4 + [2.0] and runs[5] >= 2 * share, runs[:6]
    # what the models take is not charged to a turn: a descent that forms a Hessian at each step
    # (Ne evaluations of the budget) scores as many selections as the others
    search = _CountingRace.make(_view(evaluations=evaluations, k=10, n=20)[1], race, None, modelled=(1,))
    with pytest.raises(BudgetExhausted):  # the Hessians use the budget up in the second turn
        search.race_descents(starts)
    runs = _CountingRace.turns(search)
    assert search.hessians > 100 and search.model_used > 0.2
    assert all(abs(r - share) <= 1 for r in runs[:4]), runs[:6]  # (to rounding of the shares)
    # quota given: race_quota selections a descent in the first turn, doubled after
    search = _CountingRace.make(_view(evaluations=evaluations, k=10, n=20)[1], race, 100)
    search.race_descents(starts)
    runs = _CountingRace.turns(search)
    assert runs[:5] == [100] * 4 + [200] and runs[5] >= 200
    # no limited budget: RACE_QUOTA
    search = _CountingRace.make(_view(k=10, n=20)[1], race, None)
    search.race_descents(starts)
    runs = _CountingRace.turns(search)
    assert runs[:5] == [RACE_QUOTA] * 4 + [2 * RACE_QUOTA] and runs[5] >= 2 * RACE_QUOTA


def test_automatic_model_is_quadratic_up_to_its_element_limit():
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.localsearch import QUADRATIC_MAX_ELEMENTS, SwapSearch

    small = SwapSearch(ToyObjective(QUADRATIC_MAX_ELEMENTS, 8), 8, numpy_rng(0), PLAIN, model=None)
    large = SwapSearch(ToyObjective(QUADRATIC_MAX_ELEMENTS + 4, 8), 8, numpy_rng(0), PLAIN, model=None)
    assert (small.model, large.model) == ("quadratic", "linear")
    with pytest.raises(ParameterError, match="model"):
        SwapSearch(ToyObjective(16, 8), 8, numpy_rng(0), PLAIN, model="cubic")


def test_best_pair_swaps_are_the_two_swaps_the_quadratic_model_predicts_best():
    from arraysel.selectors.localsearch import best_pair_swaps

    rng = np.random.default_rng(0)
    for n, k, width, block in ((12, 5, 64, 256), (14, 7, 64, 3), (20, 10, 6, 4)):
        g, a = rng.normal(size=n), rng.normal(size=(n, n))
        H = a + a.T
        mask = np.zeros(n, dtype=bool)
        mask[rng.choice(n, k, replace=False)] = True
        out, into, pred = best_pair_swaps(g, H, mask, 40, width=width, block=block)
        moves = []
        for off in itertools.combinations(np.flatnonzero(mask), 2):
            for on in itertools.combinations(np.flatnonzero(~mask), 2):
                d = np.zeros(n)
                d[list(on)], d[list(off)] = 1.0, -1.0
                moves.append((d @ g + 0.5 * d @ H @ d, off, on))
        direct = {(off, on): v for v, off, on in moves}
        assert out.shape == into.shape == (40, 2) and np.all(np.diff(pred) >= 0)
        for o, i, v in zip(out, into, pred):  # each prediction is d.g + d.H.d / 2 of its move
            assert mask[o].all() and not mask[i].any()
            assert v == pytest.approx(direct[(tuple(o), tuple(i))], abs=1e-9)
        if width >= max(k, n - k):  # every move considered: the 40 lowest of all
            np.testing.assert_allclose(pred, sorted(v for v, _, _ in moves)[:40], atol=1e-9)
        else:  # drawn from the `width` elements of each kind with the lowest one-swap prediction
            assert len(set(out.ravel())) <= width and len(set(into.ravel())) <= width
    out, into, pred = best_pair_swaps(g, H, np.eye(1, 20, 3, dtype=bool)[0], 5)  # one active element
    assert out.shape == (0, 2) and pred.size == 0


def test_a_pair_step_takes_the_best_improving_two_swap_of_the_first_chunk_that_holds_one():
    from arraysel.selectors.contract import numpy_rng
    from arraysel.selectors.localsearch import SwapSearch, best_pair_swaps, loss_quadratic

    obj, view, _ = _view(evaluations=100_000, k=8, n=24)
    rng = np.random.default_rng(3)
    for trial in range(20):
        mask = np.zeros(24, dtype=bool)
        mask[rng.choice(24, 8, replace=False)] = True
        value = float(obj.evaluate(mask[None])["Mean"][0])
        search = SwapSearch(view, 8, numpy_rng(0), PLAIN, model="quadratic", guide=1.0, pairs=48, chunk=16)
        found = search._pair_step(mask, value)
        g, H = loss_quadratic(view, mask)
        out, into, _ = best_pair_swaps(g, H, mask, 48)
        cands = np.repeat(mask[None], len(out), axis=0)
        cands[np.arange(len(out))[:, None], out] = False
        cands[np.arange(len(out))[:, None], into] = True
        values = obj.evaluate(cands)["Mean"]
        first = next((c for c in range(0, 48, 16) if values[c:c + 16].min() < value), None)
        if first is None:
            assert found is None
        else:
            j = first + int(np.argmin(values[first:first + 16]))
            assert (found[0] == cands[j]).all() and found[1] == pytest.approx(values[j])
            assert int(found[0].sum()) == 8 and int((found[0] != mask).sum()) == 4
    assert SwapSearch(view, 8, numpy_rng(0), PLAIN, model="linear", pairs=48)._pair_step(mask, value) is None
    # at the optimum no two-swap improves
    best, best_value = brute_force_optimum(12, 4)
    _, small, _ = _view(evaluations=100_000, k=4, n=12)
    at = np.zeros(12, dtype=bool)
    at[best] = True
    assert SwapSearch(small, 4, numpy_rng(0), PLAIN, model="quadratic", guide=1.0, pairs=10 ** 4)._pair_step(
        at, best_value) is None
    with pytest.raises(ParameterError, match="pairs"):
        SwapSearch(view, 8, numpy_rng(0), PLAIN, pairs=-1)
