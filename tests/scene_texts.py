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
