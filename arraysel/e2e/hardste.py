"""The HARD-STE selection module of end-to-end training (``docs/training.md``) and its temperature schedule.

A *selection module* is an ``nn.Module`` called as ``selection(tau, generator) -> (P, P_soft)``
(the protocol is stated in :mod:`arraysel.e2e.trainer`); :class:`HardSTESelection` is the paper's.
"""
from __future__ import annotations


import torch
import torch.nn as nn

from arraysel.errors import ParameterError, check_number
from arraysel.scenes.schema import training_default as _T
from arraysel.selectors.relax import cosine_temperature, sequential_selection

__all__ = ["tau_schedule", "HardSTESelection"]


def tau_schedule(step: int, tau_start: float = _T("tau_start"), tau_end: float = _T("tau_end"),
                 tau_steps: int = _T("tau_steps")) -> float:
    """Cosine decay of the softmax temperature from ``tau_start`` (step 0) to
    ``tau_end`` (step ``tau_steps``, the scene key ``training.tau_steps``), constant afterwards
    (:func:`arraysel.selectors.relax.cosine_temperature`). Defaults: the scene schema's
    ``[training]``."""
    return cosine_temperature(step, tau_start, tau_end, tau_steps)


class HardSTESelection(nn.Module):
    """HARD-STE selection of ``k`` of ``n_elements``: logits ``l`` of shape ``(Ne, k)``.

    Columns are drawn one after another; for column ``j`` the elements already
    chosen are masked out and ``p_j = softmax(l_j / tau)`` over the others.
    In training mode (``sample=True``) the element is drawn from ``p_j``
    with the ``generator`` passed in; in ``eval()`` mode, or with
    ``sample=False``, it is the most probable one. The draw is
    :func:`arraysel.selectors.relax.sequential_selection`. The output
    is ``P = (P_hard - P_soft).detach() + P_soft``: exactly one-hot columns
    with distinct rows in the forward pass, the softmax gradient backwards.

    ``generator`` (optional) draws the initial logits ``init_std * N(0, 1)``;
    without it they start at 0.
    """

    def __init__(self, n_elements: int, k: int, *, generator: torch.Generator | None = None,
                 init_std: float = 0.01, sample: bool = True):
        super().__init__()
        ne = check_number("n_elements", n_elements, lo=1, integer=True)
        k = check_number("k", k, lo=1, hi=ne, integer=True)
        init = torch.zeros(ne, k)
        if generator is not None:
            init = check_number("init_std", init_std, lo=0) * torch.randn(ne, k, generator=generator)
        self.logits = nn.Parameter(init)
        self.sample = bool(sample)

    @property
    def n_elements(self) -> int:
        return self.logits.shape[0]

    @property
    def k(self) -> int:
        return self.logits.shape[1]

    def forward(self, tau: float = 1.0, generator: torch.Generator | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        tau = check_number("tau", tau, lo=0, lo_open=True)
        sampling = self.training and self.sample
        if sampling and generator is None:
            raise ParameterError("HardSTESelection samples in training mode: pass a "
                                 "torch.Generator (or call .eval() / set sample=False)")
        # the draw runs where the generator lives (the trainer's is on the CPU); the
        # (Ne, k) logits are tiny, and moving them keeps the gradient path
        where = generator.device if sampling else self.logits.device
        rel = sequential_selection(self.logits.to(where), tau, hard=True, sample=sampling,
                                   generator=generator if sampling else None)
        dev = self.logits.device
        return rel.P.to(dev), rel.P_soft.to(dev)

    @torch.no_grad()
    def indices(self, tau: float = 1.0) -> torch.Tensor:
        """The deterministic (argmax) selection, sorted element indices ``(k,)``."""
        was = self.training
        self.eval()
        try:
            P, _ = self(tau)
        finally:
            self.train(was)
        return torch.nonzero(P.sum(1) > 0.5).flatten().sort().values
