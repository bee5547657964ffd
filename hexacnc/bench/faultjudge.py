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
    ends = drive_ends(tap, t0)
    out["drives_disabled"] = all(e["shown_disabled"] for e in ends)
    out["drives_disabled_reporting"] = all(e["shown_disabled"] for e in ends if e["reporting"])
    out["drives_not_reporting"] = [e["node"] for e in ends if not e["reporting"]]
    quiet = [e for e in ends if not e["shown_disabled"]]
    if quiet:
        out["drives_end"] = {str(e["node"]): e for e in quiet}
    out["latency_s"] = round(t_detect - t0, 4) if t_detect is not None else None
    out["detected"] = t_detect is not None
    return out


def _commands_off(cw: int) -> bool:
    """A controlword that takes a CiA 402 drive out of Operation enabled and leaves it without torque:
    shutdown (bit 0 clear), disable voltage (bit 1 clear) or quick stop (bit 2 clear, ends in Switch on
    disabled)."""
    return (cw & 0x7) != 0x7


def drive_ends(tap: RingTap, t0: float) -> list[dict]:
    """How each drive ended, from the frames after ``t0``: its last statusword (state, and whether it was
    sent after ``t0``: a silent drive's last one is stale), a boot-up after its last statusword (a drive
    that resets comes up in Switch on disabled, NMT pre-operational, and sends no PDO until it is
    started again: its boot-up is its last word), and the last controlword the master sent it.
    ``shown_disabled``: a disabled state in a statusword sent after ``t0``, or a boot-up after the last
    statusword; ``reporting``: some statusword or boot-up after ``t0``."""
    with tap.lock:
        status = list(tap.seen.status)
        boots = list(tap.seen.bootup)
        cws = list(tap.seen.cw)
    out = []
    for i in range(6):
        st = [(t, sw) for t, k, sw in status if k == i]
        bt = [t for t, k in boots if k == i and t >= t0]
        cw = [(t, c) for t, k, c in cws if k == i]
        t_sw, sw = st[-1] if st else (None, None)
        state = cia402.state_from_status(sw) if sw is not None else None
        fresh = t_sw is not None and t_sw >= t0
        booted = bool(bt) and (t_sw is None or bt[-1] > t_sw)
        e = {"node": i + 1, "state": cia402.state_name(state) if state is not None else None,
             "statusword_after_t0": fresh, "booted_after_t0": bool(bt),
             "last_controlword": f"0x{cw[-1][1]:04x}" if cw else None,
             "disable_commanded": bool(cw) and _commands_off(cw[-1][1]) and cw[-1][0] >= t0,
             "shown_disabled": booted or (fresh and state in DISABLED),
             "reporting": fresh or bool(bt)}
        if not e["reporting"]:
            e["note"] = ("no statusword since the fault: the frames cannot show its state"
                         + (" (the master sent it a disabling controlword)" if e["disable_commanded"] else ""))
        out.append(e)
    return out


def moving_daemon(cfg, feed_mm_s: float = 150.0, move: bool = True):
    """An in-process daemon with a ring tap, moving at ``feed_mm_s`` (``move`` false: not yet, see
    :func:`start_move`)."""
    from ..daemon.core import Daemon
    d = Daemon(cfg, realtime=False)
    tap = RingTap(cfg, [seg.name for seg in d.sim.segments]).start()
    if move:
        start_move(d, tap, cfg, feed_mm_s)
    return d, tap


def start_move(d, tap: RingTap, cfg, feed_mm_s: float) -> None:
    """A 100 mm move in x from where the machine is, once under way at 40 % of ``feed_mm_s``."""
    pose = np.array(d.status()["pose_cmd"], dtype=float)
    pose[0] += 100.0
    d.move_to(pose, feed_mm_s)
    t_end = time.monotonic() + 10
    while time.monotonic() < t_end:
        t, L = tap.lengths_mm(time.monotonic() - 0.05)
        if len(L) > 10 and speed(L, cfg.cycle.period_s)[-1] > 0.4 * feed_mm_s:
            break
        time.sleep(0.01)


def wait_fault(d, timeout_s: float) -> dict | None:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        st = d.status()
        if st["loop_state"] in ("fault", "disabled") or not d.alive:
            return st["fault"]
        time.sleep(0.005)
    return None
