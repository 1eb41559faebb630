"""The physics a scene describes: its probe, acquisition and PSF setups (the :class:`SceneSetups`
half of :class:`~arraysel.scenes.scene.Scene`).

The setups are built from the scene's values on demand; nothing is simulated here. A 1-D
scene gives one :class:`~arraysel.physics.psf.PSFSetup` per field point, a 3-D scene (a
``[volume]`` section) one :class:`~arraysel.physics.volume.MatrixPSFSetup`. A grid too large
for the memory cap is refused from its sizes alone (:func:`memory_check`).
"""
from __future__ import annotations

import math

import numpy as np

from arraysel.errors import ParameterError
from arraysel.scenes.keys import SCHEMA


class SceneSetups:
    """The physics methods of :class:`~arraysel.scenes.scene.Scene`; they read the scene through
    its ``section``, ``get``, ``value``, ``length``, ``points``, ``pixel`` and ``wavelength``."""

    def probe(self):
        """The scene's probe: a :class:`~arraysel.physics.probes.Probe` or, for a matrix
        catalogue probe, a :class:`~arraysel.physics.probes.MatrixProbe` (keys of the other
        kind of probe are refused, naming the key)."""
        from arraysel.physics.probes import MATRIX_ONLY_FIELDS, LINEAR_ONLY_FIELDS, get_probe

        p = self.section("probe")
        if p.get("file"):  # a probe file: its geometry, the other keys fill in or replace its fields
            from arraysel.physics.probe_files import PROBE_FIELDS, load_probe

            path = p.pop("file")
            wrong = [k for k in p if k not in PROBE_FIELDS]
            if wrong:
                raise ParameterError(f"probe.{wrong[0]} cannot be set with probe.file (the geometry comes from "
                                     f"the file); allowed with it: {', '.join(PROBE_FIELDS)}")
            return load_probe(path, **p)
        p.pop("file", None)
        name = p.pop("name", SCHEMA["probe"]["name"].default)
        matrix = get_probe(name).is_matrix
        wrong = [k for k in p if k in (LINEAR_ONLY_FIELDS if matrix else MATRIX_ONLY_FIELDS)]
        if wrong:
            kind, other = ("a matrix", "1-D") if matrix else ("a 1-D", "matrix")
            raise ParameterError(f"probe.{wrong[0]} applies to {other} probes only; probe.name = {name!r} is "
                                 f"{kind} probe")
        try:
            return get_probe(name, **p)
        except ParameterError as exc:  # a check across fields ("width = ... (0, pitch]"): name the key
            if str(exc).split(" = ", 1)[0] in p:
                raise ParameterError(f"probe.{exc}") from None
            raise

    def constraints(self):
        """The scene's :class:`~arraysel.constraints.Constraints` (its ``[constraints]`` section
        checked against the probe and ``selection.k``), None without the section."""
        sec = self.section("constraints")
        if not sec:
            return None
        import numpy as np

        from arraysel.constraints import Constraints

        probe = self.probe()
        n = int(probe.n_elements)
        if probe.is_matrix:
            positions = probe.element_positions()
        else:
            positions = np.stack([probe.element_positions()[0], np.zeros(n)], axis=1)
        off = list(sec.get("forced_off") or [])
        rows = sec.get("forced_off_rows")
        if rows:
            if not probe.is_matrix or not hasattr(probe, "element_grid"):
                raise ParameterError("constraints.forced_off_rows needs a gridded matrix probe; list the elements "
                                     "in constraints.forced_off")
            ny = probe.grid_shape[0]
            bad = [r for r in rows if r >= ny]
            if bad:
                raise ParameterError(f"constraints.forced_off_rows = {rows}: row {bad[0]} is out of range "
                                     f"[0, {ny - 1}]")
            iy = probe.element_grid(np.arange(n))[1]
            off += np.flatnonzero(np.isin(iy, rows)).tolist()
        groups = sec.get("groups")
        return Constraints(n, int(self.get("selection", "k")), groups=groups,
                           group_mode=sec.get("mode", "exactly-one"), forced_on=sec.get("forced_on") or (),
                           forced_off=off, symmetry=sec.get("symmetry", "none"), positions=positions,
                           source=groups if isinstance(groups, str) and not groups.endswith(".csv") else
                           (f"the group file {groups}" if groups else ""))

    def matrix_probe(self):
        """The scene's probe for a 3-D scene: refused, naming ``probe.name``, unless it is a matrix probe."""
        probe = self.probe()
        if not probe.is_matrix:
            raise ParameterError(f"probe.name = {probe.name!r} is a 1-D probe: a 3-D scene needs a matrix probe "
                                 "(e.g. 'MATRIX-32x32')")
        return probe


    def matrix_setup(self):
        """The :class:`~arraysel.physics.volume.MatrixPSFSetup` of a 3-D scene (``[volume]``)."""
        from arraysel.physics.volume import MatrixPSFSetup

        if not self.is_volume:
            raise ParameterError(f"scene {self.name!r} has no [volume] section: it is not a 3-D scene")
        probe = self.matrix_probe()
        acq = self.acquisition()
        delays = self._delays3(probe, acq)
        lam = self.wavelength
        half = {k: float(self.length("volume", k)) * lam for k in ("half_x", "half_y", "half_z")}
        x = self.length("medium", "scatterer_x")
        y = self.length("medium", "scatterer_y")
        z = self.length("medium", "scatterer_z")
        return MatrixPSFSetup(probe=probe, acq=acq, delays=delays,
                              scatterer=(0.0 if x is None else float(x), 0.0 if y is None else float(y), float(z)),
                              pixel=lam / float(self.value("volume", "pixels_per_wavelength")),
                              planes=self.planes(), reflectivity=float(self.value("medium", "reflectivity")),
                              iq_bandwidth=self.value("receive", "iq_bandwidth"), options=self._sim_options(), **half)

    def _delays3(self, probe, acq):
        """The full-array delays of a 3-D scene's transmits (``[transmit]``)."""
        from arraysel.physics.volume import diverging_delays3, plane_wave_delays3, tilt_grid

        tx = self.value("transmit", "max_tilt_deg")
        ty = self.value("transmit", "max_tilt_deg_y")
        ax, ay = tilt_grid(int(self.value("transmit", "n_tx_x")), int(self.value("transmit", "n_tx_y")),
                           float(tx), float(tx if ty is None else ty))
        dist = float(self.length("transmit", "source_distance"))
        return diverging_delays3(probe, ax, ay, dist, acq) if dist > 0 else plane_wave_delays3(probe, ax, ay, acq)

    def sector_geometry(self) -> dict:
        """A sector scene's geometry (``docs/sector.md``): ``tilts`` (the largest transmit tilts in x
        and y, degrees), ``half_angles`` (the sector's, degrees), ``aperture`` (m, along x and y),
        ``pitch`` (m), ``lobe`` (lambda0 / D along x and y), ``step`` (the surfaces' u-v step) and
        ``half_uv`` (how far the surfaces reach in u and v)."""
        probe = self.matrix_probe()
        pos = probe.element_positions()
        ap = (float(np.ptp(pos[:, 0])) + probe.width, float(np.ptp(pos[:, 1])) + probe.height)
        pitch = (float(getattr(probe, "pitch_x", ap[0])), float(getattr(probe, "pitch_y", ap[1])))
        tx = float(self.value("transmit", "max_tilt_deg"))
        ty = self.value("transmit", "max_tilt_deg_y")
        ty = tx if ty is None else float(ty)
        half = self.value("sector", "half_angle_deg")
        halves = (tx, ty) if half is None else (float(half), float(half))
        lam = self.wavelength
        lobe = (lam / ap[0], lam / ap[1])
        step = min(lobe) / float(self.value("sector", "samples_per_lobe"))
        margin = float(self.value("sector", "margin"))
        half_uv = tuple(math.sin(math.radians(h)) + margin * lb for h, lb in zip(halves, lobe))
        return {"tilts": (tx, ty), "half_angles": halves, "aperture": ap, "pitch": pitch, "lobe": lobe,
                "step": step, "half_uv": half_uv}

    def sector_setup(self):
        """The :class:`~arraysel.physics.volume.sector.SectorSetup` of a sector scene (``[sector]``)."""
        from arraysel.physics.volume.sector import SectorSetup, beam_point, sector_grid

        if not self.is_sector:
            raise ParameterError(f"scene {self.name!r} has no [sector] section: it is not a sector scene")
        probe = self.matrix_probe()
        acq = self.acquisition()
        geo = self.sector_geometry()
        pts = [beam_point(ax, ay, float(self.length("sector", "points", r))) for ax, ay, r in self.get("sector", "points")]
        u, v = sector_grid(*geo["half_uv"], geo["step"])
        return SectorSetup(probe=probe, acq=acq, delays=self._delays3(probe, acq), points=pts, u=u, v=v,
                           sines=tuple(math.sin(math.radians(h)) for h in geo["half_angles"]),
                           reflectivity=float(self.value("medium", "reflectivity")),
                           iq_bandwidth=self.value("receive", "iq_bandwidth"), options=self._sim_options())

    def planes(self) -> tuple[str, ...]:
        """The planes of a 3-D scene (``volume.planes``), checked."""
        from arraysel.physics.probes import MATRIX_PLANES as PLANES

        raw = str(self.value("volume", "planes"))
        names = tuple(p.strip() for p in raw.split(",") if p.strip())
        bad = [p for p in names if p not in PLANES]
        if bad or not names or len(set(names)) != len(names):
            raise ParameterError(f"volume.planes = {raw!r}: allowed a comma-separated subset of {list(PLANES)} "
                                 "without repeats")
        return names

    def _sim_options(self):
        from arraysel.physics.simus import SimOptions

        split = self.value("simulator", "element_splitting")
        return SimOptions(db_thresh=float(self.value("simulator", "db_thresh")),
                          element_splitting=None if not split else int(split),
                          full_frequency_directivity=bool(self.value("simulator", "full_frequency_directivity")),
                          frequency_step=float(self.value("simulator", "frequency_step")))

    def acquisition(self):
        from arraysel.physics.probes import Acquisition

        probe = self.probe()
        a = self.section("acquisition")
        ratio = a.pop("fs_over_fc", None)
        fs = a.pop("fs", None)
        if fs is None:
            fs = (ratio or SCHEMA["acquisition"]["fs_over_fc"].default) * probe.fc
        elif ratio is not None:
            raise ParameterError("acquisition.fs and acquisition.fs_over_fc are exclusive: give one")
        return Acquisition(fs=fs, **a)

    def psf_setups(self) -> list:
        """One :class:`~arraysel.physics.psf.PSFSetup` per field point (see :meth:`points`).

        With ``medium.points`` each point gets its own grid, shifted by whole
        pixels (``x_offset``, ``z_offset``) so that the point sits where the
        one-scatterer scene puts its scatterer: column ``n_x // 2``, row
        ``n_z // 2`` (to within half a pixel; rows never start above z = 0).
        """
        if self.get("medium", "points") is None:
            return [self.psf_setup()]
        pixel = self.pixel
        n_z = int(self.length("grid", "n_z"))
        out = []
        for x, z in self.points():
            z_off = max(0, int(round(z / pixel)) - n_z // 2)
            out.append(self._setup(x_offset=int(round(x / pixel)), z_offset=z_off, scatterer=(x, z)))
        return out

    def psf_setup(self, point: int = 0):
        """The :class:`~arraysel.physics.psf.PSFSetup` of field point ``point`` (the only one of most scenes)."""
        if self.get("medium", "points") is not None:
            setups = self.psf_setups()
            if not 0 <= point < len(setups):
                raise ParameterError(f"point = {point} is out of range; the scene has {len(setups)} point(s)")
            return setups[point]
        m = self.section("medium")
        scat = None
        if "scatterer_x" in m or "scatterer_z" in m:
            scat = self.points()[0]
        return self._setup(x_offset=0, z_offset=int(self.value("grid", "z_offset")), scatterer=scat)

    def _setup(self, x_offset: int, z_offset: int, scatterer):
        from arraysel.physics.psf import PSFSetup

        probe = self.probe()
        if probe.is_matrix:
            raise ParameterError(f"probe.name = {probe.name!r} is a matrix probe: this scene images the xz plane "
                                 "of a 1-D probe; a matrix probe needs a 3-D scene")
        memory_check(self, probe.n_elements)
        acq = self.acquisition()
        n_tx = int(self.value("transmit", "n_tx"))
        tilt = float(self.value("transmit", "max_tilt_deg"))
        tilts = tuple(np.deg2rad(np.linspace(-tilt, tilt, n_tx))) if n_tx > 1 else (0.0,)
        pixel = self.pixel
        options = self._sim_options()
        setup = PSFSetup(probe=probe, acq=acq, tilts=tilts, n_x=int(self.length("grid", "n_x")),
                         n_z=int(self.length("grid", "n_z")), pixel=pixel, z_offset=z_offset, x_offset=x_offset,
                         scatterer=scatterer, reflectivity=float(self.value("medium", "reflectivity")),
                         window=int(self.length("grid", "window")), fnumber=float(self.value("receive", "fnumber")),
                         iq_bandwidth=self.value("receive", "iq_bandwidth"), options=options)
        scatterer_on_grid(setup)
        aperture_at_scatterer(setup)
        return setup


def scatterer_on_grid(setup) -> None:
    """Refuse a scatterer off its grid (its PSF would be cut from the grid's edge: a number that
    means nothing), naming the key(s) and the grid's extent."""
    row, col = setup.scatterer_pixel
    off = [key for key, inside in (("medium.scatterer_x", 0 <= col < setup.n_x),
                                   ("medium.scatterer_z", 0 <= row < setup.n_z)) if not inside]
    if off:
        x, z = setup.scatterer_position
        raise ParameterError(
            f"{' and '.join(off)}: the scatterer at x = {x:g} m, z = {z:g} m lies outside the grid (x from "
            f"{setup.x[0]:g} to {setup.x[-1]:g} m, z from {setup.z[0]:g} to {setup.z[-1]:g} m: grid.n_x x grid.n_z = "
            f"{setup.n_x} x {setup.n_z} pixels of {setup.pitch:g} m); move it onto the grid or enlarge the grid")


def aperture_at_scatterer(setup) -> None:
    """Refuse an f-number whose receive aperture holds no element at the scatterer (its image
    would be all zero), naming ``receive.fnumber``."""
    f = float(setup.fnumber)
    if f <= 0:
        return
    xs, zs = setup.scatterer_position
    xe, ze, theta, _ = setup.probe.element_positions()
    dx = xs - xe
    if setup.probe.is_linear:
        inside = np.abs(dx) <= zs / 2 / f
    else:
        inside = np.abs(np.arcsin(dx / np.hypot(dx, zs - ze)) - theta) <= np.arctan(1 / 2 / f)
    if not inside.any():
        raise ParameterError(
            f"receive.fnumber = {f:g} leaves no element in the receive aperture at the scatterer (x = {xs:g} m, "
            f"z = {zs:g} m: an aperture {zs / f:.3g} m wide, elements {setup.probe.pitch:g} m apart); lower it "
            f"(0: every element receives)")


def memory_check(scene, n_elements: int) -> None:
    """Refuse, from the sizes alone (nothing allocated), a grid whose setting up needs more memory
    than the cap ``ARRAYSEL_MEMORY_GIB`` (:func:`arraysel.physics.psf.settings.grid_bytes`):
    the message names the keys, the memory needed and allowed, and the largest grid allowed."""
    from arraysel.physics.psf.settings import MEMORY_GIB, grid_bytes, largest_grid_pixels, memory_limit_bytes

    n_x, n_z = int(scene.length("grid", "n_x")), int(scene.length("grid", "n_z"))
    win = int(scene.length("grid", "window"))
    need, step = grid_bytes(n_x, n_z, win, n_elements)
    limit = memory_limit_bytes()
    if need <= limit:
        return
    most = largest_grid_pixels(n_elements, limit)
    side = int(math.isqrt(most))
    raise ParameterError(
        f"grid.n_x x grid.n_z = {n_x} x {n_z} pixels needs about {need / 2 ** 30:.1f} GiB ({step}, "
        f"{n_elements} elements), more than the {limit / 2 ** 30:.1f} GiB allowed by {MEMORY_GIB}; allowed: "
        f"grid.n_x * grid.n_z up to about {most / 1e6:.3g} million pixels (e.g. {side} x {side}): reduce "
        f"grid.n_x / grid.n_z (or coarsen grid.pixel), or raise {MEMORY_GIB}")
