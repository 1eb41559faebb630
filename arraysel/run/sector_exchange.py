"""The exchange polish: a selection's side lobes held down over the whole sector, not only on the
scene's points.

A polish on a fixed set of points lowers the side lobes those points see and moves side-lobe energy
to where no point looks (``docs/sector.md``, "Checked on points the scene does not have"). The
exchange method of semi-infinite minimax optimisation answers that by rounds:

1. **scan**: the selection's worst side lobe (``PSL_dB``, exact path) on ``scan`` points drawn at
   random in the sector (angles uniform within the sector's half-angles less ``edge_deg``, ranges
   uniform in ``ranges``), a fresh draw each round;
2. **exchange**: the ``add`` worst scanned points whose side lobe lies above the scene's own worst
   join the scene's points (a scan that finds none ends the rounds: the scene's worst bounds every
   scanned point);
3. **polish**: :func:`~arraysel.objective.sector_polish.polish_on_beams` on the enlarged set of
   points, from the selection, for ``seconds``, with the settings of the polish inside ``compare``
   and its width cap (``sector.polish_width_ratio`` x the fresh random median's mean width over the
   enlarged set).

Each added point needs its own fast model (built once and cached, about a minute and 1.2 GB of
cache on ``matrix-1024-sector``), and each makes a polish round dearer: the rounds trade time for
the points' coverage. The points a run adds are returned, so the enlarged scene can be reused.
"""
from __future__ import annotations

import gc
import time

import numpy as np

from arraysel.errors import ParameterError, check_number
from arraysel.scenes.keys import SCHEMA
from arraysel.scenes.load import load_scene

__all__ = ["random_sector_points", "scan_points", "exchange_polish", "MAX_POINTS"]

#: the most points a sector scene holds (the range of the ``sector.points`` key)
MAX_POINTS = int(SCHEMA["sector"]["points"].cons[1])


def _tree(scene, points) -> dict:
    """``scene``'s tree with ``points`` as its sector points (the cysts, a final check, left out)."""
    tree = scene.to_dict()
    tree.pop("cysts", None)
    tree["sector"] = {**tree["sector"], "points": [list(p) for p in points]}
    return tree


def random_sector_points(scene, n: int, rng: np.random.Generator, ranges=(20e-3, 110e-3),
                         edge_deg: float = 2.0) -> list[list]:
    """``n`` points ``[theta_x_deg, theta_y_deg, "R mm"]`` drawn at random in the sector of
    ``scene`` (a sector scene): angles uniform within its half-angles less ``edge_deg``, ranges
    (metres) uniform in ``ranges``; rounded to 0.1 degree and 0.1 mm."""
    sc = load_scene(scene)
    n = int(check_number("n", n, lo=1, hi=10000, integer=True))
    lo, hi = (check_number("ranges[0]", ranges[0], lo=1e-3, hi=1.0), check_number("ranges[1]", ranges[1], lo=1e-3, hi=1.0))
    if hi < lo:
        raise ParameterError(f"ranges = ({lo:g}, {hi:g}) m: the largest range must not be below the smallest")
    hx, hy = sc.sector_geometry()["half_angles"]
    edge = check_number("edge_deg", edge_deg, lo=0, hi=min(hx, hy), hi_open=True)
    ax = rng.uniform(-(hx - edge), hx - edge, n)
    ay = rng.uniform(-(hy - edge), hy - edge, n)
    r = rng.uniform(lo, hi, n)
    return [[round(float(a), 1), round(float(b), 1), f"{float(c) * 1e3:.1f} mm"] for a, b, c in zip(ax, ay, r)]


def scan_points(scene, mask, points, log=None) -> dict[str, np.ndarray]:
    """The exact per-beam metrics of a selection on ``points`` (the scene's surfaces and settings,
    these points instead of its own): ``{name: float64 (P,)}``, the names of
    :data:`~arraysel.objective.sector_beams.BEAM_COLUMNS`. ``mask``: one selection (Ne,) (boolean,
    or non-negative element weights: an apodized array), or a batch (B, Ne), then ``(B, P)``
    arrays, every selection scored on a point while its exact model is held. ``log``: a callable
    given one line per point."""
    from arraysel.objective.sector_objective import SectorObjective

    sc = load_scene(scene)
    w = np.asarray(mask)
    single = w.ndim == 1
    w = w.reshape(1, -1) if single else w
    if w.ndim != 2:
        raise ParameterError(f"mask must be (Ne,) or (B, Ne), got shape {np.asarray(mask).shape}")
    w = w.astype(bool) if w.dtype == bool else w.astype(np.float64)
    out: dict[str, list] = {}
    for lo in range(0, len(points), MAX_POINTS):        # a scene holds at most MAX_POINTS points
        part = points[lo:lo + MAX_POINTS]
        obj = SectorObjective(load_scene(_tree(sc, part)), fast=False)
        for i in range(len(part)):  # one point at a time: the exact path holds one point's model
            bm = obj.beam_metrics(w, points=[i], exact=True)
            obj.beams.exact.release(i)
            for k, v in bm.items():
                out.setdefault(k, []).append(v[:, 0].astype(np.float64))
            if log is not None:
                log(f"point {lo + i + 1}/{len(points)} {part[i]} scored")
    return {k: (np.stack(v, 1)[0] if single else np.stack(v, 1)) for k, v in out.items()}


def exchange_polish(scene, mask, *, rounds: int = 3, scan: int = 24, add: int = 2, seconds: float = 300.0,
                    seed: int = 0, ranges=(20e-3, 110e-3), edge_deg: float = 2.0, log=None) -> dict:
    """The exchange polish of ``mask`` (Ne,) bool on sector scene ``scene`` (module docstring).

    ``rounds`` [1, 50] of scan, exchange and polish; ``scan`` [1, 1000] points a round; ``add``
    [1, 16] of them at most added a round; ``seconds`` of polish a round; ``seed`` of the points
    (round ``r`` draws from ``default_rng([seed, r])``) and of the polish's moves; ``log``: a
    callable given one line per step.

    Returns ``{"mask", "points" (the scene's points and the added ones), "added", "history"}``:
    ``history`` one dict a round (``scene_worst_dB`` before it, ``scan_worst_dB``, the scanned
    points and their ``PSL_dB``, the added points, the polish's result less its mask, and the
    polished selection's ``elements``).
    """
    from arraysel.objective.sector_objective import SectorObjective
    from arraysel.objective.sector_polish import polish_on_beams
    from arraysel.run.sector_report import BEAM_POLISH_SETTINGS, BeamPolish

    sc = load_scene(scene)
    if not sc.is_sector:
        raise ParameterError(f"scene {sc.name!r} has no [sector] section: it is not a sector scene")
    rounds = int(check_number("rounds", rounds, lo=1, hi=50, integer=True))
    scan = int(check_number("scan", scan, lo=1, hi=1000, integer=True))
    add = int(check_number("add", add, lo=1, hi=16, integer=True))
    seconds = check_number("seconds", seconds, lo=0)
    seed = int(check_number("seed", seed, lo=0, integer=True))
    m = np.asarray(mask, dtype=bool).reshape(-1).copy()
    say = log or (lambda _line: None)
    points = [list(p) for p in sc.get("sector", "points")]
    if len(points) + rounds * add > MAX_POINTS:
        raise ParameterError(f"rounds x add = {rounds} x {add}: with the scene's {len(points)} points that may make "
                             f"{len(points) + rounds * add}, more than the {MAX_POINTS} a sector scene holds; allowed: "
                             f"rounds x add <= {MAX_POINTS - len(points)}")
    added: list[list] = []
    history = []
    ratio = float(sc.value("sector", "polish_width_ratio"))

    def objective_on(pts):
        """The objective on ``pts``, its points' fast models (cached) and the cap over all of them."""
        gc.collect()            # the previous objective's models unmapped before the next are built
        o = SectorObjective(load_scene(_tree(sc, pts)))
        p = BeamPolish(1.0, ratio)
        p.prepare(o)
        return o, p

    obj, plan = objective_on(points)    # kept from round to round: the polished set is the next scene
    for r in range(rounds):
        t0 = time.perf_counter()
        cand = random_sector_points(sc, scan, np.random.default_rng([seed, r]), ranges, edge_deg)
        psl = scan_points(sc, m, cand)["PSL_dB"]
        _, summ = obj.beam_loss(m[None], plan.cap)
        worst = float(summ["worst_PSL_dB"][0])
        order = [int(j) for j in np.argsort(-psl) if psl[j] > worst][:add]
        step = {"round": r, "scene_points": len(points), "scene_worst_dB": worst, "scan": cand,
                "scan_PSL_dB": psl.tolist(), "scan_worst_dB": float(psl.max()), "added": [cand[j] for j in order],
                "scan_seconds": time.perf_counter() - t0}
        say(f"round {r}: scene's worst {worst:.2f} dB on {len(points)} points; scan of {scan}: worst "
            f"{psl.max():.2f} dB at {cand[int(np.argmax(psl))]}, {int((psl > worst).sum())} above the scene's")
        if not order:
            history.append(step)
            say(f"round {r}: no scanned point above the scene's worst: done")
            break
        points += [cand[j] for j in order]
        added += [cand[j] for j in order]
        del obj
        obj, plan = objective_on(points)
        res = polish_on_beams(obj, m, width_cap=plan.cap, seconds=seconds, seed=seed + r, **BEAM_POLISH_SETTINGS)
        m = np.asarray(res["mask"], dtype=bool)
        step["polish"] = {k: v for k, v in res.items() if k != "mask"}
        step["elements"] = [int(e) for e in np.flatnonzero(m)]
        step["width_cap_m"] = plan.cap
        history.append(step)
        say(f"round {r}: added {[cand[j] for j in order]}; polish {res['start_loss']:.2f} -> {res['loss']:.2f} "
            f"(worst {res['worst_PSL_dB']:.2f} dB on {len(points)} points, mean width "
            f"{res['mean_width_m'] * 1e3:.3f} mm, {res['rounds']} rounds, {res['accepted']} moves, "
            f"{res['seconds']:.0f} s)")
    return {"mask": m, "points": points, "added": added, "history": history}
