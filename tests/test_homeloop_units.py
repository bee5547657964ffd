"""The hot loop's homing steps (hexacnc.daemon.homeloop) against a scripted SDO server / drive:
the frames sent, the sequence, and every failure path (SDO abort, silence, homing error, limits)."""
from __future__ import annotations

import struct
import types

import numpy as np

from hexacnc.config import load_config
from hexacnc.daemon import homecodes as C
from hexacnc.daemon import homeloop as H
from hexacnc.daemon import shm as S
from hexacnc.config.operator import HomingConfig

OE = 0x0237                       # Operation enabled, remote


class FakeDrives:
    """Answers expedited downloads one cycle later; mode 6 statusword; bit 4 -> attained after ``delay``."""

    def __init__(self, abort_index=None, silent=False, homing_error=False, delay=3):
        self.statusword = [OE | (1 << 12)] * 6          # CSP: follows
        self.sdo_resp = [bytearray(8) for _ in range(6)]
        self.sdo_count = [0] * 6
        self.cw = [0x0F] * 6
        self.sent: list[list[bytes]] = [[] for _ in range(6)]
        self.pending = [None] * 6
        self.abort_index, self.silent, self.homing_error, self.delay = abort_index, silent, homing_error, delay
        self.mode = [8] * 6
        self.count = [0] * 6

    def send_sdo(self, i, data):
        self.sent[i].append(bytes(data))
        self.pending[i] = bytes(data)
        return True

    def set_controlword(self, i, cw):
        self.cw[i] = cw

    def tick(self):
        for i in range(6):
            req = self.pending[i]
            if req is not None and not self.silent:
                self.pending[i] = None
                cs, index, sub, value = struct.unpack("<BHBi", req)
                if index == self.abort_index:
                    self.sdo_resp[i][:] = struct.pack("<BHBI", 0x80, index, sub, 0x06090030)
                else:
                    self.sdo_resp[i][:] = struct.pack("<BHBI", 0x60, index, sub, 0)
                    if index == 0x6060:
                        self.mode[i] = value & 0xFF
                self.sdo_count[i] += 1
            if self.mode[i] == 6:
                if self.cw[i] & 0x10:
                    self.count[i] += 1
                    if self.count[i] >= self.delay:
                        self.statusword[i] = OE | (1 << 10) | ((1 << 13) if self.homing_error else (1 << 12))
                    else:
                        self.statusword[i] = OE
                else:
                    self.statusword[i] = OE | (1 << 10)
            else:
                self.statusword[i] = OE | (1 << 12)


def make_loop(io, cfg=None):
    cfg = cfg or load_config()
    hm = HomingConfig(method="cia402", homing_method=-2, speed_search_mm_s=10.0, speed_zero_mm_s=2.0,
                      acceleration_mm_s2=100.0, offset_mm=np.arange(6) * 0.5)
    cfg = cfg.replace(operator=cfg.operator.__class__(homing=hm))
    mid = [(lo + hi) / 2 for lo, hi in zip(cfg.min_length_mm, cfg.max_length_mm)]
    return types.SimpleNamespace(cfg=cfg, io=io, ipm=float(cfg.bus.increments_per_mm),
                                 sh=types.SimpleNamespace(h=[0] * S.N_HEADER), act=list(mid), out=[0.0] * 6,
                                 lmin=list(cfg.min_length_mm), lmax=list(cfg.max_length_mm),
                                 hb_timeout_ns=int(cfg.bus.heartbeat_timeout_ms * 1_000_000))


def run(hc, io, n=200, t_ns=1_000_000, start=1):
    now = start
    r = C.RUNNING
    for _ in range(n):
        now += t_ns
        r = hc.step(now)
        io.tick()
        if r != C.RUNNING:
            return r, now
    return r, now


def test_sdo_frames_and_successful_sequence():
    io = FakeDrives()
    loop = make_loop(io)
    hc = H.HomingCycle(loop)
    assert hc.begin(1)
    assert loop.sh.h[S.H_HOME_RESULT] == C.RUNNING
    r, _ = run(hc, io)
    assert r == C.DONE and loop.sh.h[S.H_HOME_RESULT] == C.DONE
    ipm = loop.ipm
    for i in range(6):
        frames = io.sent[i]
        assert all(len(f) == 8 for f in frames)
        # method -2 as int8 (size 1, value byte 0xFE), speeds/acceleration in units/s, offset per strut
        assert frames[0] == bytes([0x2F, 0x98, 0x60, 0x00, 0xFE, 0xFF, 0xFF, 0xFF])
        assert frames[1] == struct.pack("<BHBI", 0x23, 0x6099, 1, round(10.0 * ipm))
        assert frames[2] == struct.pack("<BHBI", 0x23, 0x6099, 2, round(2.0 * ipm))
        assert frames[3] == struct.pack("<BHBI", 0x23, 0x609A, 0, round(100.0 * ipm))
        assert frames[4] == struct.pack("<BHBi", 0x23, 0x607C, 0, round(0.5 * i * ipm))
        assert frames[5] == struct.pack("<BHBI", 0x2F, 0x6060, 0, 6)
        assert frames[6] == struct.pack("<BHBI", 0x2F, 0x6060, 0, 8)       # back to CSP
        assert len(frames) == 7
        assert io.mode[i] == 8 and io.cw[i] == 0x0F
    assert loop.out == loop.act                   # targets held at the measured lengths


def test_sdo_abort_fails_with_the_strut_and_restores_csp():
    io = FakeDrives(abort_index=0x609A)
    loop = make_loop(io)
    hc = H.HomingCycle(loop)
    hc.begin(1)
    r, now = run(hc, io, t_ns=10_000_000)
    # still in mode 8 (no bit 10 "halted" to wait for): mode 8 is written after SDO_TIMEOUT_S
    assert now - 1 > C.SDO_TIMEOUT_S * 1e9
    assert r == C.E_SDO_ABORT and loop.sh.h[S.H_HOME_STRUT] == 1
    assert all(f[-1] == struct.pack("<BHBI", 0x2F, 0x6060, 0, 8) for f in io.sent)
    assert all(cw == 0x0F for cw in io.cw)


def test_homing_error_bit_13_fails():
    io = FakeDrives(homing_error=True)
    loop = make_loop(io)
    hc = H.HomingCycle(loop)
    hc.begin(1)
    r, _ = run(hc, io)
    assert r == C.E_HOMING_ERROR
    assert all(cw & 0x10 == 0 for cw in io.cw)     # bit 4 cleared: the drives stop homing


def test_silent_drive_times_out():
    io = FakeDrives(silent=True)
    loop = make_loop(io)
    hc = H.HomingCycle(loop)
    hc.begin(1)
    r, now = run(hc, io, n=100, t_ns=50_000_000)
    assert r == C.E_SDO_TIMEOUT
    assert now > C.SDO_TIMEOUT_S * 1e9


def test_length_outside_the_strut_limits_fails():
    io = FakeDrives(delay=10_000)
    loop = make_loop(io)
    hc = H.HomingCycle(loop)
    hc.begin(1)
    run(hc, io, n=20)
    loop.act[3] = loop.lmax[3] + 1.0
    r, _ = run(hc, io, n=50)
    assert r == C.E_LIMIT and loop.sh.h[S.H_HOME_STRUT] == 4


def test_drive_leaving_operation_enabled_or_silent_fails():
    io = FakeDrives(delay=10_000)
    loop = make_loop(io)
    hc = H.HomingCycle(loop)
    hc.begin(1)
    run(hc, io, n=20)
    io.statusword[2] = 0x0233                   # Switched on (bit 2 clear), no fault bit
    assert hc.step(10**9) == C.RUNNING           # the abort: bit 4 cleared, mode 8 written back
    r, _ = run(hc, io, n=50, start=10**9)
    assert r == C.E_FAULT and loop.sh.h[S.H_HOME_STRUT] == 3
    io = FakeDrives(delay=10_000)
    io.hb_ns = [1] * 6
    loop = make_loop(io)
    hc = H.HomingCycle(loop)
    hc.begin(1)
    io.hb_ns[5] = 0                              # none yet: not judged
    r, _ = run(hc, io, n=50, t_ns=loop.hb_timeout_ns // 10)
    assert r == C.E_HEARTBEAT and loop.sh.h[S.H_HOME_STRUT] == 1


def test_whole_run_times_out():
    io = FakeDrives(delay=10**9)
    loop = make_loop(io)
    hc = H.HomingCycle(loop)
    hc.begin(1)
    r, now = run(hc, io, n=200, t_ns=int(C.HOME_TIMEOUT_S * 1e9 / 50))
    assert r == C.E_TIMEOUT


def test_no_sdo_channel_is_unsupported():
    io = types.SimpleNamespace(statusword=[OE] * 6)
    loop = make_loop(io)
    hc = H.HomingCycle(loop)
    assert not hc.begin(1)
    assert loop.sh.h[S.H_HOME_RESULT] == C.E_UNSUPPORTED
