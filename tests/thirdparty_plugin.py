"""A third-party selector plugin written against the documented contract (docs/plugins.md), kept
unchanged as a fixture: every member a plugin may use is used here, so a change of arraysel's
internals that breaks a plugin in the field breaks tests/test_thirdparty_plugin.py first.

Do not modernise this file when arraysel's internals change: it stands for code arraysel's users
wrote and will not rewrite.

``tp-descent``: a few gradient steps on ``mask_loss`` from uniform soft weights, the top k of the
weights, then batches of random swaps scored with ``score`` and ``score_indices`` until the budget
ends (``BudgetExhausted`` propagates), reading ``best``, ``best_mean`` and ``remaining()``.
"""
import numpy as np
import torch

from arraysel.selectors.contract import Option, Selector, indices_to_mask, numpy_rng, torch_rng
from arraysel.selectors.hookspecs import hookimpl

#: what the last run saw, for the tests: the problem's description and the search's state
SEEN = {}


class ThirdPartyDescent(Selector):
    name = "tp-descent"
    description = "gradient steps on mask_loss, then random swaps (a third-party plugin)"
    options = {"steps": Option(int, 3, "gradient steps on mask_loss", lo=0, hi=100),
               "batch": Option(int, 8, "random swaps scored at once", lo=1, hi=256)}
    uses_gradients = True
    needs_evaluations = True

    def batch_size(self, n_elements, k):
        return self.options["batch"]

    def select(self, objective, k, seed):
        n = objective.n_elements
        rng = numpy_rng(seed)
        torch_rng(seed, objective.device)
        SEEN.update(n_elements=n, scene=objective.scene, device=str(objective.device), dtype=objective.dtype)
        w = torch.full((1, n), k / n, dtype=objective.dtype, device=objective.device, requires_grad=True)
        for _ in range(self.options["steps"]):
            total, terms = objective.mask_loss(w)
            (g,) = torch.autograd.grad(total.sum(), w)
            with torch.no_grad():
                w -= 0.05 * g / (g.abs().max() + 1e-12)
                w.clamp_(0, 1)
        order = np.argsort(-w.detach().cpu().numpy()[0], kind="stable")
        current = sorted(int(i) for i in order[:k])
        means = objective.score(indices_to_mask(current, n)[None])
        best, best_mean = list(current), float(means[0])
        SEEN["first_mean"] = best_mean
        while True:
            cand = []
            for _ in range(self.options["batch"]):
                c = list(best)
                if 0 < k < n:
                    out = int(rng.integers(k))
                    into = int(rng.choice(np.setdiff1d(np.arange(n), c)))
                    c[out] = into
                cand.append(sorted(c))
            scores = objective.score_indices(cand)
            i = int(np.argmin(scores))
            if scores[i] < best_mean:
                best, best_mean = cand[i], float(scores[i])
            SEEN.update(best=objective.best, best_mean=objective.best_mean, remaining=objective.remaining())
            if 0 == k or k == n:
                objective.evaluate(indices_to_mask(best, n)[None])
                return best


@hookimpl
def arraysel_register_selectors(register):
    register(ThirdPartyDescent)
