"""Shared scorer of the offline searches: every mask scored once by the paper scene's objective.

Logs go to ``LOG_DIR/<tag>.log``; LOG_DIR is the environment variable ``SEARCH_LOG_DIR``,
by default the current folder.
"""
import os, sys, time, math, numpy as np, arraysel
LOG_DIR = os.environ.get("SEARCH_LOG_DIR", ".")
obj = arraysel.build_objective(arraysel.load_scene("paper"))
N, K = 64, 32
class S:
    def __init__(self, tag):
        self.cache = {}; self.n = 0; self.best = math.inf; self.bm = None; self.t0 = time.time()
        self.log = open(os.path.join(LOG_DIR, f"{tag}.log"), "a")
    def p(self, *a): print(f"{time.time()-self.t0:8.1f}s evals {self.n}", *a, file=self.log, flush=True)
    def __call__(self, masks):
        masks = np.asarray(masks, bool)
        keys = [np.packbits(m).tobytes() for m in masks]
        todo = [i for i, k in enumerate(keys) if k not in self.cache]
        if todo:
            v = obj.evaluate(masks[todo].astype(np.float32))["Mean"]
            self.n += len(todo)
            for i, x in zip(todo, v):
                x = float(x) if np.isfinite(x) else math.inf
                self.cache[keys[i]] = x
                if x < self.best:
                    self.best, self.bm = x, masks[i].copy()
                    self.p(f"best {x:.6f}", " ".join(map(str, np.flatnonzero(masks[i]))))
        return np.array([self.cache[k] for k in keys])
def mask(idx):
    m = np.zeros(N, bool); m[list(idx)] = True; return m
BEST = mask([2,3,4,9,10,11,14,15,18,19,22,23,25,27,29,31,32,34,36,38,40,42,43,46,47,50,51,55,56,59,60,63])
