"""Scene files the tests write: one home for each text (imported by tests in tests/ and
tests/hostile/, which pytest runs with tests/ on the path through its conftest)."""

#: an 8-element paper scene on a 32 x 32 grid: a basis builds in about a second
TINY_SCENE = """
name = "tiny"
base = "paper"
[probe]
n_elements = 8
[transmit]
n_tx = 1
[grid]
n_x = 32
n_z = 32
window = 16
[selection]
k = 4
[metrics]
r_main = 0.25
r_guard = 0.5
[simulator]
fast_margin = 2
fast_block = 4
"""

#: a 3-D scene of a 4 x 4 matrix probe (one plane wave, small planes): its fast path builds in a second
TINY_MATRIX_SCENE = """
name = "tiny3d"
base = "matrix-1024"
[probe]
nx = 4
ny = 4
[transmit]
n_tx_x = 1
n_tx_y = 1
source_distance = 0.0
[medium]
scatterer_z = "10 mm"
[volume]
half_x = 3.0
half_y = 3.0
half_z = 2.0
pixels_per_wavelength = 2.0
[selection]
k = 4
[metrics]
r_main = 1.0
r_guard = 2.0
"""
