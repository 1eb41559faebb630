"""3-D acoustics for matrix (2-D) probes: transmit delays, SIMUS3/PFIELD3 echoes, delay-and-sum
onto 3-D points, the exact point-spread function on three planes through a scatterer and its fast
path (:mod:`~arraysel.physics.volume.fast`).

Conventions: :mod:`arraysel.physics.probes` (element ``iy * nx + ix``, x along the rows, y along
the columns, z depth, right-handed; SI units; the earliest element fires at 0). ``docs/matrix.md``
states the planes' convention.
"""
from arraysel.physics.volume.beamform import das_plan3, receive_distance3, transmit_distance3
from arraysel.physics.volume.delays import (diverging_delays3, focused_delays3, plane_wave_delays3, tilt_grid,
                                            virtual_sources3)
from arraysel.physics.volume.fast import (FastPathUnavailable, FastSettings, MatrixFastPSF, fast_relative_error,
                                          interpolation_harmonics)
from arraysel.physics.volume.psf import PLANES, MatrixPSF, MatrixPSFSetup, peak_normalise, plane_axes
from arraysel.physics.volume.simus import element_responses3, grid_for_points3, simulate_rf3

__all__ = ["plane_wave_delays3", "focused_delays3", "diverging_delays3", "virtual_sources3",
           "element_responses3", "grid_for_points3", "simulate_rf3", "transmit_distance3",
           "receive_distance3", "das_plan3", "MatrixPSF", "MatrixPSFSetup", "PLANES", "peak_normalise",
           "plane_axes", "tilt_grid", "MatrixFastPSF", "FastSettings", "FastPathUnavailable",
           "fast_relative_error", "interpolation_harmonics"]
