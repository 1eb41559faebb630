"""The fast-path basis on disk: load it from the cache of :mod:`arraysel.io.cache` (keyed by the
scene physics and the basis settings) or build and store it."""
from __future__ import annotations

import torch

from arraysel.physics.psf.basis import BUILD_RANK_TOL, PairBasis

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
    """The window estimate stored with ``model``'s basis (None when it is not cached): the same
    number :meth:`~arraysel.physics.psf.operator.PSFModel.window_estimate` computes, without its
    delay-and-sum plans."""
    from arraysel.io import cache

    got = cache.peek("psf-basis", _key(model), [WINDOW_KEY])
    return None if got is None else int(got[WINDOW_KEY])


def load_or_build_basis(model) -> PairBasis:
    """The full (stored-rank) pair basis of ``model``: loaded from the on-disk cache, or built
    (with progress and size hints) and stored; the stored state is :meth:`PairBasis.state`,
    a dict of named tensors, and ``window_estimate``."""
    from arraysel.io import cache

    built = []

    def build() -> dict:
        from arraysel.io.allocator import malloc_tuned

        # large temporaries reuse the heap during the build (malloc_tuned: 172 -> 151 s at 256
        # elements), and the process gives that memory back after it
        with malloc_tuned():
            built.append(PairBasis(model, rank_tol=BUILD_RANK_TOL))
        return {**built[0].state(), WINDOW_KEY: torch.tensor(model.window_estimate())}

    state = cache.load_or_build(
        "psf-basis", _key(model),
        build, what="the PSF fast-path basis",
        size_hint=model.basis_stored_bytes(), seconds_hint=model.basis_build_seconds())
    return built[0] if built else PairBasis.from_state(model, state)
