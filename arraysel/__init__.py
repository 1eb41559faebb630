"""arraysel: sparse ultrasound array design on a differentiable SIMUS objective."""

__version__ = "0.1.0"
