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

#: a sector scene of an 8 x 8 matrix probe (two points at 15 mm): its fast paths build in seconds
TINY_SECTOR = {"name": "tiny-sector", "probe": {"name": "MATRIX-32x32", "nx": 8, "ny": 8},
               "acquisition": {"fs_over_fc": 4.0},
               "transmit": {"n_tx_x": 3, "n_tx_y": 3, "max_tilt_deg": 20.0, "max_tilt_deg_y": 20.0,
                            "source_distance": "5 mm"},
               "sector": {"points": [[0.0, 0.0, "15 mm"], [10.0, 0.0, "15 mm"]], "samples_per_lobe": 3.0,
                          "margin": 1.0, "n_freq": 4, "fresh_random": 3},
               "selection": {"k": 16}, "weights": {"L_PSF": 10.0, "L_contrast": 10.0, "L_SLR": 10.0}}
