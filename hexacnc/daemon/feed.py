"""Setpoint sources for the hot loop's ring (supervisor side, numpy allowed).

A source yields chunks of rows ``[x, y, z, a, b, c (rad), line, flags]`` (platform
pose, one row per cycle) and supports ``pause()``, ``resume()``,
``set_feed_override(f)`` and ``stop()``; the last row it yields carries
``FLAG_END`` and is at rest.

* :func:`point_to_point` - straight line in pose space with a jerk-limited
  (Ruckig, one DOF on the path parameter) profile whose limits come from the
  strut-length derivatives along the line, using half of each strut's
  acceleration and jerk budget so that a pause or override ramp fits in the rest.
* :class:`ArraySource` - plays precomputed rows with a time warp: the playback
  rate follows its target (1 x override, or 0 for pause/stop) by a jerk-limited
  profile, so pausing decelerates *along the path*.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import KinematicsError, PlanError
from ..kinematics import Hexapod
from .shm import FLAG_END, ROW
from .stopgen import stop_accel

#: share of the strut acceleration/jerk limits a point-to-point profile may use
P2P_SHARE = 0.5


def _strut_derivatives(hx: Hexapod, p0: np.ndarray, p1: np.ndarray, n: int = 400):
    """Max |dL/ds|, |d2L/ds2|, |d3L/ds3| per strut along the straight line p0 -> p1 (deg poses)."""
    s = np.linspace(0.0, 1.0, n + 1)
    poses = p0[None, :] + s[:, None] * (p1 - p0)[None, :]
    L = hx.inverse_batch(poses)
    h = 1.0 / n
    d1 = np.abs(np.diff(L, axis=0)) / h
    d2 = np.abs(np.diff(L, 2, axis=0)) / h ** 2
    d3 = np.abs(np.diff(L, 3, axis=0)) / h ** 3
    return d1.max(axis=0), d2.max(axis=0), d3.max(axis=0), poses


def point_to_point(cfg, hx: Hexapod, start_rad, target_deg, feed_mm_s: float, period_s: float,
                   line: int = 0) -> np.ndarray:
    """Rows (N, 8) from ``start_rad`` (platform pose, mm/rad) to ``target_deg`` (mm/deg).

    Raises :class:`KinematicsError` if the target or the line breaks a strut-length or joint
    limit, :class:`PlanError` if the profile's samples do not satisfy the strut limits.
    """
    t = np.asarray(target_deg, dtype=float)
    if t.shape != (6,) or not np.all(np.isfinite(t)):
        raise KinematicsError(f"move_to: target pose {list(target_deg)!r} is not 6 finite numbers")
    if not (math.isfinite(feed_mm_s) and feed_mm_s > 0):
        raise PlanError(f"move_to: feed {feed_mm_s!r} mm/s must be a positive number", limit="feed")
    s0 = np.asarray(start_rad, dtype=float)
    p0 = np.concatenate([s0[:3], np.degrees(s0[3:])])
    hx.check_pose(t)
    d1, d2, d3, poses = _strut_derivatives(hx, p0, t)
    bad = hx.batch_violations(poses)
    if bad.any():
        k = int(np.argmax(bad))
        raise KinematicsError(f"move_to: the straight line leaves the limits at {100.0 * k / (len(poses) - 1):.1f} % "
                              f"of the way: " + "; ".join(hx.limit_violations(poses[k])))
    dist = float(np.linalg.norm(t[:3] - p0[:3]))
    ang = float(np.max(np.abs(t[3:] - p0[3:])))
    if dist < 1e-9 and ang < 1e-9:
        row = np.zeros((1, ROW))
        row[0, :6] = s0
        row[0, 6] = line
        row[0, 7] = FLAG_END
        return row
    vmax = np.asarray(cfg.max_velocity_mm_s, float)
    amax = np.asarray(cfg.max_acceleration_mm_s2, float) * P2P_SHARE
    jmax = np.asarray(cfg.max_jerk_mm_s3, float) * P2P_SHARE
    eps = 1e-12
    sd = math.inf
    if dist > 0:
        sd = feed_mm_s / dist
    if ang > 0:
        sd = min(sd, cfg.planner.max_angular_velocity_deg_s / ang)
    sd = min(sd, float(np.min(0.9 * vmax / (d1 + eps))))
    sd = min(sd, float(np.min(np.sqrt(0.5 * amax / (d2 + eps)))))
    sd = min(sd, float(np.min(np.cbrt(0.3 * jmax / (d3 + eps)))))
    sdd = float(np.min((amax - d2 * sd * sd) / (d1 + eps)))
    sdd = min(sdd, float(np.min(np.sqrt(0.3 * jmax / (3.0 * d2 * sd + eps)))))
    sddd = float(np.min((jmax - d3 * sd ** 3 - 3.0 * d2 * sd * sdd) / (d1 + eps)))
    if not (sd > 0 and sdd > 0 and sddd > 0):
        raise PlanError("move_to: no feasible profile within the strut limits", limit="strut")
    from ruckig import InputParameter, Ruckig, Trajectory  # never the third argument (cloud)
    inp = InputParameter(1)
    inp.current_position = [0.0]
    inp.current_velocity = [0.0]
    inp.current_acceleration = [0.0]
    inp.target_position = [1.0]
    inp.target_velocity = [0.0]
    inp.target_acceleration = [0.0]
    inp.max_velocity = [sd]
    inp.max_acceleration = [sdd]
    inp.max_jerk = [sddd]
    otg = Ruckig(1)
    tr = Trajectory(1)
    otg.calculate(inp, tr)
    n = int(math.ceil(tr.duration / period_s))
    s = np.empty(n + 1)
    for k in range(n + 1):
        s[k] = tr.at_time(min(k * period_s, tr.duration))[0][0]
    s[-1] = 1.0
    rows = np.zeros((n + 1, ROW))
    rows[:, :3] = s0[None, :3] + s[:, None] * (t[:3] - p0[:3])[None, :]
    rows[:, 3:6] = s0[None, 3:] + s[:, None] * np.radians(t[3:] - p0[3:])[None, :]
    rows[:, 6] = line
    rows[-1, 7] = FLAG_END
    check_rows(cfg, hx, rows, period_s)
    return rows


def check_rows(cfg, hx: Hexapod, rows: np.ndarray, period_s: float, margin: float = 1.0) -> None:
    """Strut lengths, joints, velocity and acceleration of consecutive rows within the limits."""
    poses = np.concatenate([rows[:, :3], np.degrees(rows[:, 3:6])], axis=1)
    bad = hx.batch_violations(poses)
    if bad.any():
        k = int(np.argmax(bad))
        raise KinematicsError(f"row {k}: " + "; ".join(hx.limit_violations(poses[k])))
    L = hx.inverse_batch(poses)
    if len(L) >= 2:
        v = np.abs(np.diff(L, axis=0)) / period_s
        over = v > np.asarray(cfg.max_velocity_mm_s) * margin
        if over.any():
            k, i = np.argwhere(over)[0]
            raise PlanError(f"strut {i + 1} velocity {v[k, i]:.1f} mm/s over max_velocity_mm_s", limit="velocity")
    if len(L) >= 3:
        a = np.abs(np.diff(L, 2, axis=0)) / period_s ** 2
        over = a > np.asarray(cfg.max_acceleration_mm_s2) * margin
        if over.any():
            k, i = np.argwhere(over)[0]
            raise PlanError(f"strut {i + 1} acceleration {a[k, i]:.0f} mm/s^2 over max_acceleration_mm_s2",
                            limit="acceleration")


class ArraySource:
    """Plays rows (N, 8) with a jerk-limited playback rate (pause, resume, override, stop)."""

    def __init__(self, cfg, hx: Hexapod, rows: np.ndarray, period_s: float, name: str = "",
                 total_lines: int | None = None):
        self.rows = np.asarray(rows, dtype=float)
        self.n = len(self.rows)
        self.dt = period_s
        self.name = name
        self.total_lines = total_lines
        poses = np.concatenate([self.rows[:, :3], np.degrees(self.rows[:, 3:6])], axis=1)
        L = hx.inverse_batch(poses[:: max(1, self.n // 4000)]) if self.n > 1 else None
        step = max(1, self.n // 4000)
        vpk = 1e-9
        if L is not None and len(L) > 1:
            vpk = float(np.max(np.abs(np.diff(L, axis=0)) / (period_s * step)))
        amin = float(np.min(cfg.max_acceleration_mm_s2))
        jmin = float(np.min(cfg.max_jerk_mm_s3))
        # rate limits: the warp adds (strut speed at rate 1) x (rate derivative) to the strut acceleration
        self.rate_acc = min(50.0, 0.4 * amin / max(vpk, 1e-6))
        self.rate_jerk = min(5000.0, 0.4 * jmin / max(vpk, 1e-6))
        self.tau = 0.0              # playback position, rows
        self.rate = 1.0
        self.rate_d = 0.0
        self.override = 1.0
        self.paused = False
        self.stopping = False
        self.finished = False
        self._out = np.zeros(ROW)

    # -- control -------------------------------------------------------------------------
    def pause(self) -> None:
        self.paused = True

    def resume(self) -> None:
        self.paused = False

    def set_feed_override(self, f: float) -> None:
        self.override = max(0.0, min(2.0, float(f)))

    def stop(self) -> None:
        self.stopping = True

    def snapshot(self) -> tuple:
        """State before the next row (see :meth:`Daemon._rewind`)."""
        return (self.tau, self.rate, self.rate_d, self.override, self.paused, self.stopping, self.finished)

    def restore(self, snap: tuple) -> None:
        (self.tau, self.rate, self.rate_d, self.override, self.paused, self.stopping, self.finished) = snap

    @property
    def target_rate(self) -> float:
        return 0.0 if (self.paused or self.stopping) else self.override

    @property
    def at_rest(self) -> bool:
        return self.rate == 0.0 and self.rate_d == 0.0

    def progress(self) -> tuple[int, float, float]:
        """(line, percent, time_left_s) at the playback position."""
        k = min(self.n - 1, int(self.tau))
        left = (self.n - 1 - self.tau) * self.dt / max(self.override, 1e-3)
        return int(self.rows[k, 6]), 100.0 * self.tau / max(1, self.n - 1), max(0.0, left)

    # -- rows ------------------------------------------------------------------------------
    def next_rows(self, count: int) -> np.ndarray:
        out = np.empty((count, ROW))
        m = 0
        dt = self.dt
        while m < count and not self.finished:
            # jerk-limited approach of the rate to its target (rate units: rows per cycle)
            tgt = self.target_rate
            ad = stop_accel(self.rate - tgt, self.rate_d, self.rate_jerk, self.rate_acc, dt)
            self.rate_d = ad
            self.rate += ad * dt
            if abs(self.rate - tgt) < 1e-9 and abs(ad) < self.rate_jerk * dt:
                self.rate = tgt
                self.rate_d = 0.0
            if self.rate < 0.0:
                self.rate = 0.0
            self.tau += self.rate
            last = self.n - 1
            if self.tau >= last:
                self.tau = last
                out[m] = self.rows[last]
                out[m, 7] = FLAG_END
                self.finished = True
            else:
                k = int(self.tau)
                f = self.tau - k
                out[m] = self.rows[k] + f * (self.rows[k + 1] - self.rows[k])
                out[m, 6] = self.rows[k, 6]
                out[m, 7] = 0.0
                if self.stopping and self.at_rest:
                    out[m, 7] = FLAG_END
                    self.finished = True
            m += 1
        return out[:m]
