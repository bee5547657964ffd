"""Test helper: the disable walk judged by the frames the drives received (decoded off the rings).

:class:`OrderTap` is :class:`hexacnc.bench.ringtap.RingTap` noting, with every controlword, the
bus it came on and how many SYNCs that bus had carried before it (exact order on one bus), so a
test can tell whether 0x0000 reached a drive while its targets still moved.
"""
from __future__ import annotations

from drivers.cia402 import CW_DISABLE_OPERATION, CW_DISABLE_VOLTAGE, CW_QUICK_STOP
from hexacnc.bench.ringtap import RingTap


class OrderTap(RingTap):
    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.cw_where = []      #: per entry of seen.cw: (bus, SYNCs on that bus before it)

    def _master(self, t, b, arb, data):
        n = len(self.seen.cw)
        super()._master(t, b, arb, data)
        for _ in range(len(self.seen.cw) - n):
            self.cw_where.append((b, len(self.seen.targets[b])))


def controlwords(tap: OrderTap, since_t: float) -> list:
    """Per drive: the controlwords it received after ``since_t`` as (cw, bus, SYNC count), the
    repeats of the same value dropped."""
    out = [[] for _ in range(6)]
    with tap.lock:
        for (t, i, cw), (b, n) in zip(tap.seen.cw, tap.cw_where):
            if t >= since_t and (not out[i] or out[i][-1][0] != cw):
                out[i].append((cw, b, n))
    return out


def quick_stopped(tap: OrderTap, since_t: float) -> list:
    """The 0-based drives that received quick stop after ``since_t``."""
    return [i for i, seq in enumerate(controlwords(tap, since_t)) if any(cw == CW_QUICK_STOP for cw, _, _ in seq)]


def assert_disable_walk(tap: OrderTap, since_t: float, drives=range(6), still_syncs: int = 5) -> None:
    """Every drive in ``drives`` got 0x0007 (transition 5) before its first 0x0000, and that 0x0000
    came after its targets had stood still for ``still_syncs`` SYNCs on its bus; SYNC kept running
    after it (the walk holds the targets, it does not stop the frames)."""
    per = controlwords(tap, since_t)
    with tap.lock:
        for i in drives:
            cws = [cw for cw, _, _ in per[i]]
            assert CW_DISABLE_VOLTAGE in cws, f"drive {i + 1}: no 0x0000 after the stop: {cws}"
            k = cws.index(CW_DISABLE_VOLTAGE)
            assert CW_DISABLE_OPERATION in cws[:k], f"drive {i + 1}: 0x0000 without 0x0007 first: {cws}"
            _, b, n = per[i][k]
            col = list(tap.plan.bus_nodes[b]).index(i)
            rows = [v[col] for _, v in tap.seen.targets[b][max(0, n - still_syncs):n]]
            assert len(rows) == still_syncs and None not in rows, rows
            assert len(set(rows)) == 1, f"drive {i + 1}: 0x0000 while its target moved: {rows}"
            assert len(tap.seen.targets[b]) > n, f"drive {i + 1}: SYNC stopped with the 0x0000"
