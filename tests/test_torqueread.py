"""The hot loop's decimated torque / current sampling (:mod:`hexacnc.daemon.torqueread`) on fake SDO
servers: values land in the shared slots and the status keys; a drive without 0x6077 (SDO abort) or a
silent one simply has none, never a fault; the channel is left to the probe latch and homing."""
from __future__ import annotations

import math
import struct

import numpy as np

from hexacnc.config import load_config
from hexacnc.daemon import shm as S
from hexacnc.daemon import torqueread as TR


class FakeIO:
    """Drives answering 0x6077 / 0x6078 uploads at the next poll; ``lacking``: drives that abort 0x6077,
    ``silent``: drives that never answer."""

    def __init__(self, values, lacking=(), silent=()):
        self.values = values
        self.lacking, self.silent = set(lacking), set(silent)
        self.sdo_resp = [bytearray(8) for _ in range(6)]
        self.sdo_count = [0] * 6
        self.pending: list = []
        self.sent: list = []

    def send_sdo(self, i, data):
        self.sent.append((i, bytes(data)))
        if i not in self.silent:
            self.pending.append((i, bytes(data)))
        return True

    def poll(self):
        for i, data in self.pending:
            cs, index, sub, _ = struct.unpack("<BHBI", data)
            if index == 0x6077 and i in self.lacking:
                r = struct.pack("<BHBI", 0x80, index, sub, 0x06020000)      # object does not exist
            else:
                v = self.values[i] if index == 0x6077 else max(-32768, min(32767, 2 * self.values[i]))
                r = struct.pack("<BHBhH", 0x4B, index, sub, v, 0)
            self.sdo_resp[i][:] = r
            self.sdo_count[i] += 1
        self.pending.clear()


class Loop:
    def __init__(self, io, state=S.ST_IDLE):
        self.io = io
        self.cfg = load_config(None)
        self.state = state
        self.sh = type("Sh", (), {"s": np.zeros(S.N_STATUS)})()
        self.latch = type("Latch", (), {"active": False, "seen": 0.0})()


def _run(tq, io, seconds: float, t0: int = 1_000_000_000, period_ns: int = 500_000) -> int:
    t = t0
    for _ in range(int(seconds * 1e9 / period_ns)):
        io.poll()
        tq.step(t)
        t += period_ns
    return t


def test_values_reach_the_slots_and_the_status_keys():
    vals = [12, -7, 300, -32768 + 5, 0, 41]
    io = FakeIO(vals)
    loop = Loop(io)
    tq = TR.TorqueSampler(loop)
    t = _run(tq, io, 0.2)
    st = TR.status_keys(loop.sh.s, t * 1e-9)
    assert st["torque_actual_permille"] == [float(v) for v in vals]
    assert st["current_actual_permille"] == [float(max(-32768, min(32767, 2 * v))) for v in vals]
    assert 0.0 <= st["torque_actual_age_s"] < 0.2
    # decimated: at most one request per GAP_NS over all drives
    assert len(io.sent) <= 0.2e9 / TR.GAP_NS + 1


def test_a_drive_without_0x6077_or_silent_has_no_value_and_no_fault():
    io = FakeIO([5] * 6, lacking=(2,), silent=(4,))
    loop = Loop(io)
    tq = TR.TorqueSampler(loop)
    t = _run(tq, io, 3.0)
    st = TR.status_keys(loop.sh.s, t * 1e-9)
    tor = st["torque_actual_permille"]
    assert tor[2] is None and tor[4] is None and tor[0] == 5.0
    assert st["current_actual_permille"][2] == 10.0 and st["current_actual_permille"][4] is None
    assert not tq.supported[2][0] and not tq.supported[4][0] and not tq.supported[4][1]
    assert loop.state == S.ST_IDLE
    n = len(io.sent)
    _run(tq, io, 0.5, t)
    assert all(i not in (4,) for i, _ in io.sent[n:])            # given up after MAX_TIMEOUTS
    assert all(not (i == 2 and d[1:3] == b"\x77\x60") for i, d in io.sent[n:])


def test_no_drive_with_the_objects_gives_no_status_keys():
    io = FakeIO([1] * 6, lacking=range(6))
    loop = Loop(io)
    tq = TR.TorqueSampler(loop)
    for i in range(6):
        tq.supported[i][1] = False
    t = _run(tq, io, 0.3)
    assert TR.status_keys(loop.sh.s, t * 1e-9) == {}
    assert all(math.isnan(loop.sh.s[S.S_TORQUE + i]) for i in range(6))


def test_the_channel_is_left_to_the_latch_homing_and_motion_without_room():
    io = FakeIO([1] * 6)
    loop = Loop(io)
    tq = TR.TorqueSampler(loop)
    loop.latch.active = True
    _run(tq, io, 0.1)
    assert io.sent == []
    loop.latch.active = False
    for st in (S.ST_HOMING, S.ST_BOOT, S.ST_FAULT):
        loop.state = st
        _run(tq, io, 0.1)
        assert io.sent == []
    loop.state = S.ST_RUNNING
    assert TR.motion_room(loop.cfg) is False           # default layout: load 0.93, no room for 8 bytes
    _run(tq, io, 0.1)
    assert io.sent == []
    loop.state = S.ST_IDLE
    io.silent = set(range(6))
    _run(tq, io, 0.001)
    assert len(io.sent) == 1 and tq.holds(io.sent[0][0])      # the latch and homing wait for it
