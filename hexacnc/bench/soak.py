"""The soak of ``hexacnc bench faults``: back-and-forth moves while the drives' process is stalled
now and then for less than the configured bound, every fault accounted for.

**The bound.** The longest stall of the drives the machine accepts is ``[cycle] feedback_timeout_s``
(B): the hot loop faults on stale feedback after B; its heartbeat check waits at least B plus one
master heartbeat period; the following-error history covers B + 50 ms; the simulated drives do not
count their own stall against their RPDO deadline or their master-heartbeat consumer. The hot loop's
own stalls have their bound on the drives' side: ``[bus] comm_loss_timeout_s`` (the drives then stop
on their own, by design).

**Stalls injected**: SIGSTOP/SIGCONT of the drives' process, ``uniform(0.05, STALL_SHARE x B)`` s
every 1-3 s. **Stalls measured**: the watcher (:class:`~hexacnc.bench.ringgaps.RingGaps`, its own
process) times every silence of each side of the frame rings, so a stall made longer by a loaded
machine (SIGCONT late, the drives' process not scheduled) shows its real length, bracketed by the
watcher's polls. A fault in the second after a silence of the drives of at least B, or of the master
of at least ``comm_loss_timeout_s``, is *over the bound*; one where only the upper end of the
bracket reaches the bound is *undetermined*; any other is *spurious*.
"""
from __future__ import annotations

import os
import signal
import time

import numpy as np

from ..errors import HexacncError
from .ringgaps import RingGaps

#: injected stalls are at most this share of the bound (the rest: scheduling on a loaded machine)
STALL_SHARE = 0.9


def _explain(gaps: RingGaps, t_fault: float, bound_s: float, comm_s: float) -> tuple[str, str]:
    """("over_bound" | "undetermined" | "spurious", why) for a fault latched at ``t_fault``."""
    for side, who, b, key in ((1, "drives", bound_s, "[cycle] feedback_timeout_s"),
                              (0, "master", comm_s, "[bus] comm_loss_timeout_s")):
        lo = gaps.longest(side, t_fault - 1.0, t_fault)
        if lo >= b:
            return "over_bound", f"{who} silent {lo:.3f} s >= {key} {b:g} s"
    for side, who, b, key in ((1, "drives", bound_s, "[cycle] feedback_timeout_s"),
                              (0, "master", comm_s, "[bus] comm_loss_timeout_s")):
        lo, hi = gaps.longest(side, t_fault - 1.0, t_fault), gaps.longest(side, t_fault - 1.0, t_fault, upper=True)
        if hi >= b:
            return "undetermined", f"{who} silent {lo:.3f}-{hi:.3f} s (the watcher woke late), {key} {b:g} s"
    return "spurious", "no silence reached the bound"


def soak(cfg, seconds: float, seed: int = 1) -> dict:
    """Run the soak for ``seconds``; the report counts stalls injected and measured, and faults."""
    from ..daemon.core import Daemon
    rnd = np.random.default_rng(seed)
    bound = float(cfg.cycle.feedback_timeout_s)
    comm = float(cfg.bus.comm_loss_timeout_s)
    load0 = os.getloadavg()
    d = Daemon(cfg, realtime=False)
    gaps = RingGaps([seg.name for seg in d.sim.segments])
    faults, stalls, moves = [], [], 0
    try:
        gaps.start()
        t_end = time.monotonic() + seconds
        t_stall = time.monotonic() + 2.0
        sign = 1.0
        while time.monotonic() < t_end:
            st = d.status()
            if st["state"] == "fault":
                t_f = d.sh.h[57] * 1e-9
                time.sleep(0.05)                 # the watcher closes the gap that ended in the fault
                faults.append((t_f, st["fault"]["message"]))
                try:
                    d.reset()
                except HexacncError:             # faulted again meanwhile: counted on the next pass
                    pass
                continue
            if st["state"] == "idle":
                pose = np.array(cfg.home_pose, dtype=float)
                pose[0] += 80.0 * sign
                sign = -sign
                try:
                    d.move_to(pose, 150.0)
                    moves += 1
                except HexacncError:             # a fault latched since the status: counted on the next pass
                    pass
            if time.monotonic() > t_stall:
                s = float(rnd.uniform(0.05, STALL_SHARE * bound))
                t0 = time.monotonic()
                os.kill(d.sim.proc.pid, signal.SIGSTOP)
                time.sleep(s)
                os.kill(d.sim.proc.pid, signal.SIGCONT)
                stalls.append((t0, s))
                t_stall = time.monotonic() + float(rnd.uniform(1.0, 3.0))
            time.sleep(0.02)
        time.sleep(0.1)
        fe = d.status()["following_error_max_mm"]
    finally:
        gaps.stop()
        d.close()
    return _report(seconds, moves, stalls, faults, gaps, bound, comm, fe, load0)


def _report(seconds, moves, stalls, faults, gaps: RingGaps, bound, comm, fe, load0) -> dict:
    measured = [gaps.longest(1, t0, t0 + s + 0.2) for t0, s in stalls]
    judged = [(msg, *_explain(gaps, t_f, bound, comm)) for t_f, msg in faults]
    spurious = [msg for msg, verdict, _ in judged if verdict == "spurious"]
    master_gaps = [g[2] for g in gaps.gaps if g[0] == 0]
    drive_gaps = [g[2] for g in gaps.gaps if g[0] == 1]
    return {
        "seconds": seconds, "moves": moves,
        "bound_s": {"feedback_timeout_s": bound, "comm_loss_timeout_s": comm},
        "stalls_injected": len(stalls),
        "stall_injected_max_s": round(max((s for _, s in stalls), default=0.0), 3),
        "stall_measured_max_s": round(max(measured, default=0.0), 3),
        "stalls_measured_over_bound": sum(1 for m in measured if m >= bound),
        "stall_overrun_s": {"median": round(float(np.median([m - s for m, (_, s) in zip(measured, stalls)])), 3)
                            if stalls else None,
                            "max": round(max((m - s for m, (_, s) in zip(measured, stalls)), default=0.0), 3)},
        "drive_silences_over_bound": sum(1 for g in drive_gaps if g >= bound),
        "master_silences": {"over_20ms": len(master_gaps), "longest_s": round(max(master_gaps, default=0.0), 3),
                            "over_comm_loss_timeout": sum(1 for g in master_gaps if g >= comm)},
        "watcher_longest_wakeup_s": round(gaps.own_max_gap_s, 4),
        "faults": len(faults),
        "faults_over_bound": [f"{msg} ({why})" for msg, verdict, why in judged if verdict == "over_bound"][:10],
        "faults_undetermined": [f"{msg} ({why})" for msg, verdict, why in judged if verdict == "undetermined"][:10],
        "fault_messages": [msg for _, msg in faults][:10],
        "following_error_max_mm": [round(float(x), 4) for x in fe],
        "spurious": len(spurious), "spurious_messages": spurious[:10],
        "loadavg_start": [round(x, 2) for x in load0], "loadavg_end": [round(x, 2) for x in os.getloadavg()],
    }
