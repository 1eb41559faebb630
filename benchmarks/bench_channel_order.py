"""The order in which the compiled per-channel kernels visit (selection, receive element) pairs.

The certificates' channel envelopes are computed one receive channel of one selection at a time:
a neighbour's channel corrected from the selection's held channel sums
(``peakkernels._swap_peaks_kernel``: every swap neighbourhood a search scores; and
``_swap_channels_kernel``, the refinement's corrected channels, written whole), or a small
batch's channel summed from the rows of ``pair_channels`` its selection uses
(``_channel_peaks_kernel``). The pairs are visited receive element by receive element
(``peakkernels.receive_major``, what the package does for the two peak kernels) or selection by
selection (numpy's ``nonzero`` order, what it keeps for the corrected channels). Both orders give the same values,
bit for bit (checked); the figures are the time of one call, the best of ``--repeat``, the two
orders alternated ``--rounds`` times in one process on the same inputs.

Inputs per scene: a random selection of ``k`` of its ``Ne`` elements (seed 0) with ``--pairs``
one-swap neighbours drawn from up to ``--distinct`` elements each way (64: about as random as a random
chunk of a neighbourhood; 16: the repeated elements of a model-ordered chunk), and ``--masks``
random ``k``-selections for the row-sum kernel.

    python benchmarks/bench_channel_order.py --scenes paper,l11-5v,c5-2v --threads 1

The last output line is one JSON record.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as C  # noqa: E402


def _best_ms(call, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        call()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def _scene_inputs(name: str, pairs: int, distinct: int, masks: int):
    import numpy as np

    from arraysel.objective.psf_objective import build_objective
    from arraysel.physics import peakkernels as pk

    obj = build_objective(name)
    basis = getattr(getattr(obj, "psf", None), "basis", None)
    if basis is None:
        raise SystemExit(f"scene {name!r} has no fast-path basis: nothing to measure")
    cert = basis.certificates
    ne = int(cert.model.n_elements)
    k = int(obj.k)
    rng = np.random.default_rng(0)
    on = np.zeros(ne, dtype=bool)
    on[rng.choice(ne, k, replace=False)] = True
    A = cert.pair_channels.numpy()
    Y = pk.row_sums(A, np.flatnonzero(on)).reshape(ne, -1)
    outs = rng.choice(np.flatnonzero(on), min(distinct, k), replace=False)
    ins = rng.choice(np.flatnonzero(~on), min(distinct, ne - k), replace=False)
    a = rng.choice(outs, pairs).reshape(-1, 1).astype(np.int64)
    b = rng.choice(ins, pairs).reshape(-1, 1).astype(np.int64)
    used = np.repeat(on[None], pairs, axis=0)
    used[np.arange(pairs), a[:, 0]] = False
    used[np.arange(pairs), b[:, 0]] = True
    w = np.zeros((masks, ne), dtype=A.dtype)
    for i in range(masks):
        w[i, rng.choice(ne, k, replace=False)] = 1
    ntx = len(cert.model.transmits)
    ns = cert.window_samples // cert.segment
    return dict(ne=ne, k=k, A=A, Y=Y, a=a, b=b, used=used, w=w, ntx=ntx, ns=ns, runs=cert.max_run)


def _orders(used):
    import numpy as np

    from arraysel.physics import peakkernels as pk

    sel_b, sel_e = np.nonzero(used)
    return {"receive-major": pk.receive_major(used),
            "selection-major": (sel_b.astype(np.int64), sel_e.astype(np.int64))}


def _measure(s, rounds: int, repeat: int) -> dict:
    import numpy as np

    from arraysel.physics import peakkernels as pk

    A, Y, a, b, ntx = s["A"], s["Y"], s["a"], s["b"], s["ntx"]
    kernels = {
        "swap peaks": (s["used"], lambda sb, se, out: pk._swap_peaks_kernel(A, Y, a, b, sb, se, ntx, out),
                       (ntx * s["ne"], s["runs"], s["ns"], a.shape[0])),
        "swap channels": (s["used"], lambda sb, se, out: pk._swap_channels_kernel(A, Y, a, b, sb, se, out),
                          (a.shape[0],) + Y.shape),
        "channel peaks": (s["w"] != 0, lambda sb, se, out: pk._channel_peaks_kernel(A, s["w"], sb, se, ntx, out),
                          (ntx * s["ne"], s["runs"], s["ns"], s["w"].shape[0])),
    }
    res = {}
    for name, (used, call, shape) in kernels.items():
        orders = _orders(used)
        outs = {o: np.zeros(shape, dtype=A.dtype) for o in orders}
        times = {o: float("inf") for o in orders}
        for o, (sb, se) in orders.items():  # compile and warm
            call(sb, se, outs[o])
        for _ in range(rounds):
            for o, (sb, se) in orders.items():
                times[o] = min(times[o], _best_ms(lambda: call(sb, se, outs[o]), repeat))
        same = bool(np.array_equal(outs["receive-major"], outs["selection-major"]))
        if not same:
            raise SystemExit(f"{name}: the two orders gave different values")
        res[name] = {"receive_major_ms": times["receive-major"], "selection_major_ms": times["selection-major"],
                     "ratio": times["selection-major"] / times["receive-major"], "same_values": same}
    return res


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default="paper,l11-5v,c5-2v", help="comma-separated built-in scenes")
    p.add_argument("--pairs", type=int, default=64, help="one-swap neighbours a call (default 64, a descent's chunk)")
    p.add_argument("--distinct", type=int, default=64, help="distinct elements switched each way (default 64)")
    p.add_argument("--masks", type=int, default=7, help="selections for the row-sum kernel (default 7: the "
                   "largest batch that takes it)")
    p.add_argument("--rounds", type=int, default=3, help="alternations of the two orders (default 3)")
    p.add_argument("--repeat", type=int, default=5, help="calls per timing, best taken (default 5)")
    p.add_argument("--threads", type=int, default=1, help="threads (default 1)")
    a = p.parse_args(argv)
    C.set_threads(a.threads)
    import numba

    numba.set_num_threads(min(a.threads, int(numba.config.NUMBA_NUM_THREADS)))
    record = {"pairs": a.pairs, "distinct": a.distinct, "masks": a.masks, "threads": a.threads,
              "machine": C.machine(), "scenes": {}}
    rows = []
    for name in [x for x in a.scenes.split(",") if x]:
        s = _scene_inputs(name, a.pairs, a.distinct, a.masks)
        res = _measure(s, a.rounds, a.repeat)
        record["scenes"][name] = {"n_elements": s["ne"], "k": s["k"], "kernels": res}
        for kern, r in res.items():
            rows.append([name, s["ne"], s["k"], kern, f"{r['receive_major_ms']:.2f}", f"{r['selection_major_ms']:.2f}",
                         f"{r['ratio']:.2f}"])
    print(C.table(rows, ["scene", "Ne", "k", "kernel", "receive-major ms", "selection-major ms", "ratio"]))
    C.emit_json(record)


if __name__ == "__main__":
    main()
