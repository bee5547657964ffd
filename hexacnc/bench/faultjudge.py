"""What ``hexacnc bench faults`` judges a stop by, from the frames the drives received: a moving
in-process daemon with a ring tap, the stop's figures (:func:`judge`), waiting for a fault."""
from __future__ import annotations

import time

import numpy as np

from drivers import cia402
from .ringtap import RingTap, motion_peaks

DISABLED = (cia402.SWITCH_ON_DISABLED, cia402.READY_TO_SWITCH_ON, cia402.FAULT, cia402.NOT_READY)


def speed(L: np.ndarray, period_s: float) -> np.ndarray:
    """Largest strut speed per SYNC (mm/s)."""
    return np.max(np.abs(np.diff(L, axis=0)), axis=1) / period_s if len(L) > 1 else np.zeros(0)


def judge(tap: RingTap, cfg, t0: float, t_detect: float | None = None) -> dict:
    """Figures of the stop after ``t0`` from the frames (see the module doc)."""
    time.sleep(0.05)
    tap.drain()
    t, L = tap.lengths_mm(t0 - 0.01)
    out: dict = {}
    dt = cfg.cycle.period_s
    if len(L) > 2:
        v = speed(L, dt)
        slow = np.nonzero(v < 0.98 * v[0])[0]
        if t_detect is None and len(slow) and v[0] > 1.0:
            t_detect = float(t[slow[0] + 1])
        rest = np.nonzero(v < 1e-6)[0]
        end = rest[0] + 1 if len(rest) else len(L) - 1
        pk = motion_peaks(L[: end + 1], dt, cfg.max_velocity_mm_s, cfg.max_acceleration_mm_s2, cfg.max_jerk_mm_s3,
                          1.0 / cfg.bus.increments_per_mm)
        out.update(speed_at_start_mm_s=round(float(v[0]), 1), at_rest=bool(len(rest)),
                   stop_distance_mm=[round(float(x), 3) for x in np.abs(L[end] - L[0])],
                   peak_fraction={k: round(x, 3) for k, x in pk.items()})
    states = [cia402.state_from_status(s) if s is not None else None for s in tap.last_statuswords()]
    out["drives_disabled"] = all(s in DISABLED for s in states)
    out["latency_s"] = round(t_detect - t0, 4) if t_detect is not None else None
    out["detected"] = t_detect is not None
    return out


def moving_daemon(cfg, feed_mm_s: float = 150.0):
    from ..daemon.core import Daemon
    d = Daemon(cfg, realtime=False)
    tap = RingTap(cfg, [seg.name for seg in d.sim.segments]).start()
    pose = np.array(cfg.home_pose, dtype=float)
    pose[0] += 100.0
    d.move_to(pose, feed_mm_s)
    t_end = time.monotonic() + 10
    while time.monotonic() < t_end:
        t, L = tap.lengths_mm(time.monotonic() - 0.05)
        if len(L) > 10 and speed(L, cfg.cycle.period_s)[-1] > 0.4 * feed_mm_s:
            break
        time.sleep(0.01)
    return d, tap


def wait_fault(d, timeout_s: float) -> dict | None:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        st = d.status()
        if st["loop_state"] in ("fault", "disabled") or not d.alive:
            return st["fault"]
        time.sleep(0.005)
    return None
