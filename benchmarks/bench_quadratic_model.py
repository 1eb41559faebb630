"""How well the loss's linear and quadratic models rank a selection's one-swap neighbours, and
what the quadratic model costs.

    python benchmarks/bench_quadratic_model.py --scenes paper,l11-5v,c5-2v --perturbed 3 --threads 1

Per scene, at its best-known selection (a local optimum: no swap improves it) and at
``--perturbed`` selections two random swaps away from it (seed 0: where a descent of an iterated
local search starts), every one-swap neighbour is scored exactly (``evaluate_swaps``) and its
change of Mean compared with the change the models of ``mask_loss`` predict
(``arraysel.selectors.localsearch.swap_changes``): the gradient alone (``linear``,
``g[into] - g[out]``) and the gradient with the Hessian (``quadratic``, ``mask_hessian``).
Printed per selection and model: the Pearson correlation of predicted and true changes, the
rank (0 = first) by prediction of the best neighbour, and how many of the first chunk of 64 in
predicted order improve on the selection (what a guided descent scores first). Then the seconds of one
gradient, one Hessian (from the pair basis, ``arraysel.objective.pair_model``, and side by side by
autograd through the basis's product, ``Objective.hessian_from_pairs = False``) and one chunk of
64 masks (``evaluate``), the Hessian's cost in masks.
The last line is one JSON record.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import best_known_start, set_threads  # noqa: E402


def _rank_stats(pred, true):
    """Correlation, rank of the best neighbour by prediction, improving ones among the first 64."""
    import numpy as np

    order = np.argsort(pred, kind="stable")
    rank = np.empty(order.size, dtype=np.int64)
    rank[order] = np.arange(order.size)
    first = int((true[order[:64]] < 0).sum())
    return float(np.corrcoef(pred, true)[0, 1]), int(rank[int(np.argmin(true))]), first


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="paper,l11-5v,c5-2v")
    ap.add_argument("--perturbed", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    set_threads(args.threads)
    import numpy as np

    from arraysel.objective.neighbours import swap_pairs
    from arraysel.selectors.localsearch import loss_gradient, loss_quadratic, random_swaps, swap_changes

    record = {"perturbed": args.perturbed, "threads": args.threads, "scenes": {}}
    for scene in [s for s in args.scenes.split(",") if s]:
        obj, base = best_known_start(scene)
        n = int(obj.n_elements)
        rng = np.random.default_rng(0)
        masks = [("best known", base)] + [(f"2 swaps away ({i + 1})", random_swaps(base, 2, rng))
                                          for i in range(args.perturbed)]
        rows = []
        print(f"{scene}: Ne = {n}, k = {int(base.sum())}, {int(base.sum()) * (n - int(base.sum()))} swaps")
        for label, m in masks:
            value = float(obj.evaluate(m[None])["Mean"][0])
            a, b = swap_pairs(m)
            true = obj.evaluate_swaps(m, a, b)["Mean"] - value
            g, H = loss_quadratic(obj, m)
            row = {"selection": label, "Mean": value, "improving": int((true < 0).sum())}
            for name, pred in (("linear", swap_changes(g, None, a, b)), ("quadratic", swap_changes(g, H, a, b))):
                corr, best_rank, first = _rank_stats(pred, true)
                row[name] = {"corr": corr, "best_rank": best_rank, "improving_in_first_64": first}
            rows.append(row)
            print(f"  {label:20s} Mean {value:.6f} improving {row['improving']:5d}  "
                  f"corr linear {row['linear']['corr']:.3f} quadratic {row['quadratic']['corr']:.3f}  "
                  f"best's rank {row['linear']['best_rank']} / {row['quadratic']['best_rank']}  "
                  f"improving of the first 64 {row['linear']['improving_in_first_64']} / "
                  f"{row['quadratic']['improving_in_first_64']}")
        chunk = np.repeat(base[None], 64, axis=0)
        loss_gradient(obj, base), loss_quadratic(obj, base), obj.evaluate(chunk)  # warm
        times = {}
        def autograd_hessian():
            obj.hessian_from_pairs = False
            try:
                return loss_quadratic(obj, base)
            finally:
                obj.hessian_from_pairs = True

        autograd_hessian()
        for name, call in (("gradient", lambda: loss_gradient(obj, base)),
                           ("hessian", lambda: loss_quadratic(obj, base)),
                           ("hessian_autograd", autograd_hessian),
                           ("masks64", lambda: obj.evaluate(chunk))):
            t0 = time.perf_counter()
            for _ in range(3):
                call()
            times[name] = (time.perf_counter() - t0) / 3
        per_mask = times["masks64"] / 64
        print(f"  one gradient {times['gradient']:.3f} s, one Hessian {times['hessian']:.3f} s "
              f"(= {times['hessian'] / per_mask:.0f} masks; by autograd through the basis "
              f"{times['hessian_autograd']:.3f} s, {times['hessian_autograd'] / times['hessian']:.2f}x), "
              f"64 masks {times['masks64']:.3f} s")
        record["scenes"][scene] = {"rows": rows, "seconds": times, "hessian_in_masks": times["hessian"] / per_mask}
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
