"""``gumbel``: Gumbel-softmax relaxation of the (Ne x k) selection matrix.

Each step adds fresh Gumbel noise ``g = -log(-log(u))`` (uniforms clamped to
``[tiny, 1 - eps]``) to the logits and draws the ``k`` columns sequentially
without replacement (Gumbel top-k as in Deep Probabilistic Subsampling):
column ``j`` picks the arg-max of ``(l_j + g_j) / tau`` over the elements
not chosen yet. ``variant=hard`` feeds the straight-through matrix to the
loss, ``variant=soft`` the soft one. Temperature schedule, optimiser and
best-mask bookkeeping are those of ``ste``.
"""
from __future__ import annotations

from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.contract import Option

from .ste import _COMMON, MatrixSelector


class GumbelSelector(MatrixSelector):
    name = "gumbel"
    description = "Gumbel-softmax / Gumbel top-k relaxation of the selection matrix (hard or soft)"
    options = {
        **_COMMON,
        # Gumbel noise is O(1), so the logits must move by O(1): see the
        # measurements in ste.py
        "lr": Option(float, 0.1, "Adam learning rate of the logits", lo=0.0),
        "variant": Option(str, "hard", "hard: straight-through P; soft: P_soft fed to the loss",
                          choices=("hard", "soft")),
    }

    def draw(self, logits, tau, generator):
        from arraysel.selectors.relax import gumbel_noise, sequential_selection

        noise = gumbel_noise(tuple(logits.shape), generator, device=logits.device, dtype=logits.dtype)
        return sequential_selection(logits, tau, noise=noise, hard=self.options["variant"] == "hard",
                                    **(self._groups or {}))


@hookimpl
def arraysel_register_selectors(register):
    register(GumbelSelector)
