"""The compiled scoring of a batch against torch's operations, side by side in one process.

Batched ``Objective.evaluate`` of the same random masks with the compiled passes that serve a
batch without gradient on the CPU (the Table-1 metrics, ``arraysel.objective.metric_kernels``;
the certificates' peak search and the window cut, ``peakkernels.peak_stats`` and
``peakkernels.cut_windows_compiled``) switched on, then off (torch's operations, as every
gradient step and every other device uses them). The two settings alternate ``--rounds`` times
(this machine's speed drifts between runs, so only alternated figures are compared). The
Means of the two settings are compared with the Mean of the same kernels scored in float64:
the compiled metrics sum in float64, torch's in float32.

Usage::

    python benchmarks/bench_compiled.py [--scene paper] [--masks 1024] [--rounds 4]

The last output line is a JSON record.
"""
from __future__ import annotations

import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as C  # noqa: E402


def main(argv=None):
    a = C.alternated_args(__doc__, argv, scene="paper", rounds=4)
    import numpy as np
    import torch

    from arraysel.objective import metrics as M
    from arraysel.objective.psf_objective import Objective
    from arraysel.physics import compiled

    default = compiled.MIN_BATCH

    def use_compiled(on: bool):
        # off: every batch counts as small, as a gradient step's (the block bounds are summed
        # compiled either way once a few small batches have passed)
        compiled.MIN_BATCH = default if on else 1 << 62

    obj = Objective(a.scene)
    if obj.psf.basis is None:
        raise SystemExit(f"scene {a.scene!r} has no fast path")
    masks = C.random_masks(a.masks, obj.n_elements, obj.k, seed=1).astype(np.float32)
    for on in (True, False):  # warm-up: plans, compiled code
        use_compiled(on)
        obj.evaluate(masks[:256])
    times = {True: [], False: []}
    means = {}
    for r in range(a.rounds):
        for on in ((True, False) if r % 2 == 0 else (False, True)):
            use_compiled(on)
            t = time.perf_counter()
            out = obj.evaluate(masks, return_kernels=(r == 0))
            times[on].append((time.perf_counter() - t) / a.masks * 1e3)
            if r == 0:
                means[on] = out
    use_compiled(True)
    kern = torch.from_numpy(means[True]["kernels"]).to(torch.complex128)
    ref = obj.psf.reference_kernel().to(torch.complex128)
    exact = M.psf_metrics(kern, kappa_ref=ref, compiled=False, **obj.metric_kw)["Mean"].numpy()
    err = {on: float(np.abs(means[on]["Mean"] - exact).max()) for on in (True, False)}
    print(f"scene {a.scene}, {a.masks} random masks, {a.rounds} alternated rounds, {a.threads} threads")
    print(f"{'':28s} {'compiled':>10s} {'torch':>10s}")
    print(f"{'ms a mask, each round':28s} " + " / ".join(f"{x:.2f}" for x in times[True])
          + "   |   " + " / ".join(f"{x:.2f}" for x in times[False]))
    print(f"{'ms a mask, median':28s} {statistics.median(times[True]):10.2f} {statistics.median(times[False]):10.2f}")
    print(f"{'max |Mean - float64 Mean|':28s} {err[True]:10.1e} {err[False]:10.1e}")
    print(json.dumps({"machine": C.machine(), "scene": a.scene, "masks": a.masks,
                      "ms_per_mask_compiled": times[True], "ms_per_mask_torch": times[False],
                      "mean_error_compiled": err[True], "mean_error_torch": err[False]}))


if __name__ == "__main__":
    main()
