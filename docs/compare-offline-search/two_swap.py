"""Exhaustive 1-swap and 2-swap neighbourhood of a mask on the paper scene (offline evidence for the 95 % target).

Usage: OMP_NUM_THREADS=1 python two_swap.py "2 3 4 ..." OUT.log
Scores every mask reachable by exchanging one or two active elements for inactive ones
(k (Ne-k) + C(k,2) C(Ne-k,2) masks) with the real objective and logs the best.
"""
import itertools, sys, time
import numpy as np
import torch
torch.set_num_threads(1)
from arraysel import build_objective, load_scene

start = [int(v) for v in sys.argv[1].split()]
log = open(sys.argv[2], "w", buffering=1)
obj = build_objective(load_scene("paper"))
ne = obj.n_elements
on = sorted(start)
off = [i for i in range(ne) if i not in on]
base = np.zeros(ne, np.float32); base[on] = 1
m0 = float(obj.evaluate(base[None])["Mean"][0])
log.write(f"start Mean {m0:.7f}\n")
def moves():
    for a in on:
        for b in off:
            yield (a,), (b,)
    for A in itertools.combinations(on, 2):
        for Bm in itertools.combinations(off, 2):
            yield A, Bm
best, best_mv, n, t0 = m0, None, 0, time.time()
batch, mvs = [], []
def flush():
    global best, best_mv, n
    W = np.stack(batch)
    r = obj.evaluate(W)["Mean"]
    n += len(batch)
    i = int(np.argmin(r))
    if r[i] < best:
        best, best_mv = float(r[i]), mvs[i]
        log.write(f"improved {best:.7f} by {best_mv} after {n}\n")
    batch.clear(); mvs.clear()
for A, Bm in moves():
    m = base.copy(); m[list(A)] = 0; m[list(Bm)] = 1
    batch.append(m); mvs.append((A, Bm))
    if len(batch) == 512:
        flush()
        if n % (512 * 40) == 0:
            log.write(f"{n} masks, {time.time()-t0:.0f} s, best {best:.7f}\n")
if batch: flush()
log.write(f"done: {n} masks in {time.time()-t0:.0f} s; best {best:.7f} move {best_mv}\n")
