"""Test programs for the simulator: a synthetic NC program and its time-parameterised strut commands.

:func:`synthetic_program` writes a milling-like program of ``n_lines`` linear
moves (G0/G1 with X Y Z A B C F words, platform coordinates around the home
pose): z-level raster passes at varying feeds, tilted 5-axis passes and rapids
between them, every pose inside the workspace and the strut/joint limits.

:func:`trajectory` time-parameterises a move list the way a simple exact-stop
controller does (trapezoidal path velocity per move: path acceleration limit,
feed, angular-rate limit, strut velocity limit), sampled every ``dt_s``; it
returns platform poses and strut lengths.  It is the simulator's own stand-in
for the look-ahead planner (no blending, stops at every corner: its strut
speeds are a conservative, jerk-free profile of the same program).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import DataError
from ..kinematics import Hexapod


@dataclass
class Move:
    """One program line: target platform pose (mm/deg), feed (mm/s), rapid flag, line number."""
    target: np.ndarray
    feed_mm_s: float
    rapid: bool
    line: int


@dataclass
class Trajectory:
    """Sampled motion: ``t_s`` (N,), ``poses`` (N,6) mm/deg, ``lengths_mm`` (N,6), ``line`` (N,)."""
    t_s: np.ndarray
    poses: np.ndarray
    lengths_mm: np.ndarray
    line: np.ndarray
    dt_s: float

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1]) if len(self.t_s) else 0.0

    def strut_speeds_mm_s(self) -> np.ndarray:
        """(N,6) strut speeds by central differences."""
        return np.gradient(self.lengths_mm, self.dt_s, axis=0)


def synthetic_program(cfg, n_lines: int = 1000, seed: int = 1) -> list[Move]:
    """A reachable milling-like program of ``n_lines`` linear moves (see module docstring)."""
    if n_lines < 2:
        raise DataError(f"a program needs at least 2 lines, got {n_lines}")
    hx = Hexapod(cfg)
    rng = np.random.default_rng(seed)
    home = np.asarray(cfg.home_pose, dtype=float)
    lo = np.asarray(cfg.workspace_min, dtype=float)
    hi = np.asarray(cfg.workspace_max, dtype=float)
    span = 0.6 * (hi - lo) / 2.0          # stay in the inner 60 % of the workspace box
    centre = home
    moves: list[Move] = []
    feeds = np.array([15.0, 25.0, 40.0, 60.0, 90.0, 130.0])     # mm/s (900 .. 7800 mm/min)
    rapid_feed = cfg.planner.rapid_feed_mm_min / 60.0
    cur = home.copy()
    line = 0

    def ok(p):
        return not hx.batch_violations(p[None])[0]

    while len(moves) < n_lines:
        # a pass: pick a tilt, a z level, a raster direction, a feed
        tilt = np.zeros(3)
        if rng.random() < 0.5:
            tilt = rng.uniform(-1, 1, 3) * span[3:] * np.array([1.0, 1.0, 0.5])
        z = centre[2] + rng.uniform(-1, 1) * span[2]
        feed = float(rng.choice(feeds))
        ang = rng.uniform(0, math.pi)
        d = np.array([math.cos(ang), math.sin(ang)])
        n = np.array([-d[1], d[0]])
        width = rng.uniform(0.4, 1.0) * span[0]
        step = rng.uniform(4.0, 12.0)
        rows = int(rng.integers(6, 20))
        start = centre[:2] - d * width - n * step * rows / 2
        first = np.concatenate([start, [z], tilt])
        if not ok(first):
            continue
        line += 1
        moves.append(Move(first, rapid_feed, True, line))
        cur = first
        for r in range(rows):
            if len(moves) >= n_lines:
                break
            sgn = 1.0 if r % 2 == 0 else -1.0
            p = cur.copy()
            p[:2] = cur[:2] + sgn * d * 2 * width
            p2 = p.copy()
            p2[:2] = p[:2] + n * step
            for q in (p, p2):
                if len(moves) >= n_lines or not ok(q):
                    break
                line += 1
                moves.append(Move(q, feed, False, line))
                cur = q
    return moves[:n_lines]


def to_gcode(moves: list[Move]) -> str:
    """The move list as G-code text (platform coordinates, G21 G90 G94, feed in mm/min)."""
    out = ["G21 G90 G94 G61"]
    for m in moves:
        x, y, z, a, b, c = m.target
        w = f"X{x:.4f} Y{y:.4f} Z{z:.4f} A{a:.4f} B{b:.4f} C{c:.4f}"
        out.append(f"G0 {w}" if m.rapid else f"G1 {w} F{m.feed_mm_s * 60.0:.1f}")
    out.append("M2")
    return "\n".join(out) + "\n"


def trajectory(cfg, moves: list[Move], dt_s: float = 0.002, start=None,
               path_accel_mm_s2: float = 2000.0) -> Trajectory:
    """Exact-stop trapezoidal time parameterisation of ``moves`` sampled every ``dt_s``.

    Orientation is interpolated linearly in a, b, c (small tilts); the path
    length counts 1 degree as ``char_length * pi/180`` mm; each move's speed and
    acceleration are capped so that no strut exceeds ``max_velocity_mm_s`` or
    ``max_acceleration_mm_s2`` (secant estimate) and the angular rate stays under
    ``[planner] max_angular_velocity_deg_s``.
    """
    if not (dt_s > 0 and math.isfinite(dt_s)):
        raise DataError(f"sample time must be positive, got {dt_s!r}")
    hx = Hexapod(cfg)
    cur = np.asarray(cfg.home_pose if start is None else start, dtype=float)
    rad_mm = hx.char_length_mm * math.pi / 180.0
    w_max = cfg.planner.max_angular_velocity_deg_s
    vstrut = float(np.min(cfg.max_velocity_mm_s))
    astrut = float(np.min(cfg.max_acceleration_mm_s2))
    segs = []          # (t0, T, ta, tc, v, a, s_len, start, delta, line)
    t0 = 0.0
    for m in moves:
        tgt = np.asarray(m.target, dtype=float)
        delta = tgt - cur
        lin = float(np.linalg.norm(delta[:3]))
        angd = float(np.linalg.norm(delta[3:]))
        s_len = math.hypot(lin, angd * rad_mm)
        if s_len < 1e-9:
            continue
        v = float(m.feed_mm_s)
        if angd > 0:
            v = min(v, w_max * s_len / angd)
        Ls = hx.inverse_batch(cur + np.outer([0.0, 1.0], delta))
        dLds = max(float(np.max(np.abs(Ls[1] - Ls[0]))) / s_len, 1e-3)
        a = min(path_accel_mm_s2, 0.8 * astrut / dLds)
        v = min(v, 0.9 * vstrut / dLds)
        ta = v / a
        if a * ta * ta > s_len:
            ta = math.sqrt(s_len / a)
            v = a * ta
            tc = 0.0
        else:
            tc = (s_len - a * ta * ta) / v
        T = 2 * ta + tc
        segs.append((t0, T, ta, tc, v, a, s_len, cur.copy(), delta, m.line))
        t0 += T
        cur = tgt
    if not segs:
        raise DataError("the program has no motion")
    N = int(math.floor(t0 / dt_s)) + 1
    t = np.arange(N) * dt_s
    poses = np.empty((N, 6))
    line = np.empty(N, dtype=np.int64)
    starts = np.array([sg[0] for sg in segs])
    bounds = np.searchsorted(t, np.append(starts[1:], np.inf), side="left")
    k0 = 0
    for k, (ts, T, ta, tc, v, a, s_len, p0, delta, ln) in enumerate(segs):
        k1 = int(bounds[k]) if k < len(segs) - 1 else N
        if k1 <= k0:
            continue
        tau = np.clip(t[k0:k1] - ts, 0.0, T)
        s = np.where(tau < ta, 0.5 * a * tau * tau,
                     np.where(tau < ta + tc, 0.5 * a * ta * ta + v * (tau - ta),
                              s_len - 0.5 * a * (T - tau) ** 2))
        poses[k0:k1] = p0 + np.outer(np.clip(s / s_len, 0.0, 1.0), delta)
        line[k0:k1] = ln
        k0 = k1
    return Trajectory(t_s=t, poses=poses, lengths_mm=hx.inverse_batch(poses), line=line, dt_s=dt_s)


def to_gcode_tooltip(cfg, moves: list[Move], blend: bool = True) -> str:
    """The move list as G-code for the interpreter: tool-tip coordinates in G54.

    G54 is the machine's default work offset (``[planner] work_offset_mm``, the
    home pose's angles as rotary origin); the tool tip is ``[tool]
    tip_platform_mm`` with no tool length (G49).
    """
    from ..pose import matrices_from_euler
    P = np.array([m.target for m in moves], dtype=float)
    R = matrices_from_euler(np.radians(P[:, 3:]))
    tip = P[:, :3] + R @ np.asarray(cfg.tool.tip_platform_mm, dtype=float)
    wo = np.concatenate([np.asarray(cfg.planner.work_offset_mm, dtype=float),
                         np.asarray(cfg.home_pose, dtype=float)[3:6]])
    out = ["G21 G90 G94 G49 G54 " + ("G64" if blend else "G61")]
    for m, t, p in zip(moves, tip, P):
        x, y, z = t - wo[:3]
        a, b, c = p[3:] - wo[3:]
        w = f"X{x:.4f} Y{y:.4f} Z{z:.4f} A{a:.4f} B{b:.4f} C{c:.4f}"
        out.append(f"G0 {w}" if m.rapid else f"G1 {w} F{m.feed_mm_s * 60.0:.1f}")
    out.append("M2")
    return "\n".join(out) + "\n"


def planned_trajectory(cfg, gcode_text: str, name: str = "program", dt_s: float | None = None) -> Trajectory:
    """Interpret ``gcode_text`` (hexacnc.gcode) and plan it (hexacnc.planner, look-ahead, jerk-limited)."""
    from ..gcode import program_from_config
    from ..planner import plan_program
    dt = float(cfg.cycle.period_s if dt_s is None else dt_s)
    prog = program_from_config(gcode_text, name, cfg)
    plan = plan_program(prog.blocks, cfg, period_s=dt)
    rows = plan.rows()
    poses = rows[:, :6].copy()
    poses[:, 3:] = np.degrees(poses[:, 3:])
    hx = Hexapod(cfg)
    return Trajectory(t_s=np.arange(len(rows)) * dt, poses=poses, lengths_mm=hx.inverse_batch(poses),
                      line=rows[:, 6].astype(np.int64), dt_s=dt)


def program_trajectory(cfg, moves: list[Move], dt_s: float, source: str = "auto") -> tuple[Trajectory, str]:
    """Strut commands of ``moves`` from the look-ahead planner (``source`` "planner" or "auto") or the exact-stop profile ("exact-stop"); returns the trajectory and a description."""
    if source not in ("auto", "planner", "exact-stop"):
        raise DataError(f"unknown trajectory source {source!r} (auto, planner, exact-stop)")
    if source in ("planner", "auto"):
        tr = planned_trajectory(cfg, to_gcode_tooltip(cfg, moves), "synthetic", dt_s)
        return tr, (f"synthetic {len(moves)}-line program (hexacnc.sim.program) through the G-code interpreter "
                    f"and the look-ahead planner (G64 blending, jerk-limited), {tr.duration_s:.1f} s")
    tr = trajectory(cfg, moves, dt_s=dt_s)
    return tr, (f"synthetic {len(moves)}-line program (hexacnc.sim.program), exact-stop trapezoid profile, "
                f"{tr.duration_s:.1f} s")
