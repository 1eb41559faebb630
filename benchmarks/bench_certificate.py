"""The refinement's block delay-and-sum on raw channels against complex ones, side by side.

Batched ``Objective.evaluate`` of random masks: the certificates' loose blocks summed from the
certificate product's raw channels (``Refinement.raw_channels`` = True, the default) against
the complex, time-ordered channels of ``PairBasis.channels`` (False); the time spent in
``Refinement.refine`` is reported too. The Means must agree exactly.

The two settings alternate ``--rounds`` times (this machine's speed drifts between runs, so
only alternated figures are compared); the basis must be cached or is built first.

Usage::

    python benchmarks/bench_certificate.py [--scene c5-2v] [--masks 1024] [--rounds 3]

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
    a = C.alternated_args(__doc__, argv, scene="c5-2v", rounds=3)
    import numpy as np

    from arraysel.objective.psf_objective import Objective
    from arraysel.physics.psf.refinement import Refinement

    obj = Objective(a.scene)
    basis = obj.psf.basis
    if basis is None:
        raise SystemExit(f"scene {a.scene!r} has no fast path")
    ne, k = obj.n_elements, obj.k
    masks = C.random_masks(a.masks, ne, k, seed=1).astype(np.float32)
    refine_s = [0.0]
    plain_refine = Refinement.refine

    def timed_refine(self, *args, **kw):
        t = time.perf_counter()
        try:
            return plain_refine(self, *args, **kw)
        finally:
            refine_s[0] += time.perf_counter() - t

    Refinement.refine = timed_refine
    obj.evaluate(masks[:256])
    res = {"ms_per_mask": {"raw": [], "complex": []}, "refine_ms_per_mask": {"raw": [], "complex": []}}
    means = {}
    for _ in range(a.rounds):
        for name, raw in (("complex", False), ("raw", True)):
            Refinement.raw_channels = raw
            refine_s[0] = 0.0
            t = time.perf_counter()
            means[name] = np.concatenate([obj.evaluate(masks[c:c + 128])["Mean"] for c in range(0, a.masks, 128)])
            res["ms_per_mask"][name].append(1e3 * (time.perf_counter() - t) / a.masks)
            res["refine_ms_per_mask"][name].append(1e3 * refine_s[0] / a.masks)
    Refinement.refine = plain_refine
    same = bool(np.array_equal(means["raw"], means["complex"]))
    print(f"{a.scene}: {a.rounds} alternated rounds of {a.masks} masks")
    for key, (x, y) in (("ms_per_mask", ("raw", "complex")), ("refine_ms_per_mask", ("raw", "complex"))):
        vx, vy = res[key][x], res[key][y]
        print(f"  {key:20s} {x:8s} {' '.join(f'{v:8.2f}' for v in vx)}   {y:8s} {' '.join(f'{v:8.2f}' for v in vy)}"
              f"   median ratio {statistics.median(vx) / statistics.median(vy):.3f}")
    print(f"  Means of raw and complex channels identical: {same}")
    print(json.dumps({"machine": C.machine(), "scene": a.scene, "results": res, "same_means": same}))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
