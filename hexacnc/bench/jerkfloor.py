"""Rest-to-rest jerk floor for ``hexacnc bench plan``: a lower bound on the duration of every jerk-limited
plan that rests where hexacnc's plan rests (Ruckig 1-DOF times per strut and rest-to-rest section, offline),
and its bang-bang (``j_max`` infinite) counterpart; the report block ``jerk_floor``."""
from __future__ import annotations

import math

import numpy as np

from ..errors import HexacncError


def _rest_points(plan) -> list:
    """Path positions (mm) where hexacnc's plan is at rest: programmed stops, stopping events, both ends."""
    path = plan.path
    rest = {float(v) for v in np.asarray(plan.grid_s)[np.asarray(plan.grid_x) <= 0.0]}
    return sorted({0.0, path.total} | {float(path.s0[m] + path.slen[m]) for m in path.stops_after} | rest)


def _sections(stops) -> list:
    return [(a, b) for a, b in zip(stops[:-1], stops[1:]) if b - a >= 1e-9]


def rest_to_rest_time(d_mm: float, v_max: float, a_max: float, j_max: float) -> float:
    """Minimum time (s) of any 1-DOF profile moving ``|d_mm|`` from rest to rest under
    ``|v| <= v_max``, ``|a| <= a_max``, ``|j| <= j_max``: Ruckig's time-optimal duration
    (offline ``calculate``; constructed with one argument, never the cloud ``max_waypoints``).
    ``j_max = inf``: the closed-form bang-bang time (:func:`double_s_time`)."""
    d = abs(float(d_mm))
    if d == 0.0:
        return 0.0
    if not math.isfinite(j_max):
        return double_s_time(d, v_max, a_max, j_max)
    from ruckig import InputParameter, Result, Ruckig, Trajectory
    otg = Ruckig(1)
    inp = InputParameter(1)
    inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [0.0], [0.0]
    inp.target_position, inp.target_velocity, inp.target_acceleration = [d], [0.0], [0.0]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [float(v_max)], [float(a_max)], [float(j_max)]
    traj = Trajectory(1)
    res = otg.calculate(inp, traj)
    if res not in (Result.Working, Result.Finished):
        raise HexacncError(f"Ruckig could not time a rest-to-rest move of {d} mm: {res}")
    return float(traj.duration)


def double_s_time(d_mm: float, v_max: float, a_max: float, j_max: float) -> float:
    """Closed-form minimum rest-to-rest time (s) over ``|d_mm|`` under v/a/j limits (``j_max`` may be inf)."""
    d, v, a, j = abs(float(d_mm)), float(v_max), float(a_max), float(j_max)
    if d == 0.0:
        return 0.0
    if not math.isfinite(j):
        return d / v + v / a if d >= v * v / a else 2.0 * math.sqrt(d / a)
    from ..planner.scurve import move_time
    return float(move_time(d, v, a, j))


def jerk_floor(plan, cfg, stops=None, max_moves: int = 20) -> dict:
    """A lower bound on the duration of every jerk-limited plan that rests where this plan rests.

    Per rest-to-rest section and strut i the strut must move by the net ``|dL_i|`` from rest to rest
    under its v/a/j limits: at least :func:`rest_to_rest_time`; the section takes at least the
    maximum over struts; the sum over sections bounds the whole path (stop holds and dwells not
    counted).  The same with ``j_max = inf`` bounds every plan under v/a limits only (TOPP-RA's problem).
    """
    from ..planner import path as P
    path, hx = plan.path, plan.hexapod
    stops = _rest_points(plan) if stops is None else stops
    vmax = np.asarray(cfg.max_velocity_mm_s, dtype=float)
    amax = np.asarray(cfg.max_acceleration_mm_s2, dtype=float)
    jmax = np.asarray(cfg.max_jerk_mm_s3, dtype=float)
    secs = _sections(stops)
    if not secs:
        return {"jerk_floor_s": 0.0, "bang_bang_floor_s": 0.0, "rest_to_rest_sections": 0}
    ends = np.array(secs, dtype=float)
    sa, sb = ends[:, 0], ends[:, 1]
    La = P.strut_lengths(path.platform(path.piece_at(sa), sa), hx.plat, hx.base)
    Lb = P.strut_lengths(path.platform(path.piece_at(np.maximum(sb - 1e-9, sa)), sb), hx.plat, hx.base)
    dL = np.abs(Lb - La)
    moves = []
    fl = bb = 0.0
    for k in range(dL.shape[0]):
        tj = max(rest_to_rest_time(dL[k, i], vmax[i], amax[i], jmax[i]) for i in range(6))
        tb = max(double_s_time(dL[k, i], vmax[i], amax[i], math.inf) for i in range(6))
        fl += tj
        bb += tb
        moves.append({"s_from_mm": round(float(sa[k]), 4), "s_to_mm": round(float(sb[k]), 4),
                      "max_abs_dL_mm": round(float(dL[k].max()), 6), "jerk_floor_s": round(tj, 6),
                      "bang_bang_floor_s": round(tb, 6)})
    out = {"jerk_floor_s": fl, "bang_bang_floor_s": bb, "rest_to_rest_sections": len(moves)}
    if len(moves) <= max_moves:
        out["moves"] = moves
    return out


def _floor_report(fl: dict, toppra_s: float, hexacnc_s: float) -> dict:
    jf, bb = fl["jerk_floor_s"], fl["bang_bang_floor_s"]
    out = {"jerk_floor_s": round(jf, 6), "bang_bang_floor_s": round(bb, 6),
           "toppra_duration_s": round(toppra_s, 6), "hexacnc_duration_s": round(hexacnc_s, 6),
           "floor_over_toppra": round(jf / toppra_s, 6) if toppra_s > 0 else None,
           "hexacnc_over_floor": round(hexacnc_s / jf, 6) if jf > 0 else None,
           "bang_bang_floor_le_toppra": bool(bb <= toppra_s * (1 + 1e-9)),
           "floor_excludes_5_percent": bool(jf > 1.05 * toppra_s),
           "rest_to_rest_sections": fl["rest_to_rest_sections"],
           "note": "lower bound on every plan that rests where hexacnc's plan rests (programmed stops and "
                   "stopping events): per rest-to-rest section the max over struts of the minimum time to move "
                   "that strut by its net |dL| from rest to rest under |v|<=v_max, |a|<=a_max, |j|<=j_max "
                   "(Ruckig 1-DOF time-optimal, offline), summed over sections; stop holds and dwells not "
                   "counted. bang_bang_floor_s: the same with j_max infinite (closed form), a lower bound for "
                   "TOPP-RA's problem. floor_excludes_5_percent: jerk_floor_s > 1.05 x TOPP-RA, i.e. no "
                   "jerk-limited plan of this path can be within 5 % of TOPP-RA. Only net displacements are "
                   "used, so the bound is weak on sections with many moves between stops"}
    if "moves" in fl:
        out["moves"] = fl["moves"]
    return out
