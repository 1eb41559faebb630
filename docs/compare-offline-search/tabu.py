"""Tabu search from the best known mask.

Usage: OMP_NUM_THREADS=1 python tabu.py SEED SECONDS TAG SAMPLE TENURE  (log: TAG.log, see common.py)
"""
import os, sys; sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import *
seed, budget, tag = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
sample, tenure = int(sys.argv[4]), int(sys.argv[5])
rng = np.random.default_rng(seed); sc = S(tag)
cur = BEST.copy(); cv = sc([cur])[0]
tabu = np.zeros(N, int); step = 0
while time.time() - sc.t0 < budget:
    step += 1
    on, off = np.flatnonzero(cur), np.flatnonzero(~cur)
    a = np.repeat(on, off.size); b = np.tile(off, on.size)
    ok = (tabu[a] <= step) & (tabu[b] <= step)
    idx = np.flatnonzero(ok)
    idx = rng.choice(idx, min(sample, idx.size), replace=False)
    c = np.repeat(cur[None], idx.size, 0); r = np.arange(idx.size)
    c[r, a[idx]] = False; c[r, b[idx]] = True
    v = sc(c); i = int(np.argmin(v))
    cur, cv = c[i], v[i]
    tabu[a[idx[i]]] = step + tenure + rng.integers(0, 3); tabu[b[idx[i]]] = step + tenure + rng.integers(0, 3)
    if step % 10 == 0: sc.p(f"step {step} cur {cv:.6f} best {sc.best:.6f}")
sc.p("DONE", sc.best, " ".join(map(str, np.flatnonzero(sc.bm))))
