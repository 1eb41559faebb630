"""Whole-scene checks: what a scene must satisfy once all its keys are known.

The windows, grids and metric regions of a 1-D scene must fit in pixels (:func:`region_checks`),
a 3-D scene must image planes around one scatterer below a matrix probe (:func:`volume_checks`),
and keys of the other kind of scene are refused, naming the key (:func:`check_scene`). Errors
name the keys and the allowed range.
"""
from __future__ import annotations

import logging
import math

from arraysel.errors import ParameterError, check_number

_log = logging.getLogger("arraysel.scenes.schema")  # the scene loader's one logger name, as before the split


def region_checks(scene) -> None:
    """Windows, grids and metric regions in pixels: they must fit (errors name the keys)."""
    n_x, n_z = int(scene.length("grid", "n_x")), int(scene.length("grid", "n_z"))
    win = int(scene.length("grid", "window"))
    for key, n in (("n_x", n_x), ("n_z", n_z)):
        if not 8 <= n <= 8192:
            raise ParameterError(f"grid.{key} = {scene.value('grid', key)!r} is {n} pixels; allowed: [8, 8192] "
                                 f"pixels (pitch {scene.pixel * 1e3:.4g} mm)")
    if not 4 <= win <= 8192:
        raise ParameterError(f"grid.window = {scene.value('grid', 'window')!r} is {win} pixels; allowed: "
                             f"[4, 8192] pixels (pitch {scene.pixel * 1e3:.4g} mm)")
    if win > min(n_x, n_z):
        raise ParameterError(f"grid.window = {scene.value('grid', 'window')!r} must not exceed grid.n_x and "
                             f"grid.n_z (window {win} px, grid {n_x} x {n_z} px)")
    r_main = float(scene.length("metrics", "r_main"))
    r_guard = float(scene.length("metrics", "r_guard"))
    for key, r in (("r_main", r_main), ("r_guard", r_guard)):
        if not 0 < r <= 1000:
            raise ParameterError(f"metrics.{key} = {scene.value('metrics', key)!r} is {r:.4g} wavelengths; "
                                 f"allowed: (0, 1000]")
    if r_guard < r_main:
        raise ParameterError("metrics.r_guard must be >= metrics.r_main "
                             f"(r_main = {r_main:.4g} wl, r_guard = {r_guard:.4g} wl)")
    # in pixels, around the window's centre pixel (where the peak sits)
    lam_px = scene.wavelength / scene.pixel
    c = win // 2
    inscribed = min(c, win - 1 - c)
    corner = math.hypot(c, c)
    w_mm = win * scene.pixel * 1e3
    problem = None
    if r_main * lam_px > inscribed * (1 + 1e-9):
        problem = (
            f"metrics.r_main = {scene.value('metrics', 'r_main')!r} ({r_main * lam_px:.1f} px) does not fit "
            f"grid.window = {scene.value('grid', 'window')!r} ({win} px, {w_mm:.3g} mm): the main lobe region "
            f"must lie inside the window (r_main <= {inscribed} px = {inscribed / lam_px:.3g} wl); "
            f"enlarge grid.window or reduce metrics.r_main")
    elif r_guard * lam_px >= corner * (1 - 1e-9):
        problem = (
            f"metrics.r_guard = {scene.value('metrics', 'r_guard')!r} ({r_guard * lam_px:.1f} px) does not fit "
            f"grid.window = {scene.value('grid', 'window')!r} ({win} px, {w_mm:.3g} mm): the side-lobe region "
            f"r >= r_guard would be empty (r_guard < {corner:.1f} px = {corner / lam_px:.3g} wl needed); "
            f"enlarge grid.window or reduce metrics.r_guard")
    if problem is None:
        return
    if not scene.needs_data:
        raise ParameterError(problem)
    # an end-to-end scene's window is also the kernel of L_conv: small ones stay allowed there
    _log.warning("scene %r: %s (L_contrast and L_SLR are then 0 or partial)", scene.name, problem)


#: keys that only a 3-D scene reads
VOLUME_ONLY_KEYS = (("transmit", "n_tx_x"), ("transmit", "n_tx_y"), ("transmit", "max_tilt_deg_y"),
                    ("transmit", "source_distance"), ("medium", "scatterer_y"))
#: keys that a 3-D scene does not read (it images planes, not the xz grid)
PLANAR_ONLY_SECTIONS = ("grid",)
PLANAR_ONLY_KEYS = (("transmit", "n_tx"), ("medium", "points"), ("receive", "fnumber"),
                    ("simulator", "fast_margin"), ("simulator", "fast_block"))


def volume_checks(scene) -> None:
    """A 3-D scene: a matrix probe, one scatterer below the array, metric regions inside the planes."""
    scene.matrix_probe()
    for sec in PLANAR_ONLY_SECTIONS:
        if scene.section(sec):
            key = next(iter(scene.section(sec)))
            raise ParameterError(f"{sec}.{key} does not apply to a 3-D scene (its planes are set in [volume])")
    wrong = [f"{sec}.{key}" for sec, key in PLANAR_ONLY_KEYS if key in scene.section(sec)]
    if wrong:
        raise ParameterError(f"{wrong[0]} does not apply to a 3-D scene")
    if scene.length("medium", "scatterer_z") is None:
        raise ParameterError("medium.scatterer_z is required in a 3-D scene (the scatterer's depth, e.g. '30 mm')")
    scene.planes()
    halves = {k: float(scene.length("volume", k)) for k in ("half_x", "half_y", "half_z")}
    r_main = float(scene.length("metrics", "r_main"))
    r_guard = float(scene.length("metrics", "r_guard"))
    if r_guard < r_main:
        raise ParameterError("metrics.r_guard must be >= metrics.r_main "
                             f"(r_main = {r_main:.4g} wl, r_guard = {r_guard:.4g} wl)")
    if r_main > min(halves.values()):
        raise ParameterError(f"metrics.r_main = {r_main:.4g} wl does not fit the planes: allowed at most the "
                             f"smallest half-size, {min(halves.values()):.4g} wl (volume.half_x/y/z)")
    if r_guard >= max(halves.values()):
        raise ParameterError(f"metrics.r_guard = {r_guard:.4g} wl leaves no side-lobe region: allowed below the "
                             f"largest half-size, {max(halves.values()):.4g} wl (volume.half_x/y/z)")
    # the planes' pixels and extent (checked again, with the physics, by MatrixPSFSetup)
    per_wl = float(scene.value("volume", "pixels_per_wavelength"))
    for key, half in halves.items():
        n = max(1, int(round(2 * half * per_wl)))
        if n > 4096:
            raise ParameterError(f"volume.{key} = {half:.4g} wl is {n} pixels at volume.pixels_per_wavelength = "
                                 f"{per_wl:g}; allowed: at most 4096 pixels an axis")
    depth = float(scene.length("medium", "scatterer_z"))
    n_z = max(1, int(round(2 * halves["half_z"] * per_wl)))
    top = depth - (n_z // 2) * scene.wavelength / per_wl
    if top <= 0:
        raise ParameterError(f"volume.half_z = {halves['half_z']:.4g} wl reaches above the array from the "
                             f"scatterer's depth medium.scatterer_z = {depth:.4g} m; allowed: planes below z = 0")


def sector_checks(scene) -> None:
    """A sector scene: a matrix probe, points inside the sector, steering the probe's lattice
    allows, surfaces fine enough to resolve a side lobe (errors name the key)."""
    scene.matrix_probe()
    if scene.is_volume:
        raise ParameterError("[sector] and [volume] are exclusive: a sector scene images its points on surfaces "
                             "over the sector, not on planes")
    for sec in PLANAR_ONLY_SECTIONS:
        if scene.section(sec):
            raise ParameterError(f"{sec}.{next(iter(scene.section(sec)))} does not apply to a sector scene")
    wrong = [f"{sec}.{key}" for sec, key in PLANAR_ONLY_KEYS + (("medium", "scatterer_x"), ("medium", "scatterer_y"),
                                                                ("medium", "scatterer_z")) if key in scene.section(sec)]
    if wrong:
        raise ParameterError(f"{wrong[0]} does not apply to a sector scene (its points are sector.points)")
    if scene.get("sector", "points") is None:
        raise ParameterError("sector.points is required: [[theta_x_deg, theta_y_deg, range], ...]")
    geo = scene.sector_geometry()
    lam, pitch = scene.wavelength, geo["pitch"]
    limit = lam / max(pitch) - 1.0      # sin of the steering at which the lattice's grating lobe turns visible
    tx, ty = geo["tilts"]
    for key, tilt in (("transmit.max_tilt_deg", tx), ("transmit.max_tilt_deg_y", ty)):
        if math.sin(math.radians(tilt)) >= limit:
            top = math.degrees(math.asin(limit)) if -1 < limit < 1 else 0.0
            raise ParameterError(f"{key} = {tilt:g} degrees steers past what the probe's grid allows: its grating "
                                 f"lobe (lambda0 / pitch = {lam / max(pitch):.3g}) enters the visible region beyond "
                                 f"{top:.1f} degrees; allowed: below {top:.1f}")
    hx, hy = geo["half_angles"]
    if min(hx, hy) <= 0:
        raise ParameterError("the sector is empty: give sector.half_angle_deg > 0 or steered transmits "
                             "(transmit.max_tilt_deg > 0)")
    for i, (ax, ay, _r) in enumerate(scene.get("sector", "points")):
        if abs(ax) > hx + 1e-9 or abs(ay) > hy + 1e-9:
            raise ParameterError(f"sector.points[{i}] = [{ax:g}, {ay:g}, ...] lies outside the sector: allowed "
                                 f"|theta_x| <= {hx:g} and |theta_y| <= {hy:g} degrees (sector.half_angle_deg)")
    spl = float(scene.value("sector", "samples_per_lobe"))
    if spl < 2:
        raise ParameterError(f"sector.samples_per_lobe = {spl:g} is too coarse to resolve the main lobe and a side "
                             "lobe; allowed: at least 2 samples per lambda0 / D")
    hu, hv = geo["half_uv"]
    n = [2 * math.ceil(h / geo["step"]) + 1 for h in (hu, hv)]
    if max(n) > 1024:
        raise ParameterError(f"sector.samples_per_lobe = {spl:g} gives {max(n)} samples an axis; allowed: at most "
                             "1024 (lower it, or sector.margin)")
    cu, cv = (math.ceil(h / geo["step"] - 1e-9) * geo["step"] for h in (hu, hv))   # the grid's corner
    if cu * cu + cv * cv > 1:
        raise ParameterError(f"sector.margin = {scene.value('sector', 'margin'):g}: the surfaces (|u| <= {hu:.3f}, "
                             f"|v| <= {hv:.3f}, on the grid {cu:.3f}, {cv:.3f}) leave the visible region; lower it or "
                             "sector.half_angle_deg")


def cyst_checks(scene) -> None:
    """The optional ``[cysts]`` section of a sector scene (``docs/sector.md``): its points among
    ``sector.points``, its background ring outside the cyst, its radius at least two samples of each
    point's surface and its ring inside the surface (errors name the key)."""
    if "cysts" not in scene.tree:
        return
    if not scene.is_sector:
        raise ParameterError("[cysts] applies to sector scenes only (a [sector] section): the cysts are imaged "
                             "with the PSFs of the sector's points")
    pts = scene.get("sector", "points")
    idx = scene.value("cysts", "points")
    idx = list(range(len(pts))) if idx is None else list(idx)
    for j, i in enumerate(idx):
        if not 0 <= int(i) < len(pts):
            raise ParameterError(f"cysts.points[{j}] = {i} is out of range; allowed: [0, {len(pts) - 1}] (the "
                                 f"indices of sector.points, which has {len(pts)})")
    if not idx:
        raise ParameterError("cysts.points is empty; give at least one index of sector.points (or leave it out)")
    lo, hi = float(scene.value("cysts", "ring_inner")), float(scene.value("cysts", "ring_outer"))
    if hi <= lo:
        raise ParameterError(f"cysts.ring_outer = {hi:g} must be > cysts.ring_inner = {lo:g} (multiples of "
                             "the radius)")
    radius = float(scene.length("cysts", "radius"))
    geo = scene.sector_geometry()
    step, (hu, hv) = geo["step"], geo["half_uv"]
    for i in idx:
        ax, ay, r = pts[int(i)]
        rng = float(scene.length("sector", "points", r))
        if radius / rng < 2 * step - 1e-12:
            raise ParameterError(f"cysts.radius = {radius * 1e3:.4g} mm is {radius / rng / step:.2f} samples of "
                                 f"the surface of sector.points[{i}] (range {rng * 1e3:.4g} mm, step {step:.4g} "
                                 f"in u); allowed: at least 2 samples, {2 * step * rng * 1e3:.3g} mm")
        u0, v0 = math.sin(math.radians(ax)), math.sin(math.radians(ay))
        reach = hi * radius / rng
        if abs(u0) + reach > hu or abs(v0) + reach > hv:
            top = min(hu - abs(u0), hv - abs(v0)) * rng / hi
            raise ParameterError(f"cysts.radius = {radius * 1e3:.4g} mm: the background ring of the cyst at "
                                 f"sector.points[{i}] (out to cysts.ring_outer = {hi:g} radii) leaves the point's "
                                 f"surface; allowed: at most {top * 1e3:.3g} mm there")


def aperture_checks(scene, n_elements: int, k: int) -> None:
    """The ``[aperture]`` section: ``k_tx`` and ``k_rx`` in ``[1, Ne]`` and only with ``separate`` or
    ``per-transmit``, which needs a matrix-probe scene imaged on planes (ParameterError naming the
    key); a ``[constraints]`` section is checked when the objective lifts it onto each aperture
    (:func:`arraysel.constraints.aperture_constraints`)."""
    sec = scene.section("aperture")
    mode = sec.get("mode", "shared")
    for key in ("k_tx", "k_rx"):
        if key not in sec:
            continue
        if mode not in ("separate", "per-transmit"):
            raise ParameterError(f"aperture.{key} applies to aperture.mode = 'separate' or 'per-transmit' only "
                                 f"(aperture.mode = {mode!r})")
        if not 1 <= int(sec[key]) <= n_elements:
            raise ParameterError(f"aperture.{key} = {sec[key]} is out of range; allowed: [1, {n_elements}] "
                                 f"(the probe has {n_elements} elements)")
    if mode == "per-transmit" and (not scene.is_volume or scene.is_sector):
        raise ParameterError("aperture.mode = 'per-transmit' applies to matrix-probe scenes imaged on planes (such as "
                             "matrix-1024); allowed on this scene: shared, full-tx, separate")
    if mode != "shared" and scene.needs_data:
        raise ParameterError(f"aperture.mode = {mode!r} applies to PSF scenes; end-to-end scenes (weights.L_conv "
                             "or weights.L_rec > 0) use one shared aperture")


def check_scene(scene):
    """``scene`` if it is complete and consistent, else a :class:`ParameterError` naming the key."""
    probe = scene.probe()
    k = scene.get("selection", "k")
    if k is None:
        raise ParameterError("selection.k is required")
    if not 1 <= int(k) <= probe.n_elements:
        raise ParameterError(f"selection.k = {k} is out of range; allowed: [1, {probe.n_elements}] "
                             f"(the probe has {probe.n_elements} elements)")
    scene.constraints()  # the [constraints] section against the probe and k (ParameterError naming the key)
    aperture_checks(scene, probe.n_elements, int(k))
    if scene.is_sector:
        sector_checks(scene)
        cyst_checks(scene)
        return scene
    cyst_checks(scene)  # refuses [cysts] outside a sector scene
    if scene.is_volume:
        volume_checks(scene)
        return scene
    wrong = [f"{sec}.{key}" for sec, key in VOLUME_ONLY_KEYS if key in scene.section(sec)]
    if wrong:
        raise ParameterError(f"{wrong[0]} applies to 3-D scenes only (a [volume] section and a matrix probe)")
    if scene.get("grid", "pixel") is not None:
        p = scene.pixel
        if not 0 < p <= 1:
            raise ParameterError(f"grid.pixel = {scene.get('grid', 'pixel')!r} is {p:.4g} m; allowed: (0, 1] m")
    region_checks(scene)
    m = scene.section("medium")
    if "points" in m:
        clash = [f"medium.{k}" for k in ("scatterer_x", "scatterer_z") if k in m]
        clash += ["grid.z_offset"] if "z_offset" in scene.section("grid") else []
        if clash:
            raise ParameterError(f"medium.points and {', '.join(clash)} are exclusive: medium.points places "
                                 "each point's grid itself")
        for i, (x, z) in enumerate(scene.points()):
            if not -1 <= x <= 1:
                raise ParameterError(f"medium.points[{i}].x = {m['points'][i][0]!r} is {x:.4g} m; allowed: [-1, 1] m")
            if not 0 < z <= 2:
                raise ParameterError(f"medium.points[{i}].z = {m['points'][i][1]!r} is {z:.4g} m; allowed: (0, 2] m")
        if scene.needs_data and len(m["points"]) > 1:
            raise ParameterError("end-to-end scenes (weights.L_conv or weights.L_rec > 0) take one field point; "
                                 f"medium.points has {len(m['points'])}")
    else:
        for key, lo, hi, lo_open in (("scatterer_x", -1, 1, False), ("scatterer_z", 0, 2, True)):
            v = scene.length("medium", key)
            if v is not None:
                check_number(f"medium.{key} (m)", v, lo=lo, hi=hi, lo_open=lo_open)
    d = scene.section("data")
    if d and d.get("depth_max", 0.15) <= d.get("depth_min", 0.0):
        raise ParameterError("data.depth_max must be > data.depth_min")
    return scene

