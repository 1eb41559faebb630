"""The fast-path basis on disk: load it from the cache of :mod:`arraysel.io.cache` (keyed by the
scene physics and the basis settings) or build and store it."""
from __future__ import annotations

import torch

from arraysel.physics.psf.basis import BUILD_RANK_TOL, PairBasis
from arraysel.physics.psf.state import CERTIFICATE_DENSE, DENSE, SPARSE

#: version of the stored state (:meth:`PairBasis.state` plus ``window_estimate``); bump it when
#: its keys or meaning change (11: ``window_estimate`` added; 13: sketched bases from a sparse
#: sign sketch over tiles of pixels; 14: ``pair_channels`` stored receive-element major)
BASIS_VERSION = 14
#: the stored model's :meth:`~arraysel.physics.psf.operator.PSFModel.window_estimate`, read
#: before the basis so that a cold start need not recompute it for the memory guard
WINDOW_KEY = "window_estimate"


def _key(model) -> tuple:
    from arraysel import __version__

    return (__version__, BASIS_VERSION, model.setup, str(model.dtype), model.margin, model.block, BUILD_RANK_TOL)


def stored_window_estimate(model) -> int | None:
    """The window estimate stored with ``model``'s basis (None when it is not cached, or not a
    positive whole number: the entry is then reported and rebuilt by the full load): the same
    number :meth:`~arraysel.physics.psf.operator.PSFModel.window_estimate` computes, without its
    delay-and-sum plans."""
    from arraysel.io import cache

    got = cache.peek("psf-basis", _key(model), [WINDOW_KEY])
    if got is None:
        return None
    value = got[WINDOW_KEY]
    if value.numel() != 1 or value.is_complex() or value.is_floating_point() or int(value) <= 0:
        return None
    return int(value)


#: tensors every stored basis has (besides ``U``, present when V holds singular vectors)
_REQUIRED = (tuple(DENSE) + tuple(CERTIFICATE_DENSE) + tuple(f"{k}_{part}" for k in SPARSE
                                     for part in ("crow", "col", "val", "shape"))
             + ("err", "core_pix", "Snext", "meta", "rank_tail", "off", "row_energy", "missed", WINDOW_KEY))


def check_state(model, state: dict) -> None:
    """Raise ``ValueError`` naming the first fault when a stored state cannot be ``model``'s basis:
    a tensor missing, or sizes that do not fit together (the pair count, the rank of V and U,
    the window estimate)."""
    missing = [k for k in _REQUIRED if k not in state]
    if missing:
        raise ValueError(f"tensor {missing[0]!r} is missing")
    ne = model.n_elements
    pairs = ne * (ne + 1) // 2
    meta, V = state["meta"], state["V"]
    if meta.dim() != 1 or meta.numel() != 5 or meta.is_floating_point():
        raise ValueError(f"meta holds {list(meta.shape)} {meta.dtype}, not 5 whole numbers")
    rank = int(meta[2])
    if V.dim() != 2 or V.shape[0] != rank or rank < 1:
        raise ValueError(f"V has shape {list(V.shape)} for rank {rank}")
    U = state.get("U")
    if U is None and rank != pairs:
        raise ValueError(f"tensor 'U' is missing for a basis of rank {rank} < {pairs} pairs")
    if U is not None and list(U.shape) != [pairs, rank]:
        raise ValueError(f"U has shape {list(U.shape)}, expected [{pairs}, {rank}]")
    if state[WINDOW_KEY].numel() != 1 or int(state[WINDOW_KEY]) <= 0:
        raise ValueError("the window estimate is not a positive number")


def load_or_build_basis(model) -> PairBasis:
    """The full (stored-rank) pair basis of ``model``: loaded from the on-disk cache, or built
    (with progress and size hints) and stored; the stored state is :meth:`PairBasis.state`,
    a dict of named tensors, and ``window_estimate``."""
    from arraysel.io import cache

    built = []

    def build() -> dict:
        from arraysel.io.allocator import malloc_tuned

        # large temporaries reuse the heap during the build (faster at 256 elements,
        # ``docs/performance.md``), and the process gives that memory back after it
        with malloc_tuned():
            built.append(PairBasis.build(model, rank_tol=BUILD_RANK_TOL))
        return {**built[0].state(), WINDOW_KEY: torch.tensor(model.window_estimate())}

    restored = []

    def check(state: dict) -> None:  # a loaded state that is not a basis is damage: rebuilt
        check_state(model, state)
        restored.append(PairBasis.from_state(model, state))

    cache.load_or_build(
        "psf-basis", _key(model),
        build, what="the PSF fast-path basis",
        size_hint=model.basis_stored_bytes(), seconds_hint=model.basis_build_seconds(), check=check)
    return built[0] if built else restored[-1]
