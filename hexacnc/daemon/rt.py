"""Real-time privileges of the calling process: SCHED_FIFO, mlockall, CPU affinity.

Each request is tried and reported; none is fatal (a newcomer runs without root),
but every refusal is logged in one clear line with the reason and the fix.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import errno
import logging
import os

log = logging.getLogger("hexacnc.rt")

MCL_CURRENT = 1
MCL_FUTURE = 2


def mlockall() -> tuple[bool, str]:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        if libc.mlockall(MCL_CURRENT | MCL_FUTURE) == 0:
            return True, "memory locked (mlockall)"
        err = ctypes.get_errno()
        return False, (f"mlockall refused: {os.strerror(err)} (raise LimitMEMLOCK / ulimit -l, "
                       f"or grant CAP_IPC_LOCK)")
    except (OSError, AttributeError) as exc:
        return False, f"mlockall unavailable: {exc}"


def sched_fifo(priority: int) -> tuple[bool, str]:
    if not hasattr(os, "sched_setscheduler"):
        return False, "SCHED_FIFO unavailable on this platform"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True, f"SCHED_FIFO priority {priority}"
    except OSError as exc:
        hint = " (needs CAP_SYS_NICE or LimitRTPRIO/rtprio >= priority)" if exc.errno in (errno.EPERM,) else ""
        return False, f"SCHED_FIFO {priority} refused: {exc.strerror}{hint}; running SCHED_OTHER"


def sim_drives_priority(realtime_priority: int) -> int:
    """SCHED_FIFO priority of the simulated drives' process: just below the hot loop, above the
    supervisor's feeder (``realtime_priority - 30``).

    Tried and measured (clean-clone CI runs): below the feeder and control worker (``- 40``) or at a
    raised nice value instead of FIFO, the drives themselves missed their deadlines (lost heartbeats,
    stale feedback, following errors: the supervisor's threads holding the interpreter lock while
    the simulation waited); so the simulation keeps its place and the supervisor is made to need
    less of the CPU (``FeedMixin._push`` starts a job with ``FEED_START_S`` queued)."""
    return max(1, realtime_priority - 10)


def pin_cpu(cpu: int) -> tuple[int, str]:
    """Pin to ``cpu`` (-1: the last allowed CPU). Returns (cpu or -1, message)."""
    if not hasattr(os, "sched_setaffinity"):
        return -1, "CPU affinity unavailable on this platform"
    try:
        allowed = sorted(os.sched_getaffinity(0))
        target = allowed[-1] if cpu < 0 else cpu
        if target not in allowed:   # the parent kept itself off this CPU; we may widen back to it
            try:
                os.sched_setaffinity(0, {target})
                return target, f"pinned to CPU {target}"
            except OSError:
                pass
        if target not in allowed:
            return -1, f"CPU {target} not in the allowed set {allowed}; not pinned"
        if len(allowed) == 1:
            return target, f"single CPU {target} available (no isolation possible)"
        os.sched_setaffinity(0, {target})
        return target, f"pinned to CPU {target} of {allowed}"
    except OSError as exc:
        return -1, f"CPU affinity refused: {exc.strerror}; not pinned"


def acquire(priority: int, cpu: int, want_fifo: bool = True) -> dict:
    """Try all three; log one line each; return ``{"sched_fifo", "mlockall", "affinity_cpu", "messages"}``."""
    msgs = []
    locked, m = mlockall()
    msgs.append(m)
    (log.info if locked else log.warning)("hot loop: %s", m)
    pinned, m = pin_cpu(cpu)
    msgs.append(m)
    (log.info if pinned >= 0 else log.warning)("hot loop: %s", m)
    if want_fifo:
        fifo, m = sched_fifo(priority)
    else:
        fifo, m = False, "SCHED_FIFO not requested"
    msgs.append(m)
    (log.info if fifo else log.warning)("hot loop: %s", m)
    return {"sched_fifo": fifo, "mlockall": locked, "affinity_cpu": pinned, "messages": msgs}


def bare_loop(period_s: float, seconds: float, spin_s: float, work_s: float = 0.0) -> dict:
    """The hot loop's timing skeleton with nothing in it: the machine's own lateness.

    Same wake-up strategy as :class:`hexacnc.daemon.loop.HotLoop` (absolute deadlines on the
    monotonic clock, ``time.sleep`` until ``spin_s`` before the deadline, then spin) and the same
    overrun rule (a cycle whose end passes the next deadline; the missed deadlines are skipped and
    counted), with ``work_s`` of busy-waiting per cycle standing for the cycle's compute.  Run it
    in a process with the hot loop's privileges (see :func:`bare_loop_main`).  Returns lateness
    percentiles (us), the measured time of the fixed work (``compute_us``: anything above ``work_s``
    was taken by the machine), overruns, the longest run of consecutive overruns and the longest
    gap between two wake-ups.
    """
    import gc
    import time
    period = int(round(period_s * 1e9))
    spin = int(round(spin_s * 1e9))
    work = int(round(work_s * 1e9))
    n = int(round(seconds / period_s))
    hist = [0] * 4096
    hist_c = [0] * 4096
    mono = time.monotonic_ns
    sleep = time.sleep
    overruns = in_row = max_row = 0
    lat_max = 0
    gap_max = 0
    prev = 0
    cycles = 0
    gc.collect()
    gc.freeze()
    gc.disable()
    deadline = mono() + period
    try:
        while cycles < n:
            rem = deadline - mono()
            if rem > spin:
                sleep((rem - spin) * 1e-9)
            while mono() < deadline:
                pass
            t0 = mono()
            if work:
                t_w = t0 + work
                while mono() < t_w:
                    pass
            late = t0 - deadline
            k = late // 1000
            hist[k if k < 4095 else 4095] += 1
            if late > lat_max:
                lat_max = late
            if prev and t0 - prev > gap_max:
                gap_max = t0 - prev
            prev = t0
            t1 = mono()
            k = (t1 - t0) // 1000
            hist_c[k if k < 4095 else 4095] += 1
            cycles += 1
            deadline += period
            if t1 > deadline:
                missed = (t1 - deadline) // period + 1
                deadline += (missed - 1) * period
                overruns += missed
                in_row += missed
                if in_row > max_row:
                    max_row = in_row
            else:
                in_row = 0
    finally:
        gc.enable()
        gc.unfreeze()
    from .shm import percentiles_us
    p = percentiles_us(hist)
    c = percentiles_us(hist_c)
    return {"cycles": cycles, "period_s": period_s, "spin_us": spin / 1e3, "work_us": work / 1e3,
            "lateness_us": {"median": p[0], "p99": p[1], "p999": p[2], "max": lat_max / 1e3},
            "compute_us": {"median": c[0], "p99": c[1], "p999": c[2]},
            "overruns": overruns, "overrun_pct": 100.0 * overruns / cycles if cycles else 0.0,
            "max_overruns_in_row": max_row, "longest_gap_us": gap_max / 1e3,
            "late_over_100us": sum(hist[100:]), "late_over_period": sum(hist[int(period_s * 1e6):])}


def bare_loop_main(argv=None) -> int:
    """``python -m hexacnc.daemon.rt PERIOD_S SECONDS SPIN_S WORK_S PRIORITY CPU``: take the hot
    loop's privileges (:func:`acquire`), run :func:`bare_loop`, print one JSON object."""
    import json
    import sys
    a = sys.argv[1:] if argv is None else argv
    period_s, seconds, spin_s, work_s = (float(v) for v in a[:4])
    priority, cpu = int(a[4]), int(a[5])
    priv = acquire(max(1, priority), cpu, want_fifo=priority > 0)
    out = bare_loop(period_s, seconds, spin_s, work_s)
    out["privileges"] = {k: priv[k] for k in ("sched_fifo", "mlockall", "affinity_cpu")}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    import sys as _sys
    _sys.exit(bare_loop_main())
