"""When the compiled passes (numba, on the CPU) serve a batch instead of torch's operations.

Several steps of scoring a batch without gradient have a compiled twin that reads the data once
instead of in torch's half-dozen passes: the certificates' block bounds and peak search and the
window cut (:mod:`arraysel.physics.pairkernels`), and the Table-1 metrics
(:mod:`arraysel.objective.metric_kernels`). Loading a compiled function in a fresh process
(numba's cached machine code and its threads) costs about 0.3 s, more than torch spends on a
few kernels, so a batch smaller than :data:`MIN_BATCH` keeps torch's operations: a cold
single-mask run loads no compiled code (its first kernel 0.02 s instead of 0.7 s). A loop of
small batches (gradient steps) switches to the compiled block bounds and envelopes after a few
of them (``Certificates.compiled_bound_warm``). This module imports nothing, so that asking
costs nothing either.
"""
from __future__ import annotations

#: fewest items (selections, images, kernels) of a batch that the compiled passes serve
MIN_BATCH = 8
