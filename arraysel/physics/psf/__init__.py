"""Point-spread function (PSF) synthesis for batches of element selections.

The operator and its method are described in :mod:`arraysel.physics.psf.operator`. Modules:

* :mod:`~arraysel.physics.psf.setup`: :class:`PSFSetup` (a scene's physics part) and the grid conventions;
* :mod:`~arraysel.physics.psf.window`: the kernel convention (window on the peak, unit L2 norm);
* :mod:`~arraysel.physics.psf.operator`: :class:`PSFModel`, the exact path and the fast/exact dispatch;
* :mod:`~arraysel.physics.psf.sizing`: the model's memory and time sizing (basis build, exact path);
* :mod:`~arraysel.physics.psf.basis`: the fast path's pair basis, :class:`PairBasis`, and its entry
  points (``PairBasis.build``, ``PairBasis.from_state``), truncation, images on E and the band;
  it is made of the parts below;
* :mod:`~arraysel.physics.psf.layout`: the basis's layout (regions, pairs, blocks, strip order);
* :mod:`~arraysel.physics.psf.build`: the basis build (sample ranges, windowed pair I/Q, pair
  images, compression, strip factors);
* :mod:`~arraysel.physics.psf.state`: the stored tensors, their error constants and serialisation;
* :mod:`~arraysel.physics.psf.certificate`: envelopes and block bounds of ``|I|``;
* :mod:`~arraysel.physics.psf.refinement`: the certified kernels, peak location, ties and loose blocks;
* :mod:`~arraysel.physics.psf.store`: the basis on disk (load or build);
* :mod:`~arraysel.physics.psf.settings`: the environment variables the operator reads.
"""
from arraysel.io.cache import cache_dir
from arraysel.physics.psf.basis import BUILD_RANK_TOL, ErrorConstants, PairBasis, pair_index, pair_products
from arraysel.physics.psf.operator import PSFModel, Transmit
from arraysel.physics.psf.settings import basis_limit_bytes, memory_limit_bytes
from arraysel.physics.psf.setup import PSFSetup
from arraysel.physics.psf.store import BASIS_VERSION
from arraysel.physics.psf.window import window_and_normalise

__all__ = ["BASIS_VERSION", "BUILD_RANK_TOL", "ErrorConstants", "PSFModel", "PSFSetup", "PairBasis", "Transmit",
           "basis_limit_bytes", "cache_dir", "memory_limit_bytes", "pair_index", "pair_products",
           "window_and_normalise"]
