"""Jerk-limited controlled stop of the struts (plain floats, no allocation).

Each strut is brought from its current commanded velocity ``v`` and acceleration
``a`` to rest by the time-optimal jerk-limited profile: every cycle the new
acceleration is the one after which ramping the acceleration back to zero at
``max_jerk`` ends exactly at zero velocity, clamped to the jerk and acceleration
limits reachable in one cycle.  This is also the profile with the shortest
stopping distance, so a strut whose commanded motion so far was feasible (it
could still have stopped, or reversed, inside its length range) stops inside
its length range too; the lengths are clamped to the range as a final guard.

Margin: the stop is planned at :data:`STOP_SHARE` (0.9) of each strut's acceleration and jerk
limits, as the planner plans at shares of them (``planner.plan.ETA``), so that the stop measured on
the 0.1 um drive increments stays below the limits too. A stop that starts above the share (the
planner's own profile runs up to 0.95) brings the acceleration down to the share at the shared jerk.
Only a state whose velocity would overshoot ``max_velocity`` while its acceleration ramps down at
the shared jerk (accelerating near the velocity limit) takes up to the full jerk limit, never more.
In exact arithmetic every single-cycle difference of the commands stays within these bounds
(``tests/test_stopgen.py``).
"""
from __future__ import annotations

import math

from drivers.jerkstop import STOP_SHARE, stop_accel

__all__ = ["STOP_SHARE", "StrutStop", "peak_speed", "stop_accel"]


def peak_speed(v: float, a: float, jmax: float, dt: float) -> float:
    """|v| reached when ``a`` (same sign as ``v``) ramps down to zero in steps of ``jmax dt``."""
    jdt = jmax * dt
    aa = a if a > 0.0 else -a
    n = math.floor(aa / jdt)
    return (v if v > 0.0 else -v) + dt * (n * aa - jdt * n * (n + 1) * 0.5)


class StrutStop:
    """Controlled stop of six struts; ``start`` with the last three commands, ``step`` per cycle."""

    def __init__(self, vmax, amax, jmax, lmin, lmax, dt: float, share: float = STOP_SHARE):
        self.vmax = [float(x) for x in vmax]
        self.amax_full = [float(x) for x in amax]
        self.jmax_full = [float(x) for x in jmax]
        self.amax = [share * x for x in self.amax_full]
        self.jmax = [share * x for x in self.jmax_full]
        self.lmin = [float(x) for x in lmin]
        self.lmax = [float(x) for x in lmax]
        self.dt = float(dt)
        self.L = [0.0] * 6
        self.v = [0.0] * 6
        self.a = [0.0] * 6
        self.active = False

    def start(self, l0, l1, l2) -> None:
        """Begin from commands ``l0`` (last), ``l1``, ``l2`` (one and two cycles earlier), mm."""
        dt = self.dt
        for i in range(6):
            self.L[i] = l0[i]
            v = (l0[i] - l1[i]) / dt
            a = (l0[i] - 2.0 * l1[i] + l2[i]) / (dt * dt)
            vm = self.vmax[i]
            am = self.amax_full[i]
            self.v[i] = vm if v > vm else (-vm if v < -vm else v)
            self.a[i] = am if a > am else (-am if a < -am else a)
        self.active = True

    def step(self, out) -> bool:
        """Write the next six lengths (mm) into ``out``; True while any strut still moves."""
        dt = self.dt
        moving = False
        for i in range(6):
            v = self.v[i]
            a = self.a[i]
            if v == 0.0 and a == 0.0:
                out[i] = self.L[i]
                continue
            vm = self.vmax[i]
            j = self.jmax[i]
            if v * a > 0.0 and peak_speed(v, a, j, dt) > vm:      # ramping a down at the share overshoots
                j = self.jmax_full[i]
            an = stop_accel(v, a, j, self.amax[i], dt)
            vn = v + an * dt
            if vn > vm:
                vn = vm
                an = (vn - v) / dt
            elif vn < -vm:
                vn = -vm
                an = (vn - v) / dt
            L = self.L[i] + vn * dt
            if L < self.lmin[i]:
                L = self.lmin[i]
                vn = an = 0.0
            elif L > self.lmax[i]:
                L = self.lmax[i]
                vn = an = 0.0
            self.L[i] = L
            self.v[i] = vn
            self.a[i] = an
            out[i] = L
            if vn != 0.0 or an != 0.0:
                moving = True
        self.active = moving
        return moving
