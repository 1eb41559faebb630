"""Constraints a scanner imposes (arraysel.constraints): group maps, checks naming the constraint, the
search helpers, the reduced problem the runner hands a selector, scene keys, and a selector that
breaks a constraint. Every built-in selector under every kind of constraint: the conformance suite
(``SelectorConformance.test_meets_constraints``, tests/test_conformance.py)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from arraysel.constraints import Constraints, ConstraintError, mux_groups, read_group_csv
from arraysel.errors import ParameterError
from arraysel.objective.toy import ToyObjective
from arraysel.run.experiment import Experiment
from arraysel.scenes import load_scene
from arraysel.selectors.constrained import ConstrainedObjective
from arraysel.selectors.contract import Budget, BudgetedObjective, Recorder, Selector

POS8 = ToyObjective(64, 16, grid=(8, 8)).element_positions


# -- group maps ----------------------------------------------------------------------------

def test_mux_1024_4_table():
    g = mux_groups("mux-1024-4", 1024)
    # channel c reaches element c of each bank of 256 (8 rows x 32 columns)
    assert [int(g[e]) for e in (0, 256, 512, 768)] == [0, 0, 0, 0]
    assert [int(g[e]) for e in (255, 511, 767, 1023)] == [255] * 4
    assert int(g[8 * 32 + 5]) == 5 and int(g[3 * 32 + 7]) == 3 * 32 + 7   # row 8 col 5 -> channel 5
    assert np.array_equal(np.bincount(g), np.full(256, 4))
    for e in range(1024):
        ix, iy = e % 32, e // 32
        assert g[e] == (iy % 8) * 32 + ix


@pytest.mark.parametrize("rule, n, needle", [("mux-1024-4", 512, "is for 1024 elements"),
                                             ("mux-10-3", 10, "multiple"), ("banks", 16, "not a known rule")])
def test_mux_rule_errors(rule, n, needle):
    with pytest.raises(ParameterError, match=needle):
        mux_groups(rule, n)


def test_group_csv(tmp_path):
    good = tmp_path / "g.csv"
    good.write_text("# four channels\nelement,group\n" + "".join(f"{e},{e % 4}\n" for e in range(8)))
    assert read_group_csv(good, 8).tolist() == [0, 1, 2, 3, 0, 1, 2, 3]
    c = Constraints(8, 4, groups=str(good))
    assert c.feasible([0, 5, 2, 7]) and not c.feasible([0, 4, 2, 7])
    bad = tmp_path / "b.csv"
    bad.write_text("element,group\n0,0\n1,x\n")
    with pytest.raises(ParameterError, match="line 3"):
        read_group_csv(bad, 2)
    short = tmp_path / "s.csv"
    short.write_text("element,group\n0,0\n")
    with pytest.raises(ParameterError, match="have no group"):
        read_group_csv(short, 2)
    twice = tmp_path / "t.csv"
    twice.write_text("element,group\n0,0\n0,1\n")
    with pytest.raises(ParameterError, match="listed twice"):
        read_group_csv(twice, 2)


# -- the constraints and their checks ------------------------------------------------------

def test_inconsistent_constraints_are_refused():
    with pytest.raises(ParameterError, match="forced both on and off"):
        Constraints(16, 4, forced_on=[1], forced_off=[1])
    with pytest.raises(ParameterError, match="'exactly-one' of 4 groups selects 4"):
        Constraints(16, 5, groups="mux-16-4")
    with pytest.raises(ParameterError, match="group 1 has 2 elements forced on"):
        Constraints(16, 4, groups="mux-16-4", forced_on=[1, 5])
    with pytest.raises(ParameterError, match="every element forced off"):
        Constraints(16, 4, groups="mux-16-4", forced_off=[2, 6, 10, 14])
    with pytest.raises(ParameterError, match="symmetry together with channel groups"):
        Constraints(64, 16, groups="mux-64-4", symmetry="x", positions=POS8)
    pos7 = ToyObjective(49, 7, grid=(7, 7)).element_positions
    with pytest.raises(ParameterError, match="odd number of rows or columns"):
        Constraints(49, 8, symmetry="x", positions=pos7)
    with pytest.raises(ParameterError, match="not a\n? ?multiple of 4|multiple of 4"):
        Constraints(64, 6, symmetry="xy", positions=POS8)
    with pytest.raises(ParameterError, match="constraints.mode"):
        Constraints(16, 4, groups="mux-16-4", group_mode="sometimes")


def test_check_names_the_broken_constraint():
    c = Constraints(64, 16, forced_on=[9], forced_off=[0])
    cases = {"k": list(range(1, 16)), "forced_off": list(range(0, 16)), "forced_on": list(range(10, 26))}
    for name, sel in cases.items():
        with pytest.raises(ConstraintError, match=f"breaks the constraint {name}") as err:
            c.check(sel)
        assert err.value.constraint == name
    g = Constraints(64, 16, groups="mux-64-4")
    with pytest.raises(ConstraintError, match="constraint groups: group 0 of mux-64-4 holds 2 selected"):
        g.check([0, 16] + list(range(2, 16)))
    s = Constraints(64, 16, symmetry="x", positions=POS8)
    with pytest.raises(ConstraintError, match="constraint symmetry: element 0 is on but its mirror"):
        s.check(list(range(7)) + list(range(8, 17)))
    assert s.feasible([0, 7, 1, 6, 8, 15, 9, 14, 16, 23, 17, 22, 24, 31, 25, 30])


def test_symmetry_closes_the_forced_sets_and_units():
    c = Constraints(64, 16, symmetry="xy", positions=POS8, forced_off=[0])
    assert c.forced_off == (0, 7, 56, 63)                       # the mirror images of a dead corner
    assert c.unit_size == 4 and len(c.units) == 15 and c.k_units == 4


@pytest.mark.parametrize("mode, k", [("exactly-one", 16), ("at-most-one", 11)])
def test_search_helpers_stay_feasible(mode, k):
    c = Constraints(64, k, groups="mux-64-4", group_mode=mode)
    rng = np.random.default_rng(0)
    masks = c.random_masks(rng, 50)
    assert c.feasible_rows(masks).all()
    assert all(c.feasible(m) for m in masks)
    m = masks[0]
    a, b = c.swap_pairs(m)
    g = c.groups
    if mode == "exactly-one":
        assert a.size == 16 * 3 and (g[a] == g[b]).all()   # the swap partner is in the same group
    for i in range(a.size):
        moved = m.copy()
        moved[a[i]], moved[b[i]] = False, True
        assert c.feasible(moved)
    assert c.feasible(c.random_swaps(m, 5, rng))
    assert c.feasible(c.crossover(masks[1], masks[2], rng))
    assert c.feasible(c.project(rng.random(64)))
    # feasible_rows agrees with check on random (mostly infeasible) masks
    raw = np.zeros((200, 64), dtype=bool)
    for r in raw:
        r[rng.choice(64, k, replace=False)] = True
    assert np.array_equal(c.feasible_rows(raw), [c.feasible(r) for r in raw])


def test_projection_keeps_the_nearest_choice():
    # per group the highest score: an unconstrained selection's elements are kept where they can be
    c = Constraints(16, 4, groups="mux-16-4")
    scores = np.zeros(16)
    scores[[4, 9, 14, 3]] = 1.0
    assert c.project(scores) == [3, 4, 9, 14]


# -- the reduced problem ------------------------------------------------------------------------

def _view(cons, obj, evaluations=1000):
    budget = Budget(evaluations=evaluations).fresh().start(obj)
    rec = Recorder(obj, budget)
    return ConstrainedObjective(BudgetedObjective(obj, budget, rec, cons.k, constraints=cons), cons), rec


def test_reduced_problem_expands_masks_weights_and_moves():
    cons = Constraints(64, 16, symmetry="x", positions=POS8, forced_on=[0], forced_off=[9])
    obj = ToyObjective(64, 16, grid=(8, 8), dtype=torch.float64)
    view, rec = _view(cons, obj)
    assert view.n_elements == len(cons.units) == 30 and view.k == 7
    units = [1, 4, 7, 10, 13, 20, 25]
    elements = cons.expand_indices(units)
    assert cons.feasible(elements) and 0 in elements and 7 in elements
    mask = np.zeros(view.n_elements, dtype=bool)
    mask[units] = True
    direct = obj.evaluate(cons.expand(mask)[None])["Mean"][0]
    assert view.score(mask[None])[0] == pytest.approx(direct)
    w = torch.tensor(mask, dtype=torch.float64)
    assert float(view.mask_loss(w[None])[0].sum()) == pytest.approx(
        float(obj.mask_loss(torch.tensor(cons.expand(mask)[None], dtype=torch.float64))[0].sum()))
    # a unit swap scores as the element move (both mirror images switched)
    out, into = np.array([1]), np.array([2])
    moved = mask.copy()
    moved[1], moved[2] = False, True
    assert view.score_swaps(mask, out, into)[0] == pytest.approx(view.score(moved[None])[0])
    assert view.best == sorted(cons.reduce_indices(rec.best))


def test_only_feasible_masks_are_recorded():
    cons = Constraints(64, 16, groups="mux-64-4")
    obj = ToyObjective(64, 16, grid=(8, 8))
    budget = Budget(evaluations=100).fresh().start(obj)
    rec = Recorder(obj, budget)
    b = BudgetedObjective(obj, budget, rec, 16, constraints=cons)
    infeasible = np.zeros(64, dtype=bool)
    infeasible[list(range(1, 16)) + [17]] = True   # 16 elements: group 1 twice (1 and 17), group 0 none
    assert infeasible.sum() == 16 and not cons.feasible(infeasible)
    b.evaluate(infeasible[None])
    assert rec.best is None
    b.evaluate(cons.random_masks(np.random.default_rng(0), 1))
    assert rec.best is not None and cons.feasible(rec.best)


# -- a selector that breaks a constraint ---------------------------------------------------------

class _EverySecond(Selector):
    """Returns every second unit whatever the channel groups say."""

    name = "every-second"
    description = "every second unit (breaks channel groups)"
    deterministic = True

    def select(self, objective, k, seed):
        return list(range(0, 2 * k, 2))


def test_a_selector_that_breaks_groups_gets_a_clear_error():
    cons = Constraints(64, 16, groups="mux-64-4")
    row = Experiment(ToyObjective(64, 16, grid=(8, 8), constraints=cons), _EverySecond,
                     budget=Budget(evaluations=10)).run()
    assert "ConstraintError" in row["error"] and "breaks the constraint groups" in row["error"]
    assert row["elements"] == ""
    # forced elements and symmetry it meets without knowing: it sees the free units only
    cons = Constraints(64, 16, symmetry="xy", positions=POS8, forced_off=[0])
    row = Experiment(ToyObjective(64, 16, grid=(8, 8), constraints=cons), _EverySecond,
                     budget=Budget(evaluations=10)).run()
    assert row["error"] == "" and cons.feasible([int(i) for i in row["elements"].split()])


# -- scene keys -----------------------------------------------------------------------------------

def _scene(**constraints):
    return {"base": "matrix-1024", "probe": {"name": "MATRIX-32x32", "nx": 8, "ny": 8},
            "selection": {"k": 16}, "constraints": constraints}


@pytest.mark.parametrize("keys, needle", [
    ({"groups": "mux-1024-4"}, "constraints.groups = 'mux-1024-4' is for 1024 elements; the probe has 64"),
    ({"groups": "bank"}, "constraints.groups = 'bank' is not a known rule"),
    ({"mode": "sometimes"}, "constraints.mode"),
    ({"symmetry": "z"}, "constraints.symmetry"),
    ({"forced_on": [64]}, r"constraints.forced_on must be element indices in \[0, 63\]"),
    ({"forced_off_rows": [9]}, r"constraints.forced_off_rows = \[9\]: row 9 is out of range \[0, 7\]"),
    ({"groups": "mux-64-4", "forced_on": [1, 17]}, "group 1 has 2 elements forced on"),
    ({"colour": "red"}, "unknown scene key 'constraints.colour'"),
])
def test_scene_key_errors(keys, needle):
    with pytest.raises(ParameterError, match=needle):
        load_scene(_scene(**keys))


def test_scene_constraints_and_the_builtin_mux_scene():
    c = load_scene(_scene(groups="mux-64-4", forced_off_rows=[0])).constraints()
    assert c.forced_off == tuple(range(8)) and c.k_units == 16 - 0 and len(c.units) == 56
    mux = load_scene("matrix-1024-mux").constraints()
    assert mux.k == 256 and mux.k_units == 256 and np.array_equal(mux.groups, mux_groups("mux-1024-4", 1024))
    assert load_scene("matrix-1024").constraints() is None
    sym = load_scene(_scene(symmetry="xy")).constraints()
    assert sym.unit_size == 4 and sym.k_units == 4


def test_group_masks_figure_marks_a_shared_channel():
    from arraysel.report.layout_plots import group_masks_figure

    groups = mux_groups("mux-16-4", 16)
    masks = np.zeros((2, 16), dtype=bool)
    masks[0, [0, 5, 10, 15]] = True      # one element per group
    masks[1, [0, 4, 8, 12]] = True       # all four in group 0 (mux-16-4: group = e mod 4)
    fig = group_masks_figure(["ok", "shared"], masks, POS8[:16], groups)
    titles = [ax.get_title() for ax in fig.axes if ax.get_visible()]
    assert titles[0] == "ok: 4/4 groups, max 1" and titles[1] == "shared: 1/4 groups, max 4"


@pytest.mark.parametrize("cons", [Constraints(64, 16, groups="mux-64-4"),
                                  Constraints(64, 16, symmetry="xy", positions=POS8, forced_off=[0])],
                         ids=["groups", "symmetry"])
def test_polish_keeps_the_constraints(cons):
    row = Experiment(ToyObjective(64, 16, grid=(8, 8), constraints=cons), "random", options={"polish": 0.5},
                     budget=Budget(evaluations=300), seed=2).run()
    assert row["error"] == "" and cons.feasible([int(i) for i in row["elements"].split()])
