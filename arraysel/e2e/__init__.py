"""End-to-end training: data sets, reconstructors (unrolled ISTA, residual CNN), the trainer and its figures.

``from arraysel.e2e import run_training`` keeps working (the pipeline's entry point).
"""
from arraysel.e2e.pipeline import run_training

__all__ = ["run_training"]
