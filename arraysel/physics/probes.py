"""Probe geometry, the probe catalogue and acquisition settings.

Conventions (see ``docs/probes.md``):

* SI units everywhere: metres, seconds, hertz; angles in radians.
* x runs along the array, from the first element to the last, with x = 0 at
  the centre of the array; z is depth, positive into the medium; y (elevation)
  is not modelled except through the element ``height`` and ``elevation_focus``.
* A convex array follows the MUST convention: its elements lie on an arc of
  radius ``radius`` whose chord (through the two end elements) is the line
  z = 0, centred on x = 0; neighbouring elements are ``pitch`` apart along
  straight lines; the centre of curvature lies at (0, -h) where h is the
  apothem, so the middle of the arc bulges into the medium (z > 0).

Matrix (2-D) probes, :class:`MatrixProbe`: a planar grid of ``nx`` x ``ny``
identical rectangular elements on the plane z = 0, centred on (0, 0); x runs
along the rows (``width`` and ``pitch_x`` are along x), y along the columns
(``height`` and ``pitch_y``), z is depth, and (x, y, z) is right-handed as in
MUST's 3-D functions. **Element index = iy * nx + ix** (x fastest): element
``e`` sits at ``x = (e % nx - (nx - 1) / 2) pitch_x``,
``y = (e // nx - (ny - 1) / 2) pitch_y``. Masks, weights, figures and files of
a matrix probe use this index everywhere; ``mask.reshape(ny, nx)`` is the
probe seen from the medium with x to the right and y down the rows. A grid
with blank (unconnected) rows or columns numbers its connected cells row by
row, skipping the blank ones; :class:`PlanarProbe` holds elements at
arbitrary centres (``arraysel.physics.matrix_probes``, ``docs/matrix.md``).

The catalogue holds the probes of MUST/PyMUST's ``getparam`` (numbers are
physical facts carried over as literal data) plus a few others. Fields that
``getparam`` leaves out are filled with MUST's own defaults: width = pitch -
kerf, height = inf (no elevation directivity), elevation_focus = inf (no
elevation lens), radius = inf (linear), bandwidth = 75 %, baffle = 'soft'.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from arraysel.errors import ParameterError, check_number
from arraysel.physics.matrix_probes import MatrixProbe, PlanarProbe, probe_from_positions
from arraysel.physics.probe_fields import (C_MAX, C_MIN, Baffle, check_field_names, check_name,
                                           check_sound_speed, check_transducer, positive)

#: the planes through a scatterer a matrix probe's 3-D PSF is imaged on, in this order: the
#: C-plane ``xy`` at the scatterer's depth, then ``xz`` and ``yz`` (``docs/matrix.md``)
MATRIX_PLANES = ("xy", "xz", "yz")

__all__ = [
    "Probe",
    "MatrixProbe",
    "PlanarProbe",
    "probe_from_positions",
    "MATRIX_CATALOGUE",
    "LINEAR_ONLY_FIELDS",
    "MATRIX_ONLY_FIELDS",
    "Acquisition",
    "get_probe",
    "list_probes",
    "check_sampling",
    "min_sampling_frequency",
    "check_sound_speed",
    "C_MIN",
    "C_MAX",
    "PROBE_CATALOGUE",
]


@dataclass(frozen=True)
class Probe:
    """Geometry and pulse band of a 1-D (linear or convex) ultrasound array.

    Attributes:
        name: label of the probe.
        n_elements: number of elements Ne (integer >= 1).
        pitch: centre-to-centre distance of neighbouring elements (m, > 0);
            for a convex array it is the straight-line (chord) distance.
        width: element width along the array (m, 0 < width <= pitch).
        height: element height in elevation (m, > 0; inf = no elevation
            directivity, MUST's default).
        elevation_focus: depth of the elevation lens focus (m, > 0; inf = no lens).
        radius: radius of curvature (m, > 0; inf = linear array).
        fc: centre frequency (Hz, > 0).
        bandwidth: pulse-echo -6 dB fractional bandwidth (%, in (0, 200)).
        baffle: 'soft' (obliquity factor cos), 'rigid' (no obliquity factor)
            or a positive number, the ratio of the medium impedance to the
            baffle impedance.
    """

    name: str
    n_elements: int
    pitch: float
    width: float
    height: float
    elevation_focus: float
    radius: float
    fc: float
    bandwidth: float = 75.0
    baffle: Baffle = "soft"

    def __post_init__(self) -> None:
        set_ = lambda field, value: object.__setattr__(self, field, value)  # noqa: E731
        check_name(self.name)
        set_("n_elements", check_number("n_elements", self.n_elements, lo=1, hi=None, integer=True))
        pitch = positive("pitch", self.pitch)
        set_("pitch", pitch)
        width = positive("width", self.width)
        if width > pitch:
            raise ParameterError(
                f"width = {self.width!r} is out of range; allowed: (0, pitch] = (0, {pitch!r}] "
                "(the element cannot be wider than the pitch)")
        set_("width", width)
        set_("height", positive("height", self.height, allow_inf=True))
        set_("elevation_focus", positive("elevation_focus", self.elevation_focus, allow_inf=True))
        radius = positive("radius", self.radius, allow_inf=True)
        set_("radius", radius)
        if not math.isinf(radius):
            half_step_sine = pitch / (2.0 * radius)
            if half_step_sine > 1.0:
                raise ParameterError(
                    f"radius = {self.radius!r} is too small for pitch = {pitch!r}: a convex array "
                    f"needs pitch / (2 radius) <= 1, i.e. radius >= {pitch / 2!r}")
            total = (self.n_elements - 1) * 2.0 * math.asin(half_step_sine)
            if total >= math.pi:
                raise ParameterError(
                    f"radius = {self.radius!r} is too small for n_elements = {self.n_elements} and "
                    f"pitch = {pitch!r}: the arc would span {total!r} rad; a convex array needs "
                    f"(n_elements - 1) * 2 asin(pitch / (2 radius)) < pi")
        check_transducer(self, set_)

    # ------------------------------------------------------------------ derived
    @property
    def kerf(self) -> float:
        """Gap between neighbouring elements, pitch - width (m)."""
        return self.pitch - self.width

    @property
    def is_linear(self) -> bool:
        """True for a linear array (infinite radius), False for a convex one."""
        return math.isinf(self.radius)

    @property
    def is_matrix(self) -> bool:
        """False: a 1-D array (see :class:`MatrixProbe`)."""
        return False

    @property
    def aperture(self) -> float:
        """Distance between the centres of the first and last elements along x (m)."""
        xe = self.element_positions()[0]
        return float(xe[-1] - xe[0])

    def wavelength(self, c: float = 1540.0) -> float:
        """Wavelength c / fc at the centre frequency (m) for a speed of sound ``c`` (m/s)."""
        return check_sound_speed(c) / self.fc

    def element_positions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Return ``(xe, ze, theta, h)``: element centres and orientations.

        ``xe``, ``ze`` (m) and ``theta`` (rad) are float64 arrays of shape (Ne,).
        ``theta`` is the angle between each element's normal and the z axis
        (positive towards +x). ``h`` (m) is the apothem of a convex array, the
        distance from the centre of curvature to the chord z = 0; it is 0.0 for
        a linear array, whose elements lie on z = 0 centred on x = 0.
        """
        n = self.n_elements
        if self.is_linear:
            xe = (np.arange(n, dtype=np.float64) - (n - 1) / 2.0) * self.pitch
            zeros = np.zeros(n, dtype=np.float64)
            return xe, zeros, zeros.copy(), 0.0
        r = self.radius
        step = 2.0 * math.asin(self.pitch / (2.0 * r))   # angle between neighbouring normals
        half_span = step * (n - 1) / 2.0                 # angle of the end elements
        h = r * math.cos(half_span)                      # apothem of the chord
        theta = (np.arange(n, dtype=np.float64) - (n - 1) / 2.0) * step
        xe = r * np.sin(theta)
        ze = r * np.cos(theta) - h
        return xe, ze, theta, float(h)

    # ------------------------------------------------------------------ copies
    def replace(self, **changes: Any) -> "Probe":
        """Return a validated copy with some fields changed (e.g. ``fc=3.5e6``).

        Unknown field names raise :class:`ParameterError` naming them.
        """
        _check_field_names(changes)
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """The fields as a plain dict (same names as the dataclass)."""
        return dataclasses.asdict(self)

    def to_must_dict(self) -> dict[str, Any]:
        """The geometry under MUST's PARAM field names (Nelements, pitch, width, kerf, ...)."""
        return {
            "Nelements": self.n_elements, "pitch": self.pitch, "width": self.width,
            "kerf": self.kerf, "height": self.height, "focus": self.elevation_focus,
            "radius": self.radius, "fc": self.fc, "bandwidth": self.bandwidth,
            "baffle": self.baffle,
        }


_FIELD_NAMES = tuple(f.name for f in dataclasses.fields(Probe))
_MATRIX_FIELD_NAMES = tuple(f.name for f in dataclasses.fields(MatrixProbe))
#: fields of one kind of probe only (a scene refuses them for the other kind, naming the key)
LINEAR_ONLY_FIELDS = tuple(f for f in _FIELD_NAMES if f not in _MATRIX_FIELD_NAMES)
MATRIX_ONLY_FIELDS = tuple(f for f in _MATRIX_FIELD_NAMES if f not in _FIELD_NAMES)


def _check_field_names(changes: dict[str, Any], names: tuple = _FIELD_NAMES) -> None:
    check_field_names(changes, names)


# ---------------------------------------------------------------------- catalogue
_INF = math.inf

#: Probe data (SI units). The first ten mirror MUST/PyMUST ``getparam``; fields
#: getparam leaves out carry MUST's defaults (see the module docstring).
PROBE_CATALOGUE: dict[str, dict[str, Any]] = {
    # Verasonics/Philips linear arrays
    "L11-5v": dict(n_elements=128, pitch=0.300e-3, width=0.270e-3, height=5e-3,
                   elevation_focus=18e-3, radius=_INF, fc=7.6e6, bandwidth=77.0),
    "L12-3v": dict(n_elements=192, pitch=0.200e-3, width=0.170e-3, height=5e-3,
                   elevation_focus=20e-3, radius=_INF, fc=7.54e6, bandwidth=93.0),
    # Verasonics/Philips convex array
    "C5-2v": dict(n_elements=128, pitch=0.508e-3, width=0.460e-3, height=13.5e-3,
                  elevation_focus=60e-3, radius=49.57e-3, fc=3.57e6, bandwidth=79.0),
    # Verasonics/Philips phased array (the paper's probe)
    "P4-2v": dict(n_elements=64, pitch=0.300e-3, width=0.250e-3, height=14e-3,
                  elevation_focus=60e-3, radius=_INF, fc=2.72e6, bandwidth=74.0),
    # Vermon phased array
    "PA4-2/20": dict(n_elements=64, pitch=0.300e-3, width=0.250e-3, height=14e-3,
                     elevation_focus=_INF, radius=_INF, fc=2.5e6, bandwidth=60.0),
    # Ultrasonix / BK linear arrays
    "L9-4/38": dict(n_elements=128, pitch=0.3048e-3, width=0.2698e-3, height=6e-3,
                    elevation_focus=_INF, radius=_INF, fc=5e6, bandwidth=65.0),
    "LA530": dict(n_elements=192, pitch=0.245e-3, width=0.215e-3, height=_INF,
                  elevation_focus=_INF, radius=_INF, fc=3e6, bandwidth=75.0),
    "L14-5/38": dict(n_elements=128, pitch=0.3048e-3, width=0.2798e-3, height=_INF,
                     elevation_focus=_INF, radius=_INF, fc=7.2e6, bandwidth=70.0),
    "L14-5W/60": dict(n_elements=128, pitch=0.472e-3, width=0.447e-3, height=_INF,
                      elevation_focus=_INF, radius=_INF, fc=7.5e6, bandwidth=65.0),
    # Philips/ATL phased array
    "P6-3": dict(n_elements=64, pitch=0.218e-3, width=0.193e-3, height=_INF,
                 elevation_focus=_INF, radius=_INF, fc=4.5e6, bandwidth=66.66666666666667),  # 2/3 of fc
    # Philips/ATL L7-4 (not in PyMUST's getparam): 128 elements, 0.298 mm pitch,
    # 0.250 mm width, 5.208 MHz, 4-7 MHz band (57.6 %), about 7.5 mm elevation
    # aperture focused near 25 mm (Verasonics transducer table).
    "L7-4": dict(n_elements=128, pitch=0.298e-3, width=0.250e-3, height=7.5e-3,
                 elevation_focus=25e-3, radius=_INF, fc=5.208e6, bandwidth=57.6),
}

#: Matrix probes (:class:`MatrixProbe`). ``MATRIX-32x32``: the 3-MHz 32 x 32 array of MUST's
#: 3-D examples (``txdelay3``, ``pfield3``, ``simus3``): 300 um pitch, 250 um square elements,
#: 70 % bandwidth (PyMUST's ``getparam`` has no matrix probe; these are the numbers of its
#: examples). Its pulse-echo spectrum (1-cycle pulse times the squared response) peaks near
#: 2.7 MHz. ``MATRIX-32x35``: the same elements on a 32 x 35 grid whose rows 8, 17 and 26 are
#: blank (a row left unconnected after every 8 rows): 1024 connected elements in four banks of
#: 8 rows x 32 columns, the layout of 1024-element matrix probes wired in four 256-element banks
#: (``docs/matrix.md``).
MATRIX_CATALOGUE: dict[str, dict[str, Any]] = {
    "MATRIX-32x32": dict(nx=32, ny=32, pitch_x=0.300e-3, pitch_y=0.300e-3, width=0.250e-3,
                         height=0.250e-3, fc=3e6, bandwidth=70.0),
    "MATRIX-32x35": dict(nx=32, ny=35, pitch_x=0.300e-3, pitch_y=0.300e-3, width=0.250e-3,
                         height=0.250e-3, fc=3e6, bandwidth=70.0, blank_rows=(8, 17, 26)),
}

_LOOKUP = {name.lower(): name for name in PROBE_CATALOGUE}
_MATRIX_LOOKUP = {name.lower(): name for name in MATRIX_CATALOGUE}


def list_probes() -> list[str]:
    """Names of the catalogue probes, in catalogue order: the 1-D probes, then the matrix probes."""
    return list(PROBE_CATALOGUE) + list(MATRIX_CATALOGUE)


def get_probe(name: str, /, **overrides: Any) -> "Probe | MatrixProbe":
    """Return the catalogue probe ``name`` (case-insensitive), with optional field overrides.

    ``overrides`` are any fields of the probe's class (:class:`Probe`, e.g. ``fc=3.5e6``, or
    :class:`MatrixProbe` for a matrix probe, e.g. ``nx=8, ny=8``) and are validated. Unknown
    probe names or override keys raise :class:`ParameterError`.
    """
    if not isinstance(name, str):
        raise ParameterError(f"probe name = {name!r} must be a string; known probes: {list_probes()}")
    low = name.strip().lower()
    key = _LOOKUP.get(low)
    if key is None:
        mkey = _MATRIX_LOOKUP.get(low)
        if mkey is None:
            raise ParameterError(f"probe name = {name!r} is unknown; known probes: {list_probes()}")
        _check_field_names(overrides, _MATRIX_FIELD_NAMES)
        fields = dict(MATRIX_CATALOGUE[mkey], name=mkey)
        fields.update(overrides)
        return MatrixProbe(**fields)
    _check_field_names(overrides)
    fields = dict(PROBE_CATALOGUE[key], name=key)
    fields.update(overrides)
    return Probe(**fields)


# ---------------------------------------------------------------------- acquisition
@dataclass(frozen=True)
class Acquisition:
    """Medium and sampling settings of an acquisition.

    Attributes:
        fs: sampling frequency of the RF signals (Hz, > 0).
        c: speed of sound (m/s, in [C_MIN, C_MAX] = [300, 10000]).
        attenuation: attenuation coefficient (dB/cm/MHz, >= 0).
        tx_cycles: length of the transmit pulse in wavelengths (cycles, > 0).
    """

    fs: float
    c: float = 1540.0
    attenuation: float = 0.0
    tx_cycles: float = 1.0

    def __post_init__(self) -> None:
        set_ = lambda field, value: object.__setattr__(self, field, value)  # noqa: E731
        set_("fs", positive("fs", self.fs))
        set_("c", check_sound_speed(self.c))
        att = check_number("attenuation", self.attenuation, lo=0.0)
        if math.isinf(att):
            raise ParameterError(f"attenuation = {self.attenuation!r} must be finite; allowed: [0, inf)")
        set_("attenuation", att)
        set_("tx_cycles", positive("tx_cycles", self.tx_cycles))

    @classmethod
    def for_probe(cls, probe: "Probe | MatrixProbe | PlanarProbe", fs: float | None = None,
                  **kw: Any) -> "Acquisition":
        """Settings for ``probe``: ``fs`` defaults to 4 * probe.fc; ``kw`` sets the other fields."""
        if not isinstance(probe, (Probe, MatrixProbe, PlanarProbe)):
            raise ParameterError(f"probe must be a Probe, got {type(probe).__name__}")
        allowed = ("c", "attenuation", "tx_cycles")
        unknown = [k for k in kw if k not in allowed]
        if unknown:
            raise ParameterError(
                f"unknown acquisition field(s) {', '.join(map(repr, unknown))}; allowed: fs, {', '.join(allowed)}")
        return cls(fs=4.0 * probe.fc if fs is None else fs, **kw)

    def replace(self, **changes: Any) -> "Acquisition":
        """Return a validated copy with some fields changed."""
        names = tuple(f.name for f in dataclasses.fields(self))
        unknown = [k for k in changes if k not in names]
        if unknown:
            raise ParameterError(
                f"unknown acquisition field(s) {', '.join(map(repr, unknown))}; allowed: {', '.join(names)}")
        return dataclasses.replace(self, **changes)


def min_sampling_frequency(probe: Probe) -> float:
    """Nyquist rate of the pulse band: 2 * fc * (1 + bandwidth / 200) (Hz)."""
    return 2.0 * probe.fc * (1.0 + probe.bandwidth / 200.0)


def check_sampling(probe: Probe, acq: Acquisition) -> None:
    """Check the sampling frequency covers the probe's pulse band.

    Rule: ``fs >= 2 * fc * (1 + bandwidth / 200)``, i.e. twice the upper -6 dB
    edge fc * (1 + bandwidth/200) of the band. Raises :class:`ParameterError`
    naming fs, its value and the minimum otherwise.
    """
    fmin = min_sampling_frequency(probe)
    if acq.fs < fmin * (1.0 - 1e-12):
        raise ParameterError(
            f"fs = {acq.fs!r} Hz is below the Nyquist rate of the pulse band of probe "
            f"{probe.name!r}: need fs >= 2 * fc * (1 + bandwidth / 200) = {fmin!r} Hz "
            f"(fc = {probe.fc!r} Hz, bandwidth = {probe.bandwidth!r} %)")

