"""The ultrasound physics: probes, transmit delays, SIMUS/PFIELD synthesis, beamforming and the PSF operator.

Nothing here imports from the layers above (scenes, objective, selectors, run, report, cli).
"""
