"""Silences on a daemon's frame rings, timed by a process of their own (``hexacnc bench faults``).

:class:`RingGaps` starts ``python -m hexacnc.bench.ringgaps NAME...``: a small process (no GIL shared
with the daemon or the bench) that maps the shared-memory frame rings read-only, reads their write
indices every ``poll_s`` and records every interval longer than ``min_gap_s`` in which one side
published nothing: side 0, the master (the hot loop stalled), side 1, the drives (their process
stalled). Nothing is copied and nothing written, so it can watch a 10-minute soak.

A silence is bracketed by the watcher's own polls: ``lo`` = from the poll that saw the last record
before it to the last poll that still saw none, ``hi`` = from the poll before that record to the
first poll that saw the next one. The watcher's own wake-up delays
(a loaded VM) only widen ``hi - lo``; ``own_max_gap_s`` reports the longest.
"""
from __future__ import annotations

import json
import mmap
import os
import struct
import subprocess
import sys
import time

_I_W = (8, 24)           #: int64 slots of the write index from side 0 / side 1 (hexacnc.daemon.shmbus)
_HEADER_BYTES = 5 * 64   #: the rings' header (indices), before the records


class RingGaps:
    """``RingGaps(names).start()`` ... ``.stop()``; then ``gaps`` = [(side, t0, lo_s, hi_s)]."""

    def __init__(self, names, poll_s: float = 0.001, min_gap_s: float = 0.02):
        self.args = [sys.executable, "-m", "hexacnc.bench.ringgaps", str(poll_s), str(min_gap_s), *names]
        self.proc: subprocess.Popen | None = None
        self.gaps: list = []
        self.own_max_gap_s = 0.0

    def start(self) -> "RingGaps":
        self.proc = subprocess.Popen(self.args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        if self.proc.stdout.readline().strip() != "ready":
            raise RuntimeError("the ring watcher did not start")
        return self

    def stop(self) -> None:
        if self.proc is None:
            return
        out, _ = self.proc.communicate("stop\n", timeout=10)
        self.proc = None
        res = json.loads(out)
        self.gaps = [tuple(g) for g in res["gaps"]]
        self.own_max_gap_s = res["own_max_gap_s"]

    def longest(self, side: int, t0: float, t1: float, upper: bool = False) -> float:
        """Longest silence of ``side`` overlapping [t0, t1] (s; its lower bound, or with ``upper`` its
        upper bound; 0.0 if none over ``min_gap_s``)."""
        k = 3 if upper else 2
        return max((g[k] for g in self.gaps if g[0] == side and g[1] + g[3] >= t0 and g[1] <= t1), default=0.0)


def _watch(names, poll_s: float, min_gap_s: float) -> dict:
    maps = []
    for name in names:
        fd = os.open("/dev/shm/" + name.lstrip("/"), os.O_RDONLY)
        try:
            maps.append(mmap.mmap(fd, _HEADER_BYTES, prot=mmap.PROT_READ))
        finally:
            os.close(fd)

    def index(m, side):
        return struct.unpack_from("<q", m, 8 * _I_W[side])[0]
    now = time.monotonic()
    last = [[index(m, s) for s in (0, 1)] for m in maps]
    since = [[(now, now), (now, now)] for _ in maps]   # the last new record: published in (a, b]
    seen = [[now, now] for _ in maps]                  # the last poll that saw no new record
    gaps, own, prev = [], 0.0, now
    import select
    print("ready", flush=True)
    while not select.select([sys.stdin], [], [], poll_s)[0]:
        now = time.monotonic()
        own = max(own, now - prev)
        for b, m in enumerate(maps):
            for side in (0, 1):
                w = index(m, side)
                if w != last[b][side]:
                    a, pub = since[b][side]
                    if now - a > min_gap_s:
                        gaps.append((side, pub, max(0.0, seen[b][side] - pub), now - a))
                    last[b][side] = w
                    since[b][side] = (prev, now)
                seen[b][side] = now
        prev = now
    return {"gaps": gaps, "own_max_gap_s": own}


if __name__ == "__main__":
    sys.stdout.write(json.dumps(_watch(sys.argv[3:], float(sys.argv[1]), float(sys.argv[2]))) + "\n")
