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
