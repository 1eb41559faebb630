"""The ``spiral`` baseline: a density-tapered Fermat spiral snapped to the array's elements.

On a matrix array (``objective.element_grid`` set, or element centres spanning x and y: a grid
with blank rows, an imported layout) the ``k`` points of a sunflower spiral (golden
angle 137.508 degrees) whose density follows a radial taper are scaled to the aperture and each
takes the nearest free element (:func:`arraysel.selectors.layouts.fermat_spiral_layout`, on the
element centres when the objective gives them). On a 1-D array it takes the 1-D analogue, ``k``
points following the same taper along the line
(:func:`arraysel.selectors.layouts.tapered_line_layout`). Deterministic; one evaluation.
"""
from __future__ import annotations

import numpy as np

from arraysel.objective.contract import element_layout
from arraysel.selectors.contract import Option, Selector
from arraysel.selectors.hookspecs import hookimpl
from arraysel.selectors.starts import layout_projection
from arraysel.selectors.layouts import TAPERS, TUKEY_ALPHA, fermat_spiral_layout, is_planar, tapered_line_layout


class SpiralSelector(Selector):
    """k elements along a density-tapered Fermat spiral (matrix arrays) or a tapered line (1-D)."""

    name = "spiral"
    description = "density-tapered Fermat spiral snapped to the grid (a tapered line on a 1-D array)"
    options = {
        "taper": Option(str, "none", "radial density taper: none (plain sunflower, the default: on a "
                        "grid of a few hundred elements a taper widens the main lobe), cosine (cos(pi rho / 2)), "
                        "blackman or tukey (flat, then a cosine fall over the outer tukey_alpha of the radius)",
                        choices=TAPERS),
        "tukey_alpha": Option(float, TUKEY_ALPHA, "the share of the radius over which the tukey taper falls "
                              "to zero (1: Hann; the published 50 % Tukey spiral: 0.5); other tapers ignore it",
                              lo=0.01, hi=1.0),
        "rotation_deg": Option(float, 0.0, "angle of the spiral's first point (degrees; matrix arrays)",
                               lo=-360.0, hi=360.0),
    }
    deterministic = True
    baseline = True

    def select(self, objective, k, seed):
        n = int(objective.n_elements)
        grid, positions = element_layout(objective)
        taper, alpha = self.options["taper"], self.options["tukey_alpha"]
        if grid is None and not is_planar(positions):
            chosen = tapered_line_layout(n, k, taper, alpha)
        else:
            layout = positions if positions is not None else grid
            chosen = fermat_spiral_layout(layout, k, taper, self.options["rotation_deg"], alpha)
        mask = layout_projection(objective, chosen)  # channel groups: the documented projection
        objective.evaluate(mask[None])
        return [int(i) for i in np.flatnonzero(mask)]


@hookimpl
def arraysel_register_selectors(register):
    register(SpiralSelector)
