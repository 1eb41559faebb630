"""Batched mask evaluation and random search on an executor's workers.

:func:`distributed_random_search` scores ``n_masks`` uniformly random
k-subsets. The masks are cut into chunks of ``chunk`` masks; chunk ``i`` draws
its masks from ``numpy.random.SeedSequence(seed).spawn(n_chunks)[i]``, so the
masks, and the best one (ties broken by chunk order, then by position in the
chunk), do not depend on the executor or on the number of workers.

Example
-------
>>> from arraysel.objective.toy import ToyObjectiveFactory
>>> from arraysel.run.executors import ProcessExecutor
>>> from arraysel.run.random_search import distributed_random_search
>>> with ProcessExecutor(workers=2) as ex:                              # doctest: +SKIP
...     res = distributed_random_search(ToyObjectiveFactory(64, 32), 100_000, None, 0, ex, 4096)
>>> res.elements, res.mean                                             # doctest: +SKIP
"""
from __future__ import annotations

import dataclasses
import math
import os
import time

import numpy as np

from arraysel.errors import ArrayselError, ParameterError, check_number
from arraysel.run.executors import Executor, TaskFailed, as_executor as _as_executor
from arraysel.selectors.contract import finite_or_inf
from arraysel.selectors.starts import random_subsets

__all__ = ["RandomSearchResult", "distributed_random_search", "distributed_evaluate"]


def _random_chunk(objective, item) -> dict:
    """Score one chunk of random masks; return its best (first minimum)."""
    index, seedseq, size, k = item
    n = int(objective.n_elements)
    k = int(objective.k if k is None else k)
    rng = np.random.default_rng(seedseq)
    subsets = random_subsets(rng, size, n, k)
    masks = np.zeros((size, n), dtype=bool)
    np.put_along_axis(masks, subsets, True, axis=1)
    t0 = time.perf_counter()
    means = finite_or_inf(objective.evaluate(masks)["Mean"])
    seconds = time.perf_counter() - t0
    best = int(np.argmin(means))
    return {"chunk": index, "mean": float(means[best]), "position": best,
            "elements": [int(i) for i in subsets[best]], "masks": size, "seconds": seconds,
            "pid": os.getpid()}


@dataclasses.dataclass
class RandomSearchResult:
    """Best of ``n_masks`` random k-subsets (see :func:`distributed_random_search`)."""

    elements: list[int]
    mean: float
    chunk_index: int
    n_masks: int
    n_chunks: int
    chunk: int
    seed: int
    seconds: float
    workers: int
    executor: str
    worker_pids: int

    @property
    def masks_per_second(self) -> float:
        return self.n_masks / self.seconds if self.seconds > 0 else math.inf

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "masks_per_second": self.masks_per_second}


def distributed_random_search(objective_factory, n_masks: int, k: int | None = None, seed: int = 0,
                              executor: Executor | str | None = None, chunk: int = 1024) -> RandomSearchResult:
    """Best of ``n_masks`` uniformly random k-subsets, scored on ``executor``'s workers.

    Parameters
    ----------
    objective_factory : picklable callable building the objective on a worker
        (``objective.worker_factory()``)
    n_masks : masks to score
    k : elements per mask (``None``: the objective's ``k``)
    seed : the search's seed; chunk ``i`` uses ``SeedSequence(seed).spawn(n_chunks)[i]``
    executor : an :class:`Executor` (``None``: in-process)
    chunk : masks per task; the chunks, hence the result, do not depend on the
        number of workers

    Raises :class:`ArrayselError` when a chunk fails after its retries.
    """
    n_masks = int(check_number("n_masks", n_masks, lo=1, integer=True))
    chunk = int(check_number("chunk", chunk, lo=1, integer=True))
    seed = int(check_number("seed", seed, lo=0, integer=True))
    if k is not None:
        k = int(check_number("k", k, lo=1, integer=True))
    ex, own = _as_executor(executor)
    n_chunks = -(-n_masks // chunk)
    streams = np.random.SeedSequence(seed).spawn(n_chunks)
    items = [(i, streams[i], min(chunk, n_masks - i * chunk), k) for i in range(n_chunks)]
    best: tuple[float, int] | None = None
    best_res: dict | None = None
    pids = set()
    t0 = time.perf_counter()
    try:
        for i, res in ex.run_tasks(objective_factory, _random_chunk, items):
            if isinstance(res, TaskFailed):
                raise ArrayselError(f"random search chunk {i} of {n_chunks} failed: {res.message}")
            pids.add(res["pid"])
            key = (res["mean"], res["chunk"])
            if best is None or key < best:
                best, best_res = key, res
    finally:
        seconds = time.perf_counter() - t0
        if own:
            ex.close()
    assert best_res is not None
    mean = best_res["mean"]
    return RandomSearchResult(
        elements=best_res["elements"], mean=mean if math.isfinite(mean) else math.nan,
        chunk_index=best_res["chunk"], n_masks=n_masks, n_chunks=n_chunks, chunk=chunk, seed=seed,
        seconds=seconds, workers=ex.workers, executor=ex.name, worker_pids=len(pids))


def _evaluate_chunk(objective, item) -> dict:
    index, masks = item
    return {"chunk": index, "metrics": objective.evaluate(masks)}


def distributed_evaluate(objective_factory, masks, executor: Executor | str | None = None,
                         chunk: int = 1024) -> dict[str, np.ndarray]:
    """``objective.evaluate(masks)`` computed in chunks of ``chunk`` masks on ``executor``'s
    workers; the metrics come back in the order of ``masks``."""
    masks = np.asarray(masks)
    if masks.ndim != 2 or masks.shape[0] == 0:
        raise ParameterError(f"masks must have shape (B, Ne) with B >= 1, got {masks.shape}")
    chunk = int(check_number("chunk", chunk, lo=1, integer=True))
    ex, own = _as_executor(executor)
    items = [(i, masks[s:s + chunk]) for i, s in enumerate(range(0, masks.shape[0], chunk))]
    parts: dict[int, dict] = {}
    try:
        for i, res in ex.run_tasks(objective_factory, _evaluate_chunk, items):
            if isinstance(res, TaskFailed):
                raise ArrayselError(f"evaluation chunk {i} of {len(items)} failed: {res.message}")
            parts[i] = res["metrics"]
    finally:
        if own:
            ex.close()
    names = list(parts[0])
    return {m: np.concatenate([np.asarray(parts[i][m]) for i in range(len(items))]) for m in names}

