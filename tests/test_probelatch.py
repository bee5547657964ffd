"""The hot loop's touch-probe latch over SDO (hexacnc.daemon.probelatch) against drives that answer
like the simulated ones (drivers.touchprobe), stepped cycle by cycle without a bus."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from drivers.touchprobe import TouchProbe
from hexacnc.daemon import probelatch as PL
from hexacnc.daemon import shm as S


class FakeIO:
    """Six drives' SDO servers: a request is answered at the next poll (one cycle later)."""

    def __init__(self, refuse=False):
        self.tp = [TouchProbe() for _ in range(6)]
        self.sdo_resp = [bytearray(8) for _ in range(6)]
        self.sdo_count = [0] * 6
        self.pending: list = []
        self.refuse = refuse
        self.requests = 0

    def send_sdo(self, i, data):
        self.requests += 1
        self.pending.append((i, bytes(data)))
        return True

    def poll(self):
        for i, data in self.pending:
            cs, index, sub, value = struct.unpack("<BHBi", data)
            tp = self.tp[i]
            if self.refuse:
                r = struct.pack("<BHBI", 0x80, index, sub, 0x06020000)
            elif cs == 0x40:
                v = (tp.function, tp.status, tp.pos_value, tp.neg_value)[index - 0x60B8]
                r = struct.pack("<BHBi", 0x43, index, sub, v)
            else:
                tp.write_function(value)
                r = struct.pack("<BHBi", 0x60, index, sub, 0)
            self.sdo_resp[i][:] = r
            self.sdo_count[i] += 1
        self.pending.clear()


class Loop:
    def __init__(self, io):
        self.io = io
        self.state = S.ST_IDLE
        self.sh = type("Sh", (), {"s": np.zeros(S.N_STATUS)})()


def _cycles(latch, io, n, t0, signal=None, pos=None):
    t = t0
    for _ in range(n):
        io.poll()
        if signal is not None:
            s = signal(t)
            for i, tp in enumerate(io.tp):
                tp.sample(pos(i, t), s)
        latch.step(t)
        t += 500_000
    return t


def test_armed_latch_reads_every_drives_position_at_the_contact_edge():
    io = FakeIO()
    loop = Loop(io)
    latch = PL.ProbeLatch(loop)
    idle_requests = io.requests
    t = _cycles(latch, io, 20, 0)
    assert io.requests == idle_requests == 0                 # nothing on the bus unless armed
    req = PL.arm(loop.sh, 1)
    t = _cycles(latch, io, 6, t)
    assert loop.sh.s[S.S_PROBE_ACK] == req and PL.read(loop.sh)[0] == PL.ARMED
    # each drive moves at its own speed; the probe input closes at t_c (between two cycles)
    t_c = t + 7_250_000

    def pos(i, tt):
        return int(1000 * (i + 1) + (i + 1) * 3 * (tt - t) / 1e6)

    t = _cycles(latch, io, 60, t, signal=lambda tt: (t_c - tt) * 1e-9, pos=pos)
    state, mask, got = PL.read(loop.sh)
    assert state == PL.LATCHED and mask == 0x3F
    assert got == pytest.approx([1000 * (i + 1) + (i + 1) * 3 * 7.25 for i in range(6)], abs=1.0)   # 1 increment
    n = io.requests
    _cycles(latch, io, 20, t)
    assert io.requests == n                                  # done: no more polling
    PL.disarm(loop.sh)
    _cycles(latch, io, 4, t)
    assert PL.read(loop.sh)[0] == PL.OFF and all(tp.function == 0 for tp in io.tp)


def test_a_drive_refusing_the_latch_is_reported_not_hung():
    io = FakeIO(refuse=True)
    loop = Loop(io)
    latch = PL.ProbeLatch(loop)
    PL.arm(loop.sh, 2)
    _cycles(latch, io, 4, 0)
    assert PL.read(loop.sh)[0] == PL.E_SDO_ABORT and not latch.active


def test_not_armed_while_homing():
    io = FakeIO()
    loop = Loop(io)
    loop.state = S.ST_HOMING
    latch = PL.ProbeLatch(loop)
    PL.arm(loop.sh, 1)
    _cycles(latch, io, 2, 0)
    assert PL.read(loop.sh)[0] == PL.E_BUSY and io.requests == 0
