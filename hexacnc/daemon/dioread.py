"""M66: the supervisor's side of reading the drives' digital inputs (0x60FD) and waiting on one.

The hot loop reads (:class:`~hexacnc.daemon.dioloop.DigitalOut`, non-blocking SDO upload after the
cycle's frames) when asked through ``S_DIN_DRIVE``/``S_DIN_REQ`` and answers in ``S_DIN_VAL``/
``S_DIN_ACK``.  :func:`wait_input` polls every :data:`POLL_S` for LinuxCNC's wait modes:
``immediate`` (L0: read once), ``rise``/``fall`` (L1/L2: an edge after the wait began), ``high``/
``low`` (L3/L4: the level, at once if already there).  The result is #5399: the input's state
(0/1) when the condition was met, or -1 when ``timeout_s`` passed first.
"""
from __future__ import annotations

import time
from typing import Callable

from ..errors import HexacncError
from . import shm as S

POLL_S = 0.002
READ_TIMEOUT_S = 1.0


def read_inputs(sh, drive: int, timeout_s: float = READ_TIMEOUT_S) -> int:
    """One read of drive ``drive``'s (0..5) 0x60FD through the hot loop."""
    s = sh.s
    s[S.S_DIN_DRIVE] = float(drive)
    req = s[S.S_DIN_REQ] + 1.0
    s[S.S_DIN_REQ] = req
    t_end = time.monotonic() + timeout_s
    while s[S.S_DIN_ACK] < req:
        if time.monotonic() > t_end:
            raise HexacncError(f"no answer from the hot loop reading drive {drive + 1}'s digital inputs")
        time.sleep(0.0005)
    v = s[S.S_DIN_VAL]
    if v < 0:
        raise HexacncError(f"drive {drive + 1} did not answer the 0x60FD (digital inputs) read")
    return int(v)


def wait_input(daemon, drive: int, bit: int, mode: str, timeout_s: float,
               check_stop: Callable[[], None]) -> int:
    """Wait on bit ``bit`` of drive ``drive``'s inputs as M66 ``mode``; returns #5399."""
    sh = daemon.sh

    def level() -> int:
        return (read_inputs(sh, drive) >> bit) & 1
    first = level()
    if mode == "immediate":
        return first
    t_end = time.monotonic() + timeout_s
    prev = first
    while True:
        now = level()
        if ((mode == "high" and now) or (mode == "low" and not now) or (mode == "rise" and now and not prev)
                or (mode == "fall" and prev and not now)):
            return now
        prev = now
        if time.monotonic() >= t_end:
            return -1
        check_stop()
        time.sleep(POLL_S)
