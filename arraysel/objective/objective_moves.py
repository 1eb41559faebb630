"""How :class:`~arraysel.objective.psf_objective.Objective` scores a selection's neighbours: the
moves scored from the selection (:func:`score_moves`), the neighbourhood bases kept per field
point (:func:`swap_bases`), what is formed once before a search (:func:`prepare_neighbourhoods`)
and the neighbourhood a search asks for (:func:`moves_neighbourhood`). The objective's methods
call these.
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = ["score_moves", "swap_bases", "prepare_neighbourhoods", "moves_neighbourhood"]


def score_moves(objective, mask, out, into, return_kernels: bool = False) -> dict[str, np.ndarray]:
    """:meth:`Objective.evaluate_moves <arraysel.objective.psf_objective.Objective.evaluate_moves>`:
    the neighbours of the 0/1 selection ``mask`` that switch ``out[i]`` off and ``into[i]`` on,
    scored by the objective's neighbourhood where it has one (a 3-D scene's fast path), else
    imaged from the selection by each imager; counted as ``B`` evaluations."""
    from arraysel.objective.matrix_neighbours import check_selection
    from arraysel.objective.neighbours import check_moves

    m, a, b = check_moves(mask, out, into)
    check_selection(m, objective.n_elements)
    nb = objective._neighbourhood()
    if nb is not None and not return_kernels and a.shape[0]:
        with torch.no_grad(), objective._timed():
            nb.select(m)
            res = nb.score(nb.move_columns(a, b), int(a.shape[0]))
            objective.evaluations += int(a.shape[0])
        return {k: res[k] for k in objective._columns}
    if return_kernels:
        objective._kernels_only("evaluate_moves")
    with torch.no_grad(), objective._timed():
        base = objective.as_masks(m[None])[0]
        res = objective._score(int(a.shape[0]), lambda im, i, n: im.image_moves(base, a[i:i + n], b[i:i + n],
                                                                                bases=objective.swap_bases(im.model)),
                               return_kernels)
    return objective._images_out(res, return_kernels, False)


def swap_bases(objective, model):
    """The neighbourhood bases kept for the field point of ``model`` (one of :attr:`Objective.psfs`;
    :class:`~arraysel.objective.swapbases.SwapBases`): the state a search's neighbourhoods and
    the pair model share, kept here, not in the physics."""
    from arraysel.objective.swapbases import SwapBases

    kept = objective.__dict__.setdefault("_swap_bases", {})
    if id(model) not in kept:
        kept[id(model)] = SwapBases()
    return kept[id(model)]


def prepare_neighbourhoods(objective) -> bool:
    """Form now what :meth:`Objective.evaluate_swaps` shares between selections, so that a
    search's first neighbourhoods do not pay for it: each 1-D point's pair-image rows
    (:meth:`~arraysel.physics.psf.basis.PairBasis.fill_pair_rows`; a few seconds and
    ``k``-independent memory: 0.32 GiB on the paper scene, 1.3 GiB for 128 elements), a 3-D
    scene's elements' transmit rows, their diagonal terms and the right factors of the cross terms
    (:mod:`arraysel.objective.matrix_neighbours`; about 1.3 GiB on matrix-1024). Returns whether
    everything is kept (False: beyond the memory cap, each neighbourhood forms the rows it needs)."""
    done = True
    for im in objective.imagers:
        done = im.prepare_moves() and done
    nb = objective._neighbourhood()
    if nb is not None:
        nb.diagonal()
        nb.rights()
    return done


def moves_neighbourhood(objective):
    """The :class:`~arraysel.objective.contract.MovesNeighbourhood` of an objective that scores
    masks by :meth:`Objective.evaluate`: :meth:`Objective.evaluate_moves`, prepared by
    :meth:`Objective.prepare_neighbourhoods`; None for a scene whose imagers image a selection's
    neighbours only as masks (:attr:`~arraysel.physics.imaging.Imager.moves_from_selection`: a
    sector scene's beam pattern) unless its planes score all swaps at once (a 3-D scene's fast
    path on the CPU)."""
    from arraysel.objective.contract import MovesNeighbourhood

    if not all(im.moves_from_selection for im in objective.imagers) and objective._neighbourhood() is None:
        return None
    nb = objective._neighbourhood()
    return MovesNeighbourhood(objective.evaluate_moves, objective.prepare_neighbourhoods,
                              block=None if nb is None else nb.block())
