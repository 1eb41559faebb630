"""The scene key table: every key of every section, its kind, range, default and meaning.

:data:`SCHEMA` is the one statement of what a scene file may set (``arraysel scenes NAME --show``
lists it; ``docs/scenes.md`` describes the keys). A new scene section is a new entry here; the
values are checked by :mod:`arraysel.scenes.values`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

_INF = math.inf


@dataclass(frozen=True)
class Key:
    """One scene key: its kind, constraints, default and meaning.

    kind: ``float``, ``int``, ``bool``, ``str``, ``length`` (a number in
    ``unit`` or a string with one of ``units``), ``points`` (a list of
    ``[x, z]`` lengths), ``beams`` (a list of ``[theta_x_deg, theta_y_deg, range]``, the range a
    length) or ``ints`` (a list of integers). cons: for numbers
    ``(lo, hi, lo_open)`` (ints and lists of ints: ``(lo, hi)``), in ``unit`` for lengths; for strings the allowed choices
    (None: any). default: the value used when no scene sets the key (None:
    none, or derived as ``help`` says).
    """

    kind: str
    cons: Any = None
    default: Any = None
    help: str = ""
    unit: str | None = None
    units: tuple = ()
    integer: bool = False


_GRID_UNITS = ("px", "m", "mm", "um", "wl")
_POS_UNITS = ("m", "mm", "um", "wl")
_W = (0, 1e9, False)

# section -> key -> Key
SCHEMA: dict[str, dict[str, Key]] = {
    "probe": {
        "name": Key("str", None, "P4-2v", "catalogue probe (arraysel.physics.probes.list_probes())"),
        "n_elements": Key("int", (1, 4096), None, "number of elements (default: the probe's; 1-D probes)"),
        "pitch": Key("float", (0, 1, True), None, "element pitch, m (default: the probe's; 1-D probes)"),
        "nx": Key("int", (1, 4096), None, "elements along x (default: the probe's; matrix probes)"),
        "ny": Key("int", (1, 4096), None, "elements along y (default: the probe's; matrix probes)"),
        "pitch_x": Key("float", (0, 1, True), None, "pitch along x, m (default: the probe's; matrix probes)"),
        "pitch_y": Key("float", (0, 1, True), None, "pitch along y, m (default: the probe's; matrix probes)"),
        "width": Key("float", (0, 1, True), None, "element width (along x), m (default: the probe's)"),
        "height": Key("float", (0, _INF, True), None, "element height (along y), m (default: the probe's)"),
        "elevation_focus": Key("float", (0, _INF, True), None, "elevation focus, m (default: the probe's)"),
        "radius": Key("float", (0, _INF, True), None, "radius of curvature, m; inf = linear (default: the probe's)"),
        "fc": Key("float", (1e3, 1e9, False), None, "centre frequency, Hz (default: the probe's)"),
        "bandwidth": Key("float", (0, 200, True), None, "pulse-echo bandwidth, % (default: the probe's)"),
        "baffle": Key("str", ("soft", "rigid"), None, "baffle (default: the probe's)"),
        "blank_rows": Key("ints", (0, 4095), None, "grid rows without elements, e.g. [8, 17, 26] (matrix "
                          "probes; default: the probe's)"),
        "blank_columns": Key("ints", (0, 4095), None, "grid columns without elements (matrix probes; default: "
                             "the probe's)"),
        "file": Key("str", None, None, "a probe file instead of a catalogue probe: element positions (.csv, "
                    ".npy, .npz) or a MUST parameter set (.mat, .npz), relative to the scene file; the other "
                    "[probe] keys fill in or replace its fields (docs/matrix.md)"),
    },
    "acquisition": {
        "fs": Key("float", (1e3, 1e10, False), None, "sampling frequency, Hz (default: fs_over_fc * fc)"),
        "fs_over_fc": Key("float", (1, 1000, False), 4.0, "fs / fc when fs is not given"),
        "c": Key("float", (300, 10000, False), 1540.0, "speed of sound, m/s"),
        "attenuation": Key("float", (0, 100, False), 0.0, "attenuation, dB/cm/MHz"),
        "tx_cycles": Key("float", (0, 100, True), 1.0, "transmit pulse length, cycles"),
    },
    "transmit": {
        "n_tx": Key("int", (1, 512), 7, "number of plane waves (1-D probes)"),
        "max_tilt_deg": Key("float", (0, 89.9, False), 10.0, "tilts are linspace(-max, +max, n_tx), degrees "
                            "(3-D scenes: the largest tilt in x)"),
        "n_tx_x": Key("int", (1, 64), 3, "tilts in x (3-D scenes; the transmits are n_tx_x * n_tx_y)"),
        "n_tx_y": Key("int", (1, 64), 3, "tilts in y (3-D scenes)"),
        "max_tilt_deg_y": Key("float", (0, 89.9, False), None, "the largest tilt in y, degrees (3-D scenes; "
                              "default: max_tilt_deg)"),
        "source_distance": Key("length", (0, 1, False), 0.0, "3-D scenes: diverging waves from a virtual source "
                               "this far behind the array, m (0: plane waves)", "m", _POS_UNITS),
    },
    "grid": {
        "n_x": Key("length", (8, 8192, False), 400, "grid columns (lateral size)", "px", _GRID_UNITS, True),
        "n_z": Key("length", (8, 8192, False), 400, "grid rows (axial size)", "px", _GRID_UNITS, True),
        "pixel": Key("length", (0, 1, True), None, "grid pitch, both axes (default: (c / fs) / "
                     "pixel_per_wavelength_fs)", "m", _POS_UNITS),
        "pixel_per_wavelength_fs": Key("float", (0, 1000, True), 4.0, "pixels per c / fs when pixel is not given"),
        "z_offset": Key("int", (0, 10 ** 6), 0, "rows above the grid, px: z_i = (i + z_offset) pixel "
                        "(single-scatterer scenes; medium.points places each grid itself)"),
        "window": Key("length", (4, 8192, False), 128, "PSF window side (kernel size)", "px", _GRID_UNITS, True),
    },
    "medium": {
        "scatterer_x": Key("length", (-1, 1, False), None, "lateral position of the one scatterer, m "
                           "(default: 0)", "m", _POS_UNITS),
        "scatterer_z": Key("length", (0, 2, True), None, "depth of the one scatterer, m (default: the grid "
                           "row n_z // 2)", "m", _POS_UNITS),
        "points": Key("points", (1, 64), None, "field points [[x, z], ...] (lengths, m by default), each "
                      "simulated on its own grid centred on it; exclusive with scatterer_x/z and "
                      "grid.z_offset", "m", _POS_UNITS),
        "scatterer_y": Key("length", (-1, 1, False), None, "y of the one scatterer, m (3-D scenes; default: 0)",
                           "m", _POS_UNITS),
        "reflectivity": Key("float", (0, 1e6, True), 1.0, "reflection coefficient"),
    },
    "volume": {  # its presence makes a scene 3-D (a matrix probe, planes through the scatterer)
        "planes": Key("str", None, "xy,xz,yz", "the planes imaged, comma-separated: xy (the C-plane at the "
                      "scatterer's depth), xz, yz"),
        "half_x": Key("length", (0, 1000, True), 8.0, "half-size of the planes along x", "wl", _POS_UNITS),
        "half_y": Key("length", (0, 1000, True), 8.0, "half-size of the planes along y", "wl", _POS_UNITS),
        "half_z": Key("length", (0, 1000, True), 4.0, "half-size of the planes along z", "wl", _POS_UNITS),
        "pixels_per_wavelength": Key("float", (0.1, 100, False), 3.0, "pixel = lambda0 / this, every plane"),
        "fast": Key("bool", None, True, "use the fast 3-D path when its check passes (else the exact path)"),
    },
    "sector": {  # its presence makes a scene a sector scene (a matrix probe, points over a steered sector)
        "points": Key("beams", (1, 32), None, "point targets [[theta_x, theta_y, range], ...]: angles in "
                      "degrees (u = sin theta_x, v = sin theta_y), range a length from the array centre "
                      "(m by default); each imaged on its own surface over the sector (required)", "m",
                      _POS_UNITS),
        "half_angle_deg": Key("float", (0, 80, True), None, "half-angle of the sector in x and y, degrees "
                              "(default: the transmits' largest tilts, transmit.max_tilt_deg and "
                              "max_tilt_deg_y)"),
        "margin": Key("float", (0, 10, False), 1.0, "how far the surfaces reach past the sector's edge, in "
                      "main lobes lambda0 / D (D the aperture along each axis)"),
        "samples_per_lobe": Key("float", (0, 64, True), 3.0, "samples of the surfaces per lambda0 / D in u "
                                "and v (at least 2 to resolve a side lobe)"),
        "n_freq": Key("int", (1, 64), 8, "frequencies of the search's broadband beam pattern"),
        "fresh_random": Key("int", (0, 10000), 16, "fresh random selections scored on the points for the "
                            "random baseline's median (0: none)"),
        "polish": Key("float", (0, 0.9, False), 0.0, "share of the budget of every searching selector's run "
                      "(not the baselines) spent polishing its selection on the per-beam loss (a run's own "
                      "polish option overrides it; 0: none)"),
        "polish_width_ratio": Key("float", (1, 2, False), 1.048, "the polish's cap on the mean -6 dB width, "
                                  "over the fresh random selections' median"),
    },
    "compare": {  # the defaults of `arraysel compare` on this scene (its command-line options override them)
        "budget_s": Key("float", (0, 86400, True), None, "seconds of each selector run when --budget-s is not "
                        "given (default: the runs share 7 minutes, 10 to 120 s each)"),
        "seeds": Key("ints", (0, 2 ** 31 - 1), None, "seeds of the stochastic selectors when --seeds is not "
                     "given (default: 0, 1, 2, 3, 4)"),
    },
    "cysts": {  # optional in a sector scene: anechoic cysts in speckle, compare's cysts.csv (docs/sector.md)
        "points": Key("ints", (0, 31), None, "the sector.points (indices) whose PSF images a cyst centred on the "
                      "point (default: every point)"),
        "radius": Key("length", (0, 0.05, True), 0.004, "cyst radius, m", "m", _POS_UNITS),
        "density": Key("float", (0, 1000, True), 10.0, "scatterers per resolution cell (the full aperture's "
                       "main lobe, (lambda0 R / D)^2 at the cyst's range R)"),
        "inside": Key("float", (0, 1, True), 0.8, "the region read inside a cyst: the disc of this fraction of "
                      "its radius (clear of its blurred edge)"),
        "ring_inner": Key("float", (1, 10, False), 1.2, "the background ring read around a cyst starts at this "
                          "multiple of its radius"),
        "ring_outer": Key("float", (1, 10, True), 2.0, "... and ends at this multiple (> ring_inner)"),
        "realisations": Key("int", (1, 1000), 8, "seeded speckle realisations pooled per cyst"),
        "seed": Key("int", (0, 2 ** 31 - 1), 0, "seed of the scatterers (the same for every selection)"),
    },
    "receive": {
        "fnumber": Key("float", (0, 100, False), 0.0, "receive f-number (0 = full aperture)"),
        "iq_bandwidth": Key("float", (0, 200, True), None, "I/Q low-pass bandwidth, % (default: the probe's)"),
    },
    "selection": {
        "k": Key("int", (1, 4096), None, "number of active elements (required)"),
    },
    "constraints": {  # docs/constraints.md; arraysel.constraints checks them against the probe
        "groups": Key("str", None, None, "channel groups: a rule 'mux-N-B' (e.g. 'mux-1024-4': 4 banks, channel "
                      "c reaches element c of each) or a CSV file element,group"),
        "mode": Key("str", ("exactly-one", "at-most-one"), "exactly-one", "elements a selection holds in "
                    "each channel group"),
        "forced_on": Key("ints", (0, 4095), None, "elements always selected"),
        "forced_off": Key("ints", (0, 4095), None, "elements never selected (dead elements, unconnected rows)"),
        "forced_off_rows": Key("ints", (0, 4095), None, "grid rows iy whose elements are never selected "
                               "(matrix probes)"),
        "symmetry": Key("str", ("none", "x", "y", "xy"), "none", "mirror symmetry of the selection: in x, in "
                        "y or both (four-fold)"),
    },
    "aperture": {  # docs/apertures.md; arraysel.objective.aperture
        "mode": Key("str", ("shared", "full-tx", "separate", "per-transmit"), "shared",
                    "what a selection is: one mask that transmits and receives (shared), every element "
                    "transmitting and the selection receiving (full-tx), two selections, k_tx transmit and k_rx receive elements (separate), or a transmit "
                    "aperture of k_tx elements for every transmit event and a receive aperture of k_rx (per-transmit, "
                    "matrix-probe scenes)"),
        "k_tx": Key("int", (1, 4096), None, "transmit elements of a separate selection, of each event's "
                    "aperture under per-transmit (default: selection.k)"),
        "k_rx": Key("int", (1, 4096), None, "receive elements of a separate or per-transmit selection "
                    "(default: selection.k)"),
    },
    "metrics": {
        "r_main": Key("length", (0, 1000, True), 1.5, "main-lobe radius", "wl", _GRID_UNITS),
        "r_guard": Key("length", (0, 1000, True), 2.5, "side-lobe region starts at this radius", "wl",
                       _GRID_UNITS),
        "quantile": Key("float", (0, 1, False), 0.99, "q of L_SLR_q"),
        "aggregate": Key("str", ("mean", "worst"), "mean", "headline metrics of a several-point scene: "
                         "the mean over points or the worst point"),
        "per_beam": Key("bool", None, False, "1-D scenes: compare also scores every selection on each point's "
                        "own main lobe (beams.csv, pareto.csv, pareto.png)"),
        "fresh_random": Key("int", (0, 10000), 16, "with per_beam: fresh random selections scored on the points "
                            "for the random (fresh median) rows"),
    },
    "weights": {name: Key("float", _W, 0.0, f"weight of {name} in the training loss")
                for name in ("L_PSF", "L_conv", "L_rec", "L_contrast", "L_SLR", "L_ent", "L_row")},
    "simulator": {
        "db_thresh": Key("float", (-400, 0, True), -100.0, "frequency components below this level are "
                         "dropped, dB"),
        "element_splitting": Key("int", (0, 1000), 0, "sub-elements per element (0 = ceil(width / lambda_min))"),
        "full_frequency_directivity": Key("bool", None, False, "directivity at every frequency"),
        "frequency_step": Key("float", (0, 10, True), 1.0, "frequency step, relative to MUST's"),
        "fast_margin": Key("int", (0, 4096), 8, "fast path: pixels around the window computed exactly"),
        "fast_block": Key("int", (1, 4096), 8, "fast path: side of the bound blocks, px"),
    },
    "data": {
        "dataset": Key("str", ("mnist", "fashion"), None, "image data set (end-to-end scenes)"),
        "source": Key("str", ("auto", "sample", "idx"), None, "where the images come from"),
        "image_size": Key("int", (8, 1024), None, "image side, px"),
        "depth_min": Key("float", (0, 2, False), None, "shallowest scatterer depth, m"),
        "depth_max": Key("float", (0, 2, True), None, "deepest scatterer depth, m"),
    },
    "training": {  # the one home of the training defaults (TrainConfig, E2ESettings read them)
        "epochs": Key("int", (0, 100000), 100, "training epochs (steps, when set, take precedence)"),
        "steps": Key("int", (0, 10 ** 8), None, "training steps (none: from epochs)"),
        "batch_size": Key("int", (1, 100000), 64, "scenes per batch"),
        "lr_mask": Key("float", (0, 10, True), 1e-4, "learning rate of the selection logits"),
        "lr_ista": Key("float", (0, 10, True), 5e-4, "learning rate of the ISTA parameters"),
        "lr_head": Key("float", (0, 10, True), 1e-4, "learning rate of the CNN head"),
        "tau_start": Key("float", (1e-6, 1e6, False), 6.0, "softmax temperature at step 0"),
        "tau_end": Key("float", (1e-6, 1e6, False), 1.2, "softmax temperature after the decay"),
        "tau_steps": Key("int", (0, 10 ** 8), 1500, "length of the cosine temperature decay, steps"),
        "ista_layers": Key("int", (1, 1000), 8, "unrolled ISTA layers"),
        "finetune_epochs": Key("int", (0, 100000), 0, "head fine-tuning epochs on the fixed selection"),
    },
}


def training_default(key: str):
    """The default of the scene key ``training.<key>`` (the one home of the training defaults)."""
    return SCHEMA["training"][key].default


#: the keys a scene file may set outside its sections
TOP_LEVEL = ("name", "description", "base")
