"""Test helpers for plugin authors: the reusable selector conformance suite :class:`SelectorConformance`.

The cheap :class:`~arraysel.objective.toy.ToyObjective` it runs on lives in :mod:`arraysel.objective.toy`
and is re-exported here.

``SelectorConformance`` is a plain class (no pytest import) whose
``test_*`` methods check the selector contract. A plugin author subclasses it
in a test module::

    from arraysel.testing import SelectorConformance
    from my_plugin import MySelector

    class TestMySelector(SelectorConformance):
        selector_class = MySelector
        selector_options = {"iterations": 10}

and pytest runs every check on ``MySelector``.
"""
from __future__ import annotations

from typing import Any

from arraysel.objective.toy import ToyFailure, ToyObjective, ToyScene  # noqa: F401  (re-exported for test authors)

__all__ = ["ToyScene", "ToyObjective", "SelectorConformance"]

# ---------------------------------------------------------------------------
# conformance suite
# ---------------------------------------------------------------------------

class SelectorConformance:
    """Reusable checks of the selector contract; subclass it in a ``Test*`` class.

    Set ``selector_class`` (a Selector subclass) or ``selector_name`` (looked
    up in ``registry``, by default the built-ins without installed entry
    points). ``selector_options`` are passed to the selector. Budgets are
    small so the whole suite runs in about a second per selector.
    """

    selector_class: Any = None
    selector_name: str | None = None
    selector_options: dict = {}
    registry: Any = None
    n_elements: int = 12
    budget_evaluations: int = 150
    budget_seconds: float = 0.5
    #: wall-clock grace over ``budget_seconds`` allowed in the time-budget test
    time_grace: float = 2.0

    # -- building blocks (override to customise) -----------------------------
    def get_class(self):
        if self.selector_class is not None:
            return self.selector_class
        if self.selector_name is None:
            raise AssertionError("set selector_class or selector_name on the conformance test class")
        reg = self.registry
        if reg is None:
            from arraysel.selectors.registry import build_plugin_manager, get_registry
            reg = get_registry(build_plugin_manager(load_entrypoints=False, disabled=()))
        return reg[self.selector_name]

    def make_objective(self, k: int | None = None, **kwargs) -> ToyObjective:
        n = self.n_elements
        return ToyObjective(n, n // 2 if k is None else k, **kwargs)

    def run_experiment(self, objective, *, k: int | None = None, seed: int = 0, budget=None):
        from arraysel.run.experiment import Experiment
        from arraysel.selectors.contract import Budget
        budget = Budget(evaluations=self.budget_evaluations) if budget is None else budget
        exp = Experiment(objective, self.get_class(), options=dict(self.selector_options),
                         budget=budget, seed=seed, k=k)
        row = exp.run()
        return exp, row

    @staticmethod
    def _selection(row) -> list[int]:
        return [int(i) for i in row["elements"].split()] if row["elements"] else []

    # -- checks --------------------------------------------------------------
    def test_declared_attributes(self):
        from arraysel.selectors.contract import Option, Selector
        cls = self.get_class()
        assert issubclass(cls, Selector)
        assert isinstance(cls.name, str) and cls.name
        assert isinstance(cls.description, str) and cls.description.strip()
        assert "\n" not in cls.description.strip(), "description must be one line"
        for key, opt in cls.options.items():
            assert isinstance(opt, Option), key
            if opt.default is not None:
                assert opt.validate(key, opt.default) == opt.default
        for flag in ("uses_gradients", "deterministic", "needs_evaluations"):
            assert isinstance(getattr(cls, flag), bool), flag
        cls(**self.selector_options)

    def test_returns_k_distinct_elements(self):
        n = self.n_elements
        for k in sorted({1, 2, n // 2, n - 1, n}):
            obj = self.make_objective(k=k)
            exp, row = self.run_experiment(obj, k=k, seed=1)
            assert row["error"] == "", f"k={k}: {row['error']}"
            sel = self._selection(row)
            assert len(sel) == k and len(set(sel)) == k, f"k={k}: {sel}"
            assert all(0 <= i < n for i in sel), sel
            assert exp.selection == sel

    def test_evaluation_budget_respected(self):
        obj = self.make_objective()
        cls = self.get_class()
        exp, row = self.run_experiment(obj, seed=0)
        slack = cls(**self.selector_options).batch_size(obj.n_elements, obj.k)
        assert row["evaluations"] <= self.budget_evaluations + slack
        for t in exp.trace:
            assert t["evaluations"] <= self.budget_evaluations + slack

    def test_time_budget_respected(self):
        from arraysel.selectors.contract import Budget
        obj = self.make_objective(delay=0.002)
        _, row = self.run_experiment(obj, budget=Budget(seconds=self.budget_seconds))
        assert row["error"] == "", row["error"]
        assert row["seconds"] <= self.budget_seconds + self.time_grace, row["seconds"]

    def test_meets_constraints(self):
        """On a 4 x 4 toy matrix under each kind of constraint (forced elements, four-fold symmetry,
        channel groups with exactly one and at most one element each, the quota of separate transmit
        and receive apertures): a selection that meets them,
        or, for channel groups only, a refusal that names them (\"cannot honour ... groups\")."""
        from arraysel.constraints import Constraints, aperture_constraints
        pos = ToyObjective(16, 4, grid=(4, 4)).element_positions
        cases = {"forced": Constraints(16, 6, forced_on=[5], forced_off=[0, 15]),
                 "symmetry": Constraints(16, 8, symmetry="xy", positions=pos),
                 "groups": Constraints(16, 4, groups="mux-16-4"),
                 "groups at-most-one": Constraints(16, 3, groups="mux-16-4", group_mode="at-most-one"),
                 "apertures": aperture_constraints(8, 3, 2)}  # separate transmit and receive (2 x 8 units)
        for label, cons in cases.items():
            obj = ToyObjective(16, cons.k, grid=(4, 4), constraints=cons)
            _, row = self.run_experiment(obj, k=cons.k, seed=1)
            if row["error"]:
                assert cons.groups is not None and "cannot honour" in row["error"] and "groups" in row["error"], \
                    f"{label}: {row['error']}"
                continue
            sel = self._selection(row)
            assert cons.feasible(sel), f"{label}: {sel} breaks the constraints ({cons.describe()})"

    def test_same_seed_same_result(self):
        cls = self.get_class()
        rows = [self.run_experiment(self.make_objective(), seed=s)[1] for s in (3, 3)]
        assert rows[0]["error"] == "" and rows[1]["error"] == ""
        if cls.deterministic:
            assert rows[0]["elements"] == rows[1]["elements"]
            assert rows[0]["evaluations"] == rows[1]["evaluations"]

    def test_trace_is_monotone(self):
        exp, row = self.run_experiment(self.make_objective(), seed=2)
        events = [t.get("event", "improvement") for t in exp.trace]
        if exp.trace:  # the runner closes a trace with one `end` row at the last evaluation
            assert events[-1] == "end" and "end" not in events[:-1], events
            assert exp.trace[-1]["evaluations"] == row["evaluations"]
        best = [t["best_Mean"] for t in exp.trace if t.get("event", "improvement") == "improvement"]
        assert all(b2 < b1 for b1, b2 in zip(best, best[1:])), best
        if exp.trace:
            assert exp.trace[-1]["best_Mean"] == best[-1]
        secs = [t["seconds"] for t in exp.trace]
        evals = [t["evaluations"] for t in exp.trace]
        assert secs == sorted(secs) and evals == sorted(evals)

    def test_raising_objective_gives_clear_error(self):
        obj = self.make_objective(fail_after=0)
        _, row = self.run_experiment(obj, seed=0)
        assert "toy objective failure" in row["error"], row["error"]

    def test_objective_failing_midway_gives_clear_error(self):
        obj = self.make_objective(fail_after=5)
        _, row = self.run_experiment(obj, seed=0)
        # a selector that needs at most 5 evaluations (the final scoring included) is not affected
        if row["error"] == "":
            assert obj.evaluations <= 5
        else:
            assert "toy objective failure" in row["error"], row["error"]

    def test_nan_objective_survived(self):
        obj = self.make_objective(always_nan=True)
        _, row = self.run_experiment(obj, seed=0)
        assert row["error"], "an all-NaN objective must be reported in the error column"
        assert "NaN" in row["error"] or "nan" in row["error"], row["error"]
        sel = self._selection(row)
        if sel:
            assert len(sel) == obj.k and len(set(sel)) == obj.k

    def test_partly_nan_objective(self):
        obj = self.make_objective(nan_element=1)
        _, row = self.run_experiment(obj, seed=0)
        sel = self._selection(row)
        assert len(sel) == obj.k and len(set(sel)) == obj.k, row["error"]
        assert row["error"] == "" or "NaN" in row["error"], row["error"]
