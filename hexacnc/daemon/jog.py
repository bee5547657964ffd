"""Jogging: one axis at a time, jerk-limited, stopping at the first limit on its way.

A jog moves along a curve ``pose(s)`` of the platform pose from where the machine stands:

* Cartesian axis ``x y z`` (``s`` in mm) along the axis of the ``base``, ``tool`` (the platform's
  axes) or ``work`` frame (work offsets shift the origin only: its axes are the base axes);
* Cartesian axis ``a b c`` (``s`` in degrees): a rotation about that axis through the pivot point
  (default the tool tip; ``[workspace] pivot_mm`` or the ``pivot`` op, platform frame);
* strut ``1``..``6`` (``s`` in mm): along the pose direction that changes that strut alone (to
  first order: the other struts change by O(s^2), e.g. ~1e-5 mm for a 0.1 mm step).

:func:`plan_jog` finds the range of ``s`` within every limit (strut length, joint angle and, for
Cartesian jogs, the tool tip's ``[workspace]`` soft limits: scanned in steps then bisected), and
the speed, acceleration and jerk along ``s`` that keep every strut within ``[jog]
acceleration_scale`` of its limits (first order).  :class:`JogSource` is a feeder source: a
Ruckig trajectory (offline, position interface) to the target - the increment, or for a
continuous jog the limit itself, so a continuous jog comes to rest exactly at the limit - and on
``stop`` a jerk-limited velocity-interface stop from the state reached.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from ruckig import ControlInterface, InputParameter, Result, Ruckig, Trajectory

from ..errors import HexacncError
from ..config.operator import tip_box
from ..pose import euler_from_matrix, matrix_from_axis_angle, matrix_from_euler
from ..setpoint import COL_FLAGS, FLAG_END, FLAG_MOTION, ROW

CARTESIAN = ("x", "y", "z", "a", "b", "c")
STRUTS = ("1", "2", "3", "4", "5", "6")
FRAMES = ("base", "tool", "work")
#: limit search: step (mm or deg), longest reach, bisection tolerance and margin kept from a limit
SCAN_STEP = (0.5, 0.05)
SCAN_REACH = (2000.0, 90.0)
BISECT_TOL = 1e-5
LIMIT_MARGIN = (0.005, 0.0005)




class JogLimitError(HexacncError):
    """An incremental jog would cross a limit (``code`` = "limit")."""
    code = "limit"


@dataclass
class JogPlan:
    axis: str
    frame: str
    unit: str                   #: "mm" or "deg"
    pose_of: object             #: s array -> (n, 6) platform poses, mm/deg
    s_lo: float                 #: reachable range of s within every limit
    s_hi: float
    why_lo: str                 #: the limit that bounds each side
    why_hi: str
    v: float                    #: speed, acceleration, jerk along s
    a: float
    j: float


def tool_point_platform(cfg, tool_length_mm: float) -> np.ndarray:
    """The tool tip in the platform frame (reference point + tool length along the tool axis)."""
    return (np.asarray(cfg.tool.tip_platform_mm, dtype=float)
            + float(tool_length_mm) * np.asarray(cfg.tool.axis_platform, dtype=float))


def tip_poses(cfg, poses_deg: np.ndarray, tool_length_mm: float) -> np.ndarray:
    """Tool tip poses (machine frame, mm/deg) of platform poses (n, 6) mm/deg."""
    tp = tool_point_platform(cfg, tool_length_mm)
    out = np.array(poses_deg, dtype=float, copy=True)
    for k in range(len(out)):
        R = matrix_from_euler(*np.radians(out[k, 3:6]))
        out[k, :3] = out[k, :3] + R @ tp
    return out


def _curve(cfg, hx, start_deg: np.ndarray, axis: str, frame: str, pivot_platform: np.ndarray):
    X0 = np.asarray(start_deg, dtype=float)
    R0 = matrix_from_euler(*np.radians(X0[3:6]))
    if axis in STRUTS:
        i = int(axis) - 1
        J = hx.jacobian(X0)                          # dL = J dX (angles rad)
        d = np.linalg.solve(J, np.eye(6)[i])
        d[3:] = np.degrees(d[3:])

        def pose_of(s):
            s = np.atleast_1d(np.asarray(s, dtype=float))
            return X0[None, :] + s[:, None] * d[None, :]
        return pose_of, "mm"
    k = CARTESIAN.index(axis)
    e = np.eye(3)[k % 3]
    u = R0 @ e if frame == "tool" else e
    if k < 3:
        def pose_of(s):
            s = np.atleast_1d(np.asarray(s, dtype=float))
            out = np.repeat(X0[None, :], len(s), axis=0)
            out[:, :3] += s[:, None] * u[None, :]
            return out
        return pose_of, "mm"
    p = X0[:3] + R0 @ np.asarray(pivot_platform, dtype=float)

    def pose_of(s):
        s = np.atleast_1d(np.asarray(s, dtype=float))
        out = np.empty((len(s), 6))
        prev = X0[3:6].copy()
        for n, sv in enumerate(s):
            Q = matrix_from_axis_angle(u, math.radians(float(sv)))
            R = Q @ R0
            out[n, :3] = p + Q @ (X0[:3] - p)
            abc = np.degrees(euler_from_matrix(R))
            abc = prev + (abc - prev + 180.0) % 360.0 - 180.0      # continuous with the start
            out[n, 3:6] = abc
            prev = abc
        return out
    return pose_of, "deg"


def _violation(cfg, hx, poses: np.ndarray, tip_len: float | None, box) -> list[str]:
    """Per pose: "" when within limits, else the first limit broken (text)."""
    bad = hx.batch_violations(poses)
    out = []
    tips = tip_poses(cfg, poses, tip_len) if tip_len is not None else None
    lo, hi = box
    for n in range(len(poses)):
        if bad[n]:
            v = hx.limit_violations(poses[n])
            out.append(v[0] if v else "strut or joint limit")
            continue
        if tips is not None:
            t = tips[n]
            for i in range(6):
                if t[i] < lo[i] - 1e-9 or t[i] > hi[i] + 1e-9:
                    out.append(f"tool tip {'xyzabc'[i]} soft limit [{lo[i]:g}, {hi[i]:g}] ([workspace])")
                    break
            else:
                out.append("")
        else:
            out.append("")
    return out


def _reach(cfg, hx, pose_of, sign: float, unit: str, tip_len, box) -> tuple[float, str]:
    """Largest |s| in direction ``sign`` with every pose on the way within limits, and the limit."""
    step, reach = (SCAN_STEP[0], SCAN_REACH[0]) if unit == "mm" else (SCAN_STEP[1], SCAN_REACH[1])
    margin = LIMIT_MARGIN[0] if unit == "mm" else LIMIT_MARGIN[1]
    chunk = 256
    s_ok = 0.0
    start = 0
    nsteps = int(reach / step)
    while start < nsteps:
        ss = sign * step * np.arange(start + 1, min(nsteps, start + chunk) + 1)
        why = _violation(cfg, hx, pose_of(ss), tip_len, box)
        for n, w in enumerate(why):
            if w:
                lo, hi = s_ok, float(abs(ss[n]))
                while hi - lo > BISECT_TOL:
                    mid = 0.5 * (lo + hi)
                    if _violation(cfg, hx, pose_of([sign * mid]), tip_len, box)[0]:
                        hi = mid
                    else:
                        lo = mid
                return max(0.0, lo - margin), w
            s_ok = float(abs(ss[n]))
        start += chunk
    return s_ok, f"jog reach {reach:g} {unit}"


def plan_jog(cfg, hx, start_deg, axis: str, frame: str, pivot_platform, tool_length_mm: float,
             speed_scale: float = 1.0) -> JogPlan:
    """The curve, reachable range and dynamic limits of a jog of ``axis`` from ``start_deg``."""
    axis = str(axis).lower()
    if axis not in CARTESIAN + STRUTS:
        raise HexacncError(f"jog: unknown axis {axis!r} (x y z a b c, or strut 1..6)")
    if frame not in FRAMES:
        raise HexacncError(f"jog: unknown frame {frame!r} ({', '.join(FRAMES)})")
    X0 = np.asarray(start_deg, dtype=float)
    pose_of, unit = _curve(cfg, hx, X0, axis, frame, pivot_platform)
    tip_len = None if axis in STRUTS else float(tool_length_mm)
    box = tip_box(cfg)
    s_hi, why_hi = _reach(cfg, hx, pose_of, 1.0, unit, tip_len, box)
    s_lo, why_lo = _reach(cfg, hx, pose_of, -1.0, unit, tip_len, box)
    # strut rates per unit of s (first order, over the first step)
    h = 1e-3
    L = hx.inverse_batch(pose_of([0.0, h]))
    g = max(1e-9, float(np.max(np.abs(L[1] - L[0]))) / h)
    jc = cfg.operator.jog
    v_nom = jc.strut_speed_mm_s if axis in STRUTS else (jc.speed_mm_s if unit == "mm" else jc.speed_deg_s)
    v = min(v_nom * min(1.0, max(0.01, speed_scale)), 0.5 * float(np.min(cfg.max_velocity_mm_s)) / g)
    a = jc.acceleration_scale * float(np.min(cfg.max_acceleration_mm_s2)) / g
    j = jc.acceleration_scale * float(np.min(cfg.max_jerk_mm_s3)) / g
    return JogPlan(axis, frame, unit, pose_of, -s_lo, s_hi, why_lo, why_hi, v, a, j)


class JogSource:
    """Feeder source of one jog (see module doc); ``stop()`` is jerk-limited."""

    def __init__(self, plan: JogPlan, target: float, period_s: float, name: str = "jog"):
        self.plan = plan
        self.name = name
        self.period_s = float(period_s)
        self.target = float(target)
        self.finished = False
        self.stopping = False
        self.paused = False
        self.t = 0.0
        self._traj = self._trajectory(0.0, 0.0, 0.0, False)
        self._last = None

    # -- trajectories ------------------------------------------------------------------------
    def _trajectory(self, s: float, v: float, a: float, stop: bool) -> Trajectory:
        p = self.plan
        inp = InputParameter(1)
        inp.current_position = [s]
        inp.current_velocity = [v]
        inp.current_acceleration = [a]
        inp.max_velocity = [max(p.v, abs(v))]
        inp.max_acceleration = [max(p.a, abs(a))]
        inp.max_jerk = [p.j]
        if stop:
            inp.control_interface = ControlInterface.Velocity
            inp.target_velocity = [0.0]
        else:
            inp.target_position = [self.target]
        inp.target_acceleration = [0.0]
        traj = Trajectory(1)
        res = Ruckig(1).calculate(inp, traj)           # offline: never the 3rd (cloud) argument
        if res not in (Result.Working, Result.Finished):
            raise HexacncError(f"jog: no trajectory from s={s:g} v={v:g} a={a:g} ({res})")
        return traj

    @property
    def duration_s(self) -> float:
        return float(self._traj.duration)

    # -- control (feeder / Daemon._command interface) ------------------------------------------
    def stop(self) -> None:
        if self.stopping or self.finished:
            return
        pos, vel, acc = self._traj.at_time(min(self.t, self._traj.duration))
        self.stopping = True
        self._traj = self._trajectory(pos[0], vel[0], acc[0], True)
        self.t = 0.0

    pause = stop

    def resume(self) -> None:
        pass

    def set_feed_override(self, f: float) -> None:       # jogs keep their speed
        pass

    def snapshot(self) -> tuple:
        return (self._traj, self.t, self.stopping, self.finished, self._last)

    def restore(self, snap: tuple) -> None:
        self._traj, self.t, self.stopping, self.finished, self._last = snap

    def progress(self) -> tuple[int, float, float]:
        d = max(self._traj.duration, 1e-9)
        return 0, 100.0 * min(1.0, self.t / d), max(0.0, d - self.t)

    @property
    def position(self) -> float:
        """s of the next row (mm or deg)."""
        return float(self._traj.at_time(min(self.t, self._traj.duration))[0][0])

    # -- rows ------------------------------------------------------------------------------
    def next_rows(self, count: int) -> np.ndarray:
        if self.finished:
            return np.empty((0, ROW))
        dur = self._traj.duration
        ts = self.t + self.period_s * np.arange(1, count + 1)
        n = count
        end = ts >= dur
        if end.any():
            n = int(np.argmax(end)) + 1
            ts = ts[:n]
            ts[-1] = dur
        s = np.array([self._traj.at_time(float(t))[0][0] for t in ts])
        X = self.plan.pose_of(s)
        rows = np.zeros((n, ROW))
        rows[:, :3] = X[:, :3]
        rows[:, 3:6] = np.radians(X[:, 3:6])
        rows[:, COL_FLAGS] = float(FLAG_MOTION)
        self.t = float(ts[-1])
        if self.t >= dur:
            rows[-1, COL_FLAGS] = float(FLAG_END)
            self.finished = True
        self._last = rows[-1].copy()
        return rows
