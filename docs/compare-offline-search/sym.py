"""Offline search for the 95% target: symmetric ILS, then full swap ILS from the best.

Usage: OMP_NUM_THREADS=1 python sym.py SEED SECONDS TAG  (log: TAG.log in $SEARCH_LOG_DIR, default
the current folder)
"""
import os, sys, time, math, json, numpy as np, arraysel
obj = arraysel.build_objective(arraysel.load_scene("paper"))
N, K = 64, 32
seed = int(sys.argv[1]); budget_s = float(sys.argv[2]); tag = sys.argv[3]
rng = np.random.default_rng(seed)
cache = {}
n_eval = 0
best = [math.inf, None]
t0 = time.time()
log = open(os.path.join(os.environ.get("SEARCH_LOG_DIR", "."), f"{tag}.log"), "a")
def score(masks):
    global n_eval
    masks = np.asarray(masks, bool)
    keys = [np.packbits(m).tobytes() for m in masks]
    todo = [i for i, k in enumerate(keys) if k not in cache]
    if todo:
        v = obj.evaluate(masks[todo].astype(np.float32))["Mean"]
        n_eval += len(todo)
        for i, x in zip(todo, v):
            x = float(x) if np.isfinite(x) else math.inf
            cache[keys[i]] = x
            if x < best[0]:
                best[0], best[1] = x, masks[i].copy()
                print(f"{time.time()-t0:8.1f}s evals {n_eval} best {x:.6f} {' '.join(map(str, np.flatnonzero(masks[i])))}", file=log, flush=True)
    return np.array([cache[k] for k in keys])

def mirror(m): return m[::-1]
m = np.zeros(N, bool); m[[0,3,4,7,8,12,13,16,17,20,21,23,25,27,29,31,32,34,36,38,40,41,44,45,48,49,52,53,54,59,60,61]] = True
print("best, mirrored:", score([m, mirror(m)]), file=log, flush=True)

# symmetric space: pairs p=0..31 -> elements p and 63-p; choose 16 pairs
def sym_mask(pairs):
    m = np.zeros(N, bool); m[pairs] = True; m[N - 1 - np.asarray(pairs)] = True; return m
def sym_descend(sel):
    sel = np.array(sorted(sel)); v = score([sym_mask(sel)])[0]
    while True:
        off = np.setdiff1d(np.arange(32), sel)
        cands = []
        for a in range(16):
            for b in off:
                s = sel.copy(); s[a] = b; cands.append(np.sort(s))
        vals = score([sym_mask(s) for s in cands])
        i = int(np.argmin(vals))
        if vals[i] < v: sel, v = cands[i], vals[i]
        else: return sel, v
sbest, svbest = None, math.inf
base, bv = None, math.inf
stale = 0
while time.time() - t0 < budget_s * 0.5:
    if base is None or stale >= 8:
        start = np.sort(rng.choice(32, 16, replace=False)); stale = 0; base = None
    else:
        start = base.copy()
        for _ in range(rng.integers(2, 4)):
            off = np.setdiff1d(np.arange(32), start); start[rng.integers(16)] = rng.choice(off)
        start = np.sort(start)
    s, v = sym_descend(start)
    if base is None or v <= bv: base, bv = s, v
    if v < svbest: svbest, sbest = v, s; stale = 0
    else: stale += 1
    print(f"sym LO {v:.6f} (best sym {svbest:.6f}) t={time.time()-t0:.0f} evals={n_eval}", file=log, flush=True)
print("SYM BEST", svbest, list(np.flatnonzero(sym_mask(sbest))), file=log, flush=True)
# full swap ILS (best improvement) from the best symmetric and best overall
def descend(m, v):
    while True:
        on, off = np.flatnonzero(m), np.flatnonzero(~m)
        c = np.repeat(m[None], on.size * off.size, 0)
        r = np.arange(c.shape[0]); c[r, np.repeat(on, off.size)] = False; c[r, np.tile(off, on.size)] = True
        vals = score(c); i = int(np.argmin(vals))
        if vals[i] < v: m, v = c[i], vals[i]
        else: return m, v
cur = best[1].copy(); cv = best[0]
cur, cv = descend(cur, cv)
while time.time() - t0 < budget_s:
    s = cur.copy(); on, off = np.flatnonzero(s), np.flatnonzero(~s)
    p = rng.integers(2, 5)
    s[rng.choice(on, p, replace=False)] = False; s[rng.choice(off, p, replace=False)] = True
    m2, v2 = descend(s, score([s])[0])
    if v2 <= cv: cur, cv = m2, v2
    print(f"full LO {v2:.6f} (cur {cv:.6f}) t={time.time()-t0:.0f} evals={n_eval}", file=log, flush=True)
print("DONE best", best[0], list(np.flatnonzero(best[1])), "evals", n_eval, file=log, flush=True)
