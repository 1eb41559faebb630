"""The gradient and Hessian of the PSF loss at a selection, from the pair basis.

The image on region E of soft element weights ``w`` is bilinear in them:
``y(w) = sum_{e <= j} w_e w_j H_ej`` (``H_p`` the pair images on E, rows of the basis's ``U V``).
The kernel of a selection whose peak tier 1 certifies is a window of that image
(:meth:`~arraysel.physics.psf.refinement.Refinement.kernels` with ``tier_one``), so the loss is
``L(w) = l(y(w))`` with ``l`` the window cut, normalisation, metrics and weighting: a graph on
the window's pixels only. At a 0/1 selection ``m``:

* ``dy/dw_e = J_e = G_e + m_e H_ee``, with ``G_e = sum_{j in m} H_ej`` the element rows that the
  neighbourhood base of ``m`` already holds (:meth:`~arraysel.physics.psf.basis.PairBasis.swap_base`,
  from the bases the objective keeps, :class:`~arraysel.objective.swapbases.SwapBases`);
* the gradient is ``g = J gy`` with ``gy = dl/dy`` (one backward pass through ``l``);
* the Hessian is ``J (d2l/dy2) J^T`` (``Ne`` Hessian-vector products through ``l`` alone, in one
  batched pass) plus ``<gy, d2y/dw_e dw_j>``: ``<gy, H_ej>`` off the diagonal and
  ``2 <gy, H_ee>`` on it, every pair at once as ``U (V gy)``.

:func:`pair_model` returns them, or None where this does not apply (no basis, a selection whose
kernel tier 1 does not settle); :meth:`~arraysel.objective.psf_objective.Objective.mask_hessian`
then takes the autograd of ``mask_loss`` through the whole basis, whose values these equal to
rounding (``tests/test_pair_model.py``). The Hessian-vector products then
run through the metrics' graph only, not through the basis's product as well
(``benchmarks/bench_quadratic_model.py`` times both ways side by side).
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = ["pair_model"]


def _model_inputs(model, w: torch.Tensor, bases=None):
    """``(leaf, J, kappa)`` of one point's model at the 0/1 selection ``w`` (1, Ne): its image on
    E as a real leaf ``(1, nz, nx, 2)`` requiring grad, the rows ``J`` (Ne, 2 Npix) float64 and the
    kernel cut from the leaf; None when the kernel is not tier 1's window of the image."""
    basis = model.basis
    if basis is None:
        return None
    with torch.no_grad():
        img, eps, win_err = basis.images(w, with_error=True)
    leaf = torch.view_as_real(img.detach()).clone().requires_grad_(True)
    kappa, ok = basis.refinement.kernels(w, images=(torch.view_as_complex(leaf), eps, win_err), tier_one=True)
    if not bool(ok.all()):
        return None
    with torch.no_grad():
        m = w[0].detach()
        _y, G = basis.swap_base(m, bases)
        ne = m.shape[0]
        ar = torch.arange(ne)
        diag = basis.pair_rows(basis.pair_lookup()[ar, ar]).to(G.device, torch.float64)
        J = G + (m.to(G.device, torch.float64) != 0)[:, None] * diag
    return leaf, J, kappa


def _flat(t: torch.Tensor) -> torch.Tensor:
    """A leaf-shaped tensor (..., nz, nx, 2) as the basis's row layout (..., 2 Npix): [re | im]."""
    lead = t.shape[:-3]
    return torch.cat([t[..., 0].reshape(*lead, -1), t[..., 1].reshape(*lead, -1)], dim=-1)


def _unflat(rows: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Rows (B, 2 Npix) in the basis's layout as (B, *like.shape) tensors of ``like``'s dtype."""
    n = rows.shape[-1] // 2
    shape = like.shape[:-1]
    return torch.stack([rows[:, :n].reshape(-1, *shape), rows[:, n:].reshape(-1, *shape)], dim=-1).to(like.dtype)


def _pair_term(basis, gy: torch.Tensor) -> torch.Tensor:
    """``(Ne, Ne)`` float64: ``<gy, H_ej>`` for ``e != j`` and ``2 <gy, H_ee>`` on the diagonal
    (the second derivatives of the image, against the image gradient ``gy`` (2 Npix,))."""
    v = gy.to(basis.V.device, basis.V.dtype)
    q = basis.U @ (basis.V @ v) if basis.U is not None else basis.V @ v
    out = q.double().cpu()[basis.pair_lookup()]      # (Ne, Ne): pair (e, j) in either order
    out.diagonal().mul_(2)
    return out


def pair_model(objective, mask, hessian: bool = True):
    """``(total, g, H)`` of the objective's ``mask_loss`` at the 0/1 selection ``mask`` (Ne,):
    the loss (float), its gradient (Ne,) and, with ``hessian``, its Hessian (Ne, Ne) (else None),
    float64, from the pair basis (module docstring); None where it does not apply (a point without
    a basis or whose kernel tier 1 does not settle)."""
    ne = objective.n_elements
    w = torch.as_tensor(np.asarray(mask, dtype=np.float64), dtype=objective.dtype,
                        device=objective.device).reshape(1, ne)
    parts = []
    for model in objective.psfs:
        got = _model_inputs(model, w, objective.swap_bases(model))
        if got is None:
            return None
        parts.append(got)
    leaves = [p[0] for p in parts]
    total, _terms = objective._psf_loss(w, kappas=[p[2] for p in parts])
    if not total.requires_grad:
        return None
    grads = torch.autograd.grad(total.sum(), leaves, create_graph=hessian)
    gys = [_flat(gl.detach())[0] for gl in grads]                      # dl/dy of each point, (2 Npix,)
    g = torch.zeros(ne, dtype=torch.float64)
    for (leaf, J, _), gy in zip(parts, gys):
        g += (J @ gy.to(J.device, torch.float64)).cpu()
    H = None
    if hessian:
        H = torch.zeros(ne, ne, dtype=torch.float64)
        for gy, model in zip(gys, objective.psfs):
            H += _pair_term(model.basis, gy)
        needs = [gl.requires_grad for gl in grads]
        if any(needs):
            dirs = [_unflat(J, leaf) for (leaf, J, _) in parts]        # (Ne, 1, nz, nx, 2) each
            hv = torch.autograd.grad([gl for gl, n in zip(grads, needs) if n],
                                     leaves, grad_outputs=[d for d, n in zip(dirs, needs) if n],
                                     is_grads_batched=True, allow_unused=True)
            for (leaf, J, _), h in zip(parts, hv):
                if h is not None:
                    H += (J @ _flat(h.detach()[:, 0]).to(J.device, torch.float64).T).cpu()
        H = 0.5 * (H + H.T)
    return float(total.detach().sum()), g.numpy(), None if H is None else H.numpy()
