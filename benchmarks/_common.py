"""Helpers shared by the benchmark scripts (not part of the package).

Every benchmark measures its figures side by side in one run and prints a
human-readable table followed by one JSON line, so that results can be
collected by a script (``tail -n 1``).
"""
from __future__ import annotations

import importlib.util
import json
import os
import platform
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")


def set_threads(n: int | None) -> None:
    """Limit BLAS, OpenMP and numba threads and tune the allocator as the ``arraysel`` command does
    (:func:`arraysel.io.allocator.tune_malloc`; ``ARRAYSEL_MALLOC_TUNE=0`` disables it); call
    before numpy, torch and numba load."""
    from arraysel.io.allocator import tune_malloc

    tune_malloc()
    if n is None:
        return
    if n < 1:
        raise SystemExit(f"--threads must be >= 1, got {n}")
    for var in THREAD_VARS:
        os.environ[var] = str(n)
    import torch

    torch.set_num_threads(n)


def alternated_args(doc: str, argv, scene: str, rounds: int):
    """Parsed options of the benchmarks that alternate two settings of ``Objective.evaluate`` in
    one process (``--scene``, ``--masks``, ``--rounds``, ``--threads``), threads set."""
    import argparse

    p = argparse.ArgumentParser(description=doc.split("\n")[0])
    p.add_argument("--scene", default=scene, help=f"built-in scene name or file (default {scene})")
    p.add_argument("--masks", type=int, default=1024, help="random masks per evaluate round (default 1024)")
    p.add_argument("--rounds", type=int, default=rounds, help=f"alternations of the two settings (default {rounds})")
    p.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    a = p.parse_args(argv)
    set_threads(a.threads)
    return a


def machine() -> dict:
    """A short description of where the figures were measured."""
    import torch

    return {"python": platform.python_version(), "torch": torch.__version__,
            "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "load_avg_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None}


def random_masks(n: int, n_elements: int = 64, k: int = 32, seed: int = 0):
    """(n, n_elements) float64 0/1 masks with k ones each, reproducible."""
    import numpy as np

    rng = np.random.default_rng(seed)
    out = np.zeros((n, n_elements), dtype=np.float64)
    for i in range(n):
        out[i, rng.choice(n_elements, k, replace=False)] = 1.0
    return out


def named_masks(n_elements: int, k: int, random_seed: int = 99) -> dict:
    """The fidelity masks of issue 17: 'uniform' (k spread evenly), 'random' (one random mask of
    ``random_seed``), 'edges' (the k/2 outermost elements on each side, whose peak can leave the
    scatterer) and 'centre' (the k middle ones); float64 0/1 arrays."""
    import numpy as np

    uniform = np.zeros(n_elements)
    uniform[[(i * n_elements) // k for i in range(k)]] = 1
    edges = np.zeros(n_elements)
    edges[: k // 2] = 1
    edges[n_elements - (k - k // 2):] = 1
    centre = np.zeros(n_elements)
    centre[(n_elements - k) // 2:(n_elements - k) // 2 + k] = 1
    return {"uniform": uniform, "random": random_masks(1, n_elements, k, seed=random_seed)[0], "edges": edges,
            "centre": centre}


def uniform_mask(n_elements: int = 64, k: int = 32):
    """Every (n_elements // k)-th element on (the regular sparse array)."""
    import numpy as np

    m = np.zeros(n_elements, dtype=np.float64)
    m[:: n_elements // k] = 1.0
    return m


def load_tests_module(name: str):
    """Import ``tests/<name>.py`` by path (the tests folder is not a package): the PyMUST
    pipelines the benchmarks compare against."""
    path = os.path.join(ROOT, "tests", f"{name}.py")
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def load_pymust_pipeline():
    """Import ``tests/pymust_pipeline.py`` (the 2-D PyMUST pipeline)."""
    return load_tests_module("pymust_pipeline")


def peak_rss_gib() -> float:
    """Resident peak of this process so far (``ru_maxrss``), GiB."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20


def si_mse(k, ref) -> float:
    """Scale-invariant MSE of kernel ``k`` against ``ref`` (complex arrays), as in the tests."""
    import numpy as np

    k = np.asarray(k, dtype=np.complex128)
    ref = np.asarray(ref, dtype=np.complex128)
    a = np.vdot(k, ref) / np.vdot(k, k)
    return float(np.linalg.norm(a * k - ref) ** 2 / np.linalg.norm(ref) ** 2)


class Timer:
    """``with Timer() as t: ...`` then ``t.s`` (seconds, perf_counter)."""

    def __enter__(self):
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.s = time.perf_counter() - self.t0


def table(rows, headers) -> str:
    """Plain-text table of rows (lists of values already formatted or numbers)."""
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    cells = [[fmt(v) for v in r] for r in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(headers)]
    line = "  ".join(h.ljust(w) for h, w in zip(headers, widths))
    out = [line, "  ".join("-" * w for w in widths)]
    out += ["  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in cells]
    return "\n".join(out)


def emit_json(record: dict) -> None:
    """The machine-readable result: one JSON line, last line of the output."""
    print(json.dumps(record, sort_keys=False), flush=True)


def finish(record: dict, out: str | None) -> int:
    """Write ``record`` as JSON to ``out`` (its folder made; nothing when None), then print it as
    the last line (:func:`emit_json`); a benchmark's exit status 0."""
    import os

    if out:
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        with open(out, "w") as fh:
            json.dump(record, fh, indent=1)
            fh.write("\n")
    emit_json(record)
    return 0


def cache_files() -> set | None:
    """Names of the fast-path basis files in the on-disk cache (None when the cache is off)."""
    from arraysel.io.cache import cache_dir

    folder = cache_dir()
    if folder is None:
        return None
    try:
        return {f for f in os.listdir(folder) if f.startswith("psf-basis-") and not f.endswith((".lock", ".tmp"))}
    except FileNotFoundError:
        return set()


def basis_source(before: set | None) -> str:
    """How the basis of the model just built was obtained, from the cache listing taken before."""
    if before is None:
        return "built (cache off)"
    return "built (now cached)" if cache_files() - before else "loaded from disk cache"


def best_known_start(scene: str):
    """``(objective, mask)``: built-in scene ``scene``'s objective with its neighbourhoods prepared,
    and its best-known selection as a boolean mask (SystemExit when it has none)."""
    import numpy as np

    from arraysel.objective.neighbours import prepare_neighbourhoods
    from arraysel.objective.psf_objective import build_objective
    from arraysel.scenes.best_known import best_known

    obj = build_objective(scene)
    prepare_neighbourhoods(obj)
    known = best_known(scene, int(obj.k))
    if known is None:
        raise SystemExit(f"{scene}: no best-known selection to start from")
    base = np.zeros(int(obj.n_elements), dtype=bool)
    base[known["elements"]] = True
    return obj, base
