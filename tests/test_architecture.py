"""The package reads top-down: no import circle, and no import that goes up the layer table.

The table below is the one statement of the layers (docs/architecture.md draws it). Every
import is counted, at module level and inside functions (``ast``), relative or absolute;
``TYPE_CHECKING`` imports too. A module may import its own layer or the layers below it.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: the layers, bottom up; a module belongs to the layer of its longest matching prefix
LAYERS: tuple[tuple[str, ...], ...] = (
    ("arraysel", "arraysel.errors",                         # version, error types,
     "arraysel.selection"),                                 # a selection's representations and checks
    ("arraysel.io",),                                       # atomic writes, cache folder, mask files
    ("arraysel.physics", "arraysel.physics.volume"),        # probes, delays, SIMUS, beamforming, PSF; 3-D
    ("arraysel.scenes",),                                   # the scene schema and built-in scenes
    ("arraysel.objective",),                                # metrics, losses, contract, objectives
    ("arraysel.selectors",),                                # selector contract, hooks, registry, relaxations
    ("arraysel_plugins",),                                  # the built-in selectors (plugins/)
    ("arraysel.report",),                                   # column schema, tables, IOH export, plots
    ("arraysel.run",),                                      # experiments, compare, executors
    ("arraysel.e2e",),                                      # end-to-end training
    ("arraysel.api", "arraysel.testing"),                   # notebook API, conformance suite
    ("arraysel.cli", "arraysel.__main__"),                  # the `arraysel` command, python -m arraysel
)


def _modules() -> dict[str, Path]:
    mods = {}
    for base, pkg in ((ROOT / "arraysel", "arraysel"), (ROOT / "plugins", "arraysel_plugins")):
        for path in base.rglob("*.py"):
            parts = list(path.relative_to(base).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join([pkg, *parts])] = path
    return mods


MODULES = _modules()


def _resolve(name: str) -> str | None:
    """The module ``name`` refers to (``pkg.mod.attr`` -> ``pkg.mod``), if it is ours."""
    while name and name not in MODULES:
        if "." not in name:
            return None
        name = name.rsplit(".", 1)[0]
    return name or None


def imports_of(module: str) -> set[str]:
    path = MODULES[module]
    is_pkg = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_pkg else module.split(".")[:-1]
                base = base[:len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            targets = [f"{mod}.{a.name}" for a in node.names]
        else:
            continue
        for t in targets:
            r = _resolve(t)
            if r is not None and r != module:
                out.add(r)
    return out


GRAPH = {m: imports_of(m) for m in MODULES}


def layer_of(module: str) -> int:
    best, rank = -1, None
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best:
                best, rank = len(p), i
    assert rank is not None, f"{module} is in no layer of LAYERS: add it to the table"
    return rank


def test_every_module_has_a_layer():
    for m in MODULES:
        layer_of(m)


def test_no_import_goes_up_a_layer():
    up = [f"{m} (layer {LAYERS[layer_of(m)][0]}) imports {t} (layer {LAYERS[layer_of(t)][0]})"
          for m, targets in sorted(GRAPH.items()) for t in sorted(targets) if layer_of(t) > layer_of(m)]
    assert not up, "imports that go up the layer table:\n" + "\n".join(up)


def _cycles() -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in GRAPH[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(GRAPH):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle():
    assert _cycles() == []


def test_the_checks_can_fail():
    """A circle and an upward import planted in a copy of the graph are found."""
    global GRAPH
    saved = GRAPH
    try:
        GRAPH = {m: set(t) for m, t in saved.items()}
        GRAPH["arraysel.errors"].add("arraysel.cli.main")
        GRAPH["arraysel.cli.main"].add("arraysel.errors")
        assert _cycles()
        with pytest.raises(AssertionError, match="arraysel.errors .* imports arraysel.cli.main"):
            test_no_import_goes_up_a_layer()
    finally:
        GRAPH = saved


def test_function_level_imports_are_counted():
    assert "arraysel.run.compare" in GRAPH["arraysel.cli.compare"]      # imported inside run()


def test_the_layer_table_is_the_documented_one():
    doc = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    for prefixes in LAYERS:
        for p in prefixes:
            name = p.replace("arraysel_plugins", "plugins/").replace("arraysel.", "").replace("arraysel", "")
            if name:
                assert name in doc, f"docs/architecture.md does not mention {name}"


def test_no_library_module_uses_the_test_helpers():
    """``arraysel.testing`` is for test authors: the CLI's ``--scene toy`` and the executors use the real
    toy objective (``arraysel.objective.toy``)."""
    users = sorted(m for m, targets in GRAPH.items() if "arraysel.testing" in targets)
    assert users == []


def test_executors_do_not_know_objective_classes():
    """Workers rebuild an objective through its ``worker_factory()`` capability, not by its class:
    of the objective layer they import the contract only (``arraysel.objective.contract``, which
    defines no objective)."""
    for m in ("arraysel.run.executors", "arraysel.run.workers", "arraysel.run.isolation", "arraysel.run.template",
              "arraysel.run.random_search", "arraysel.run.compare_task", "arraysel.run.compare"):
        assert not {t for t in GRAPH[m] if t.startswith("arraysel.objective.")
                    and t != "arraysel.objective.contract"}, m
        assert "__name__ ==" not in MODULES[m].read_text(encoding="utf-8").replace("if __name__", "")


# -- one home for the loss, parts of the PSF model, one selection type ----------------------

def _tree(module: str) -> ast.Module:
    return ast.parse(MODULES[module].read_text(encoding="utf-8"))


def _defined_functions(module: str) -> set[str]:
    return {n.name for n in ast.walk(_tree(module)) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}


#: the loss terms and the function that assembles them: defined in arraysel.objective.losses only
LOSS_FUNCTIONS = {"l_conv", "l_rec", "l_ent", "l_row", "training_loss", "weighted_sum", "check_weights"}
#: the trainer's former second vocabulary of weight names
FORMER_WEIGHT_NAMES = {"psf", "conv", "rec", "contrast", "slr", "ent", "row"}


def test_the_loss_has_one_home():
    """Nothing but ``objective.losses`` defines a loss term or sums the loss; the PSF objective,
    the toy objective and the trainer assemble theirs with ``training_loss`` (the PSF objective's
    losses: ``objective.objective_losses``)."""
    for m in MODULES:
        if m != "arraysel.objective.losses":
            assert not _defined_functions(m) & LOSS_FUNCTIONS, (m, _defined_functions(m) & LOSS_FUNCTIONS)
    for m in ("arraysel.objective.objective_losses", "arraysel.objective.toy", "arraysel.e2e.trainer"):
        names = {a.name for n in ast.walk(_tree(m)) if isinstance(n, ast.ImportFrom)
                 and n.module == "arraysel.objective.losses" for a in n.names}
        assert "training_loss" in names, m


def test_training_settings_speak_the_scene_names():
    """One set of training settings: no ``LossWeights``, and no module of ``e2e`` indexes a loss
    term or weight by the former short names (``terms["conv"]``, ``weights.psf``)."""
    for m in (m for m in MODULES if m.startswith("arraysel.e2e")):
        for node in ast.walk(_tree(m)):
            assert not (isinstance(node, ast.ClassDef) and node.name == "LossWeights"), m
            if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant):
                assert node.slice.value not in FORMER_WEIGHT_NAMES, (m, node.lineno, node.slice.value)
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute):
                assert not (node.value.attr == "weights" and node.attr in FORMER_WEIGHT_NAMES), (m, node.lineno)



def _dataclass_fields(module: str, cls: str) -> set[str]:
    node = next(n for n in ast.walk(_tree(module)) if isinstance(n, ast.ClassDef) and n.name == cls)
    return {n.target.id for n in node.body if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name)}


def test_training_settings_have_one_home():
    """``TrainConfig`` is the one home of the trainer's settings: the pipeline's ``E2ESettings``
    holds one (``train``) and declares none of its fields again (nor ``steps``, its
    ``max_steps``)."""
    train = _dataclass_fields("arraysel.e2e.config", "TrainConfig")
    pipeline = _dataclass_fields("arraysel.e2e.config", "E2ESettings")
    assert {"batch_size", "lr_mask", "tau_steps", "seed", "max_steps"} <= train  # the parse works
    assert "train" in pipeline and "image_size" in pipeline
    assert not pipeline & (train | {"steps"}), sorted(pipeline & (train | {"steps"}))

#: largest module of ``physics.psf`` (lines) and largest class there: the operator, the sizing,
#: the basis and each of its parts stay files a reader takes in at once
PSF_MODULE_LINES = 600
PSF_CLASS_LINES = 520


def test_psf_modules_stay_readable_parts():
    psf = [m for m in MODULES if m.startswith("arraysel.physics.psf")]
    assert {"arraysel.physics.psf.sizing", "arraysel.physics.psf.layout", "arraysel.physics.psf.state"} <= set(psf)
    for m in psf:
        text = MODULES[m].read_text(encoding="utf-8")
        assert text.count("\n") <= PSF_MODULE_LINES, (m, text.count("\n"))
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef):
                assert node.end_lineno - node.lineno < PSF_CLASS_LINES, (m, node.name)


def test_psf_model_delegates_its_sizing():
    """``PSFModel``'s sizing methods are entry points into ``physics.psf.sizing``: each one statement
    (after its docstring) that calls the function of that module."""
    model = next(n for n in ast.walk(_tree("arraysel.physics.psf.operator"))
                 if isinstance(n, ast.ClassDef) and n.name == "PSFModel")
    sizing = _defined_functions("arraysel.physics.psf.sizing")
    methods = {n.name: n for n in model.body if isinstance(n, ast.FunctionDef)}
    for name in ("basis_bytes", "basis_stored_bytes", "basis_build_seconds", "window_estimate", "plan_cache_bytes",
                 "plan_cache_limit", "model_bytes", "exact_bytes", "exact_chunking", "masks_per_batch",
                 "exact_seconds_per_mask"):
        assert name in sizing, name
        body = [s for s in methods[name].body if not (isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant))]
        assert len(body) == 1 and "sizing." + name in ast.unparse(body[0]), name


def test_pair_basis_has_its_entry_points_and_parts():
    tree = _tree("arraysel.physics.psf.basis")
    basis = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == "PairBasis")
    methods = {n.name for n in basis.body if isinstance(n, ast.FunctionDef)}
    assert {"build", "from_state", "state", "truncated"} <= methods
    assert {"arraysel.physics.psf.layout", "arraysel.physics.psf.state"} <= GRAPH["arraysel.physics.psf.basis"]


def _foreign_self_reads(cls: ast.ClassDef) -> set[str]:
    """Attributes a class's methods read from ``self`` that the class neither defines (in its
    body) nor assigns (``self.x = ...`` in a method): what a mixin reads from a shared ``self``."""
    own = {t.id for n in cls.body if isinstance(n, (ast.Assign, ast.AnnAssign))
           for t in (n.targets if isinstance(n, ast.Assign) else [n.target]) if isinstance(t, ast.Name)}
    own |= {n.name for n in cls.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
    attrs = [n for n in ast.walk(cls) if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name)
             and n.value.id == "self"]
    own |= {a.attr for a in attrs if isinstance(a.ctx, ast.Store)}
    return {a.attr for a in attrs if isinstance(a.ctx, ast.Load)} - own


#: the pair basis's parts: module -> the class that is the part
PSF_PARTS = {"arraysel.physics.psf.certificate": "Certificates", "arraysel.physics.psf.refinement": "Refinement",
             "arraysel.physics.psf.build": "BasisBuilder", "arraysel.physics.psf.exactpixels": "ExactPixels"}


def test_pair_basis_is_built_from_parts_not_mixins():
    """``PairBasis`` inherits from nothing: its certificates, refinement and build are objects
    made from explicit constructor arguments, and each reads from ``self`` only what it defines
    or assigns itself (its inputs are named, not shared through a common ``self``)."""
    basis = next(n for n in ast.walk(_tree("arraysel.physics.psf.basis"))
                 if isinstance(n, ast.ClassDef) and n.name == "PairBasis")
    assert all(isinstance(b, ast.Name) and b.id == "object" for b in basis.bases), ast.dump(basis)
    held = {a.attr for a in ast.walk(basis) if isinstance(a, ast.Attribute) and isinstance(a.ctx, ast.Store)}
    assert {"layout", "certificates", "refinement"} <= held
    for module, name in PSF_PARTS.items():
        cls = next(n for n in _tree(module).body if isinstance(n, ast.ClassDef) and n.name == name)
        assert not cls.bases, (module, name)
        init = next(n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "__init__")
        assert len(init.args.args) >= 2, (module, "__init__ takes its inputs")
        assert not _foreign_self_reads(cls), (module, name, _foreign_self_reads(cls))
    # the check sees a mixin's read of an attribute another class sets
    mixin = ast.parse("class M:\n    k = 1\n    def f(self):\n        self.y = self.k + self.window\n").body[0]
    assert _foreign_self_reads(mixin) == {"window"}


def test_no_benchmark_history_in_psf_code():
    """Timings and dates of measurements live in ``docs/performance.md``, not in comments."""
    import re

    timing = re.compile(r"\b\d+(\.\d+)?( ?- ?\d+(\.\d+)?)? ?ms\b|\b20\d\d-\d\d-\d\d\b")
    for m in (m for m in MODULES if m.startswith("arraysel.physics.psf")):
        for no, line in enumerate(MODULES[m].read_text(encoding="utf-8").splitlines(), 1):
            assert not timing.search(line), f"{MODULES[m].name}:{no}: {line.strip()}"


def test_selections_are_not_parsed_back_from_tables():
    """Figures and tables take ``Selection`` s: nothing in ``report`` or ``run`` reads a selection
    out of a table's ``elements`` column, and ``report`` reads an ``elements`` cell only through
    ``Selection.from_text``."""
    for m in (m for m in MODULES if m.startswith(("arraysel.report", "arraysel.run"))):
        tree = _tree(m)
        for node in ast.walk(tree):
            if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id == "table":
                assert not (isinstance(node.slice, ast.Constant) and node.slice.value == "elements"), (m, node.lineno)
        if m.startswith("arraysel.report"):
            assert "parse_element_text" not in ast.unparse(tree), m
            assert ".split()" not in MODULES[m].read_text(encoding="utf-8"), m


def test_objectives_read_their_scene_once():
    # the scene is read into ObjectiveSettings (and the physics setups) in __init__; afterwards an
    # objective reads its settings, never the scene again (worker_factory only serialises it)
    import ast

    allowed = {"__init__", "worker_factory"}
    for name in ("psf_objective.py", "matrix_objective.py"):
        tree = ast.parse((Path(__file__).resolve().parents[1] / "arraysel" / "objective" / name).read_text())
        for cls in (n for n in tree.body if isinstance(n, ast.ClassDef) and n.name.endswith("Objective")):
            for fn in (n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name not in allowed):
                for node in ast.walk(fn):
                    if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute)
                            and node.value.attr == "scene" and isinstance(node.value.value, ast.Name)
                            and node.value.value.id == "self"):
                        raise AssertionError(f"{name}: {cls.name}.{fn.name} reads self.scene.{node.attr} "
                                             "after construction (use self.settings)")


# ---------------------------------------------------------------------------
# compare: a result, runners, one store (a selection's text formed at the store only)
# ---------------------------------------------------------------------------

COMPARE_FUNCTION_LINES = 80
#: the calls that write a comparison's files
FILE_WRITERS = {"write_json", "write_csv", "write_runs", "write_tables", "write_ioh", "save_figure",
                "atomic_write_text", "atomic_write_bytes", "remove_results", "write_figures"}


def _calls(tree: ast.AST) -> set[str]:
    """The names a module calls (a method of its ``store``, the CompareStore, left out)."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            if isinstance(f, ast.Attribute) and not (isinstance(f.value, ast.Name) and f.value.id == "store"):
                out.add(f.attr)
            elif isinstance(f, ast.Name):
                out.add(f.id)
    return out


def test_compare_returns_a_frozen_result():
    import dataclasses

    from arraysel.run.compare import CompareResult, compare

    assert dataclasses.is_dataclass(CompareResult) and CompareResult.__dataclass_params__.frozen
    fields = {f.name for f in dataclasses.fields(CompareResult)}
    assert {"table", "runs", "trace", "stats", "selections", "failures", "out_dir"} <= fields
    fn = next(n for n in _tree("arraysel.run.compare").body if isinstance(n, ast.FunctionDef) and n.name == "compare")
    assert ast.unparse(fn.returns) == "CompareResult"


def test_compare_functions_stay_short():
    for m in ("arraysel.run.compare", "arraysel.run.runners", "arraysel.run.store"):
        for node in ast.walk(_tree(m)):
            if isinstance(node, ast.FunctionDef):
                length = node.end_lineno - node.lineno + 1
                assert length <= COMPARE_FUNCTION_LINES, f"{m}.{node.name}: {length} lines"


def test_run_modes_are_runners():
    from arraysel.run import runners

    for name in ("InProcessRunner", "IsolatedRunner", "ExecutorRunner"):
        cls = getattr(runners, name)
        assert issubclass(cls, runners.Runner) and "run" in vars(cls), name
    # a run without a result gets its row in one place
    builders = {m for m in MODULES if m.startswith("arraysel.run")
                and any(isinstance(n, ast.Dict) and any(isinstance(k, ast.Constant) and k.value == "error"
                                                        for k in n.keys)
                        and any(isinstance(k, ast.Constant) and k.value == "n_elements" for k in n.keys)
                        for n in ast.walk(_tree(m)))}
    assert builders == {"arraysel.run.experiment", "arraysel.run.runners"}, builders  # a run's row | failure_row


def test_only_the_store_writes_the_compare_files():
    for m in (m for m in MODULES if m.startswith("arraysel.run") and m not in
              ("arraysel.run.store", "arraysel.run.outdir")):
        assert not (_calls(_tree(m)) & FILE_WRITERS), (m, _calls(_tree(m)) & FILE_WRITERS)


def test_a_selections_text_is_formed_at_the_store_only():
    """In ``run``, a row's ``elements`` is a ``Selection``: only the store forms or reads its text."""
    for m in (m for m in MODULES if m.startswith("arraysel.run") and m != "arraysel.run.store"):
        tree = _tree(m)
        attrs = {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
        names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} | attrs
        assert not names & {"format_elements", "parse_element_text", "from_text"}, m
        assert "text" not in attrs, m  # Selection.text


def test_the_cli_and_api_use_the_result_not_the_files():
    """``arraysel compare`` and ``api.compare`` take the tables from the result, never read back."""
    for m in ("arraysel.cli.compare", "arraysel.api"):
        calls = _calls(_tree(m))
        assert not calls & {"read_csv", "read_runs", "read_text", "read_bytes", "open", "load", "loads"}, (m, calls)


# -- sizes a newcomer can read ----------------------------------------------------------------

#: the most lines of a module, a class and a function (its ``def`` line to its last line)
SIZE_LIMITS = {"module": 600, "class": 400, "function": 80}
#: the packages held to the limits: all of them, with no exemption
SIZED = ("arraysel", "arraysel_plugins")


def oversized(name: str, text: str) -> list[str]:
    """What in the module ``name`` (source ``text``) is longer than :data:`SIZE_LIMITS` allows."""
    out = []
    lines = len(text.splitlines())
    if lines > SIZE_LIMITS["module"]:
        out.append(f"module {name}: {lines} lines")
    for node in ast.walk(ast.parse(text)):
        kind = {ast.ClassDef: "class", ast.FunctionDef: "function", ast.AsyncFunctionDef: "function"}.get(type(node))
        if kind is not None and node.end_lineno - node.lineno + 1 > SIZE_LIMITS[kind]:
            out.append(f"{kind} {name}.{node.name} (line {node.lineno}): {node.end_lineno - node.lineno + 1} lines")
    return out


def test_modules_classes_and_functions_are_a_size_a_newcomer_can_read():
    sized = sorted(m for m in MODULES if any(m == p or m.startswith(p + ".") for p in SIZED))
    assert set(sized) == set(MODULES)  # every module, no exemption
    assert {"arraysel.selectors.localsearch", "arraysel.physics.psf.refinement", "arraysel.constraints",
            "arraysel_plugins.swap"} <= set(sized)
    too_big = [line for m in sized for line in oversized(m, MODULES[m].read_text(encoding="utf-8"))]
    assert not too_big, "split by concept:\n" + "\n".join(too_big)


def test_the_size_check_can_fail():
    body = "\n".join(f"        x{i} = {i}" for i in range(80))
    text = f"class C:\n    def long(self):\n{body}\n" + "\n" * (SIZE_LIMITS["module"] - 80)
    assert [line.split(":")[0] for line in oversized("m", text)] == ["module m", "function m.long (line 2)"]
    assert oversized("m", "def short():\n    return 1\n") == []


# -- search asks the objective once, through the contract ------------------------------------

#: how selectors/ and run/ name an objective or a wrapper of one (``objective``, ``self.objective``,
#: ``obj``, a budgeted ``view``, a wrapper's ``self._inner`` / ``self._o``)
OBJECTIVE_NAME = re.compile(r"objective|_inner\b|\bself\._o\b|\bobj\b|\bview\b")
#: the packages whose code must not probe an objective
UNPROBING = ("arraysel.selectors", "arraysel.run")


def objective_probes(text: str) -> list[str]:
    """The calls of ``text`` that probe an objective for what it can do: ``hasattr(X, ...)``, or
    ``getattr(X, "name")`` / ``getattr(X, name, default)`` (a named attribute, or one with a
    default), ``X`` an expression that names an objective (:data:`OBJECTIVE_NAME`). A wrapper's
    forwarding, ``getattr(self._inner, name)`` with a computed name and no default, asks the
    objective nothing and is not a probe. What a search may ask is read through
    ``arraysel.objective.contract`` (``neighbourhood_of``, ``loss_model_of``, ``objective_info``,
    ``element_layout``, ``worker_factory_of``) or the budgeted objective's own methods."""
    out = []
    for node in ast.walk(ast.parse(text)):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                and node.func.id in ("getattr", "hasattr") and node.args):
            continue
        if not OBJECTIVE_NAME.search(ast.unparse(node.args[0])):
            continue
        named = len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
        if node.func.id == "hasattr" or named or len(node.args) == 3:
            out.append(f"line {node.lineno}: {ast.unparse(node)}")
    return out


def test_selectors_and_runners_do_not_probe_the_objective():
    mods = sorted(m for m in MODULES if any(m == p or m.startswith(p + ".") for p in UNPROBING))
    assert {"arraysel.selectors.searchstate", "arraysel.selectors.lossmodel", "arraysel.run.template"} <= set(mods)
    probes = [f"{m} {line}" for m in mods for line in objective_probes(MODULES[m].read_text(encoding="utf-8"))]
    assert not probes, "ask through arraysel.objective.contract:\n" + "\n".join(probes)


def test_the_probe_check_can_fail():
    text = ("def f(objective, self, x):\n"
            "    a = getattr(objective, 'mask_hessian', None)\n"
            "    b = hasattr(self.objective, 'score_swaps')\n"
            "    c = getattr(self._inner, 'dtype')\n"
            "    d = callable(getattr(type(objective), 'fallback', None))\n"
            "    e = getattr(x, 'name', None)\n"            # not an objective
            "    return getattr(self._inner, x)\n")         # forwarding
    assert [p.split(":")[0] for p in objective_probes(text)] == ["line 2", "line 3", "line 4", "line 5"]
