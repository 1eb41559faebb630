"""Relaxations of the (Ne x k) selection matrix, shared by the ``ste`` and ``gumbel`` selectors.

Conventions (the paper's HARD-STE, ``docs/training.md``): logits ``l`` have shape ``(Ne, k)``; column ``j``
chooses one element with probabilities ``p_j = softmax(l_j / tau)``; the
columns are drawn one after the other *without replacement*: elements chosen
by earlier columns are masked out (their score is ``-inf``) in later ones, as
in Deep Probabilistic Subsampling (Huijben et al., 2020). ``P_hard`` holds the
one-hot columns of the drawn elements, ``P_soft`` the masked softmax columns,
and the straight-through matrix is ``P = (P_hard - P_soft).detach() + P_soft``
(forward value ``P_hard``, gradient of ``P_soft``).

Every function works in log space (``log_softmax``) so that temperatures from
1e-3 to 1e3 and logits up to 1e4 stay finite in float32.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from arraysel.objective.losses import l_ent, l_row

__all__ = [
    "Relaxation", "cosine_temperature", "gumbel_noise", "sequential_selection",
    "selection_weights", "column_entropy", "row_penalty", "project_capped_simplex",
]


def cosine_temperature(step: int, tau_start: float = 6.0, tau_end: float = 1.2, tau_steps: int = 1500) -> float:
    """Cosine decay of the temperature from ``tau_start`` (step 0) to ``tau_end``
    (step ``tau_steps``, the scene key ``training.tau_steps``), constant afterwards.

    >>> cosine_temperature(0), cosine_temperature(1500), cosine_temperature(10**6)
    (6.0, 1.2, 1.2)
    """
    if tau_steps <= 0:
        return float(tau_end)
    t = min(max(step, 0), tau_steps) / tau_steps
    return float(tau_end + 0.5 * (tau_start - tau_end) * (1.0 + math.cos(math.pi * t)))


def gumbel_noise(shape, generator: torch.Generator | None = None, *, device=None,
                 dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Standard Gumbel noise ``-log(-log(u))`` from uniforms clamped to ``[tiny, 1 - eps]``
    of ``dtype``, so the noise is always finite (about -4.5 .. 16 in float32)."""
    finfo = torch.finfo(dtype)
    u = torch.rand(shape, generator=generator, device=device, dtype=dtype)
    u = u.clamp(min=finfo.tiny, max=1.0 - finfo.eps)
    return -torch.log(-torch.log(u))


@dataclasses.dataclass
class Relaxation:
    """Result of :func:`sequential_selection`.

    P : (Ne, k) the matrix to feed the loss (straight-through or soft)
    P_soft : (Ne, k) masked softmax columns (differentiable)
    P_hard : (Ne, k) one-hot columns (no gradient)
    indices : the k chosen elements, in column order (distinct)
    """

    P: torch.Tensor
    P_soft: torch.Tensor
    P_hard: torch.Tensor
    indices: list[int]


def sequential_selection(logits: torch.Tensor, tau: float, *, noise: torch.Tensor | None = None,
                         hard: bool = True, sample: bool = False,
                         generator: torch.Generator | None = None, groups: np.ndarray | None = None,
                         by_column: bool = False, counts: np.ndarray | None = None) -> Relaxation:
    """Draw ``k`` distinct elements, one column of ``logits`` (shape ``(Ne, k)``) at a time.

    Parameters
    ----------
    logits : (Ne, k) real tensor (may require grad)
    tau : temperature > 0
    noise : optional (Ne, k) perturbation added to the logits before the
        temperature (Gumbel noise gives the Gumbel-softmax / Gumbel top-k draw)
    hard : return the straight-through matrix as ``P`` (else ``P = P_soft``)
    sample : draw each element from ``p_j`` with ``generator`` instead of
        taking its arg-max (with Gumbel noise the arg-max already is a sample)

    groups : channel groups (one group number per element, :mod:`arraysel.constraints`): an
        element drawn takes its whole group out of the later columns (at most one element per
        group); with ``by_column`` column ``j`` is the categorical choice among the elements of
        group ``j`` (exactly one per group, ``k`` = the number of groups)
    counts : with ``by_column``, the number of elements each group holds (None: one each; the
        quota of separate transmit and receive apertures): the first ``counts[0]`` columns choose
        among the elements of group 0, the next ``counts[1]`` among those of group 1, ...

    The drawn element of each column is always one not chosen before, even
    when scores are NaN or infinite.
    """
    if logits.ndim != 2:
        raise ValueError(f"logits must have shape (Ne, k), got {tuple(logits.shape)}")
    if not tau > 0:
        raise ValueError(f"temperature must be > 0, got {tau}")
    n, k = logits.shape
    if k > n:
        raise ValueError(f"cannot draw k = {k} distinct elements out of Ne = {n}")
    scores_all = logits if noise is None else logits + noise
    scores_all = scores_all / tau
    finfo = torch.finfo(logits.dtype)
    # The draws need no gradient: column j picks among the elements that columns 0 .. j-1 left,
    # from finite, NaN-proof scores (on the host, in float64: exact for any float dtype, and the
    # order of the scores, hence every arg-max, is that of the scores themselves).
    # ``available[j]`` records what column j could choose.
    with torch.no_grad():
        picks = torch.nan_to_num(scores_all.detach(), nan=finfo.min, posinf=finfo.max, neginf=finfo.min)
        picks = picks.t().to(device="cpu", dtype=torch.float64).numpy()
    available = np.ones((k, n), dtype=bool)
    left = np.ones(n, dtype=bool)
    chosen = []
    column_group = None
    if by_column and groups is not None:
        n_groups = int(np.max(groups)) + 1
        per = np.ones(n_groups, dtype=np.int64) if counts is None else np.asarray(counts, dtype=np.int64)
        if int(per.sum()) != k or per.size != n_groups:
            raise ValueError(f"by_column needs one column per group and count: {n_groups} groups holding "
                             f"{int(per.sum())} elements, k = {k}")
        column_group = np.repeat(np.arange(n_groups), per)
    for j in range(k):
        available[j] = left if column_group is None else left & (groups == column_group[j])
        i = int(np.argmax(np.where(available[j], picks[j], -np.inf)))
        if sample:
            with torch.no_grad():
                gone = torch.from_numpy(~available[j]).to(logits.device)
                probs = torch.exp(torch.log_softmax(scores_all[:, j].detach().masked_fill(gone, -math.inf), dim=0))
                if bool(torch.isfinite(probs).all()) and float(probs.sum()) > 0:
                    i = int(torch.multinomial(probs, 1, generator=generator))
        chosen.append(i)
        left[i] = False
        if groups is not None and column_group is None:
            left[groups == groups[i]] = False
    available = torch.from_numpy(available).to(logits.device)
    # All k masked softmax columns at once, as rows of the transposed scores (each row is
    # reduced exactly as one column on its own would be).
    s = scores_all.t().masked_fill(~available, -math.inf).contiguous()
    P_soft = torch.nan_to_num(torch.exp(torch.log_softmax(s, dim=1)), nan=0.0).t().contiguous()
    P_hard = torch.zeros(n, k, dtype=logits.dtype, device=logits.device)
    P_hard[torch.tensor(chosen, device=logits.device), torch.arange(k, device=logits.device)] = 1.0
    P = (P_hard - P_soft).detach() + P_soft if hard else P_soft
    return Relaxation(P=P, P_soft=P_soft, P_hard=P_hard, indices=chosen)


def selection_weights(P: torch.Tensor) -> torch.Tensor:
    """Per-element weights ``(Ne,)`` of a selection matrix: row sums clamped to ``[0, 1]``."""
    return P.sum(dim=1).clamp(0.0, 1.0)


#: ``L_ent``, the mean entropy (nats) of the columns of ``P_soft`` (:func:`arraysel.objective.losses.l_ent`)
column_entropy = l_ent
#: ``L_row = sum_i relu(sum_j P_ij - 1)^2`` (:func:`arraysel.objective.losses.l_row`)
row_penalty = l_row


def project_groups(w: torch.Tensor, k: float, groups: np.ndarray | None = None,
                   counts: np.ndarray | None = None) -> torch.Tensor:
    """:func:`project_capped_simplex` of ``w`` (…, Ne) onto ``sum = k``, or with ``groups`` (one
    group number per element, :mod:`arraysel.constraints`) onto ``sum = counts[g]`` (default one)
    over the elements of every group ``g`` (the relaxation of exactly-one channel groups and of
    the transmit/receive quota)."""
    if groups is None:
        return project_capped_simplex(w, k)
    g = np.asarray(groups, dtype=np.int64)
    out = torch.zeros_like(w)
    for grp in np.unique(g):
        idx = torch.as_tensor(np.flatnonzero(g == grp), device=w.device)
        c = 1.0 if counts is None else float(counts[grp])
        out = out.index_copy(-1, idx, project_capped_simplex(w.index_select(-1, idx), c))
    return out


def project_capped_simplex(w: torch.Tensor, k: float, iters: int = 60) -> torch.Tensor:
    """Euclidean projection of ``w`` (…, Ne) onto ``{0 <= x <= 1, sum(x) = k}``.

    ``x = clip(w - theta, 0, 1)`` with ``theta`` found by bisection (no gradient through theta).
    """
    w_d = w.detach()
    lo = (w_d.min(dim=-1, keepdim=True).values - 1.0)
    hi = w_d.max(dim=-1, keepdim=True).values
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        s = (w_d - mid).clamp(0.0, 1.0).sum(dim=-1, keepdim=True)
        too_big = s > k
        lo = torch.where(too_big, mid, lo)
        hi = torch.where(too_big, hi, mid)
    theta = 0.5 * (lo + hi)
    return (w - theta).clamp(0.0, 1.0)
