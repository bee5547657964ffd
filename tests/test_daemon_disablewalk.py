"""The hot loop's disable walk (:mod:`hexacnc.daemon.disablewalk`) and quick stop, in process.

What the drives received is judged from the controlwords the in-process drive model (the one CiA
402 drive side, :func:`drivers.cia402.drive_step`) got, in order, with the targets sent meanwhile.
"""
from __future__ import annotations

import logging

import numpy as np

from drivers import cia402
from drivers.cia402 import (CW_DISABLE_OPERATION, CW_DISABLE_VOLTAGE, CW_ENABLE_OPERATION, CW_FAULT_RESET,
                            CW_QUICK_STOP)
from hexacnc.daemon import shm as S
from hexacnc.daemon.disablewalk import DISABLE_TIMEOUT_NS, DisableWalk
from hexacnc.daemon.faults import F_EMCY, F_HEARTBEAT, F_TEST

from test_daemon_loop import _moving_rows, _push, _run, rig  # noqa: F401 (fixture)

SOD = 0x0040 | cia402.SW_REMOTE
OE = 0x0027 | cia402.SW_REMOTE | cia402.SW_DRIVE_FOLLOWS


class Drives:
    """Six drives on the CiA 402 drive side; ``hold_qs``: stay in Quick stop active (0x605A 5/6)."""

    def __init__(self, sw):
        self.statusword = list(sw)
        self.got = [[] for _ in range(6)]
        self.prev = [CW_ENABLE_OPERATION] * 6

    def set_controlword(self, i, cw):
        self.got[i].append(cw)
        state = cia402.state_from_status(self.statusword[i])
        new, num = cia402.drive_step(state, cw, self.prev[i])
        self.prev[i] = cw
        if num:
            self.statusword[i] = cia402.drive_statusword(new)


def test_walk_goes_through_transition_5_then_10_and_ends():
    io = Drives([OE] * 6)
    w = DisableWalk(io, [CW_ENABLE_OPERATION] * 6)
    w.begin(0)
    assert not w.step(1)
    assert all(g == [CW_DISABLE_OPERATION] for g in io.got)        # transition 5 first: 0x0007
    assert all(cia402.state_from_status(s) == cia402.SWITCHED_ON for s in io.statusword)
    assert not w.step(2)
    assert all(g == [CW_DISABLE_OPERATION, CW_DISABLE_VOLTAGE] for g in io.got)   # then 10
    assert all(cia402.state_from_status(s) == cia402.SWITCH_ON_DISABLED for s in io.statusword)
    assert w.step(3) and not w.active               # the statuswords say so: done
    assert w.timeouts == 0


def test_a_drive_ramping_down_keeps_0x0007_until_switched_on():
    io = Drives([OE] * 6)
    io.set_controlword = lambda i, cw, f=io.set_controlword: f(i, cw) if i != 2 else io.got[2].append(cw)
    w = DisableWalk(io, [CW_ENABLE_OPERATION] * 6)
    w.begin(0)
    for k in range(5):                  # drive 3 still ramps per 0x605C: stays Operation enabled
        assert not w.step(k)
    assert io.got[2] == [CW_DISABLE_OPERATION]                      # sent once, held, never 0x0000
    io.statusword[2] = cia402.drive_statusword(cia402.SWITCHED_ON)
    assert not w.step(6)
    assert io.got[2] == [CW_DISABLE_OPERATION, CW_DISABLE_VOLTAGE]


def test_quick_stop_active_waits_for_the_drive_fault_is_not_reset_timeout_forces_0x0000(caplog):
    io = Drives([SOD] * 6)
    io.statusword[1] = cia402.drive_statusword(cia402.QUICK_STOP_ACTIVE)
    io.statusword[4] = 0x0208                                       # Fault
    w = DisableWalk(io, [CW_ENABLE_OPERATION] * 6)
    w.begin(0)
    assert not w.step(10)
    assert io.got[1] == [CW_QUICK_STOP]             # held in Quick stop active, never 16 (0x000F)
    assert CW_FAULT_RESET not in io.got[4]          # a disable never resets a fault
    with caplog.at_level(logging.WARNING, logger="hexacnc.loop"):
        assert w.step(DISABLE_TIMEOUT_NS + 1)       # 0x605A 5/6: stays; the time-out ends it
    assert w.timeouts == 1 and "drive 2: Quick stop active" in caplog.text
    assert io.got[1] == [CW_QUICK_STOP, CW_DISABLE_VOLTAGE]
    assert cia402.state_from_status(io.statusword[1]) == cia402.SWITCH_ON_DISABLED


def test_quick_stop_sends_bit_2_cleared_once():
    io = Drives([OE] * 6)
    w = DisableWalk(io, [CW_ENABLE_OPERATION] * 6)
    w.quick_stop(3)
    w.quick_stop(3)
    assert io.got[3] == [CW_QUICK_STOP] and not CW_QUICK_STOP & cia402.CW_BIT_QUICK_STOP
    assert cia402.state_from_status(io.statusword[3]) == cia402.QUICK_STOP_ACTIVE


def _cw_per_drive(io, since):
    out = [[] for _ in range(6)]
    for n, i, cw in io.cw_log:
        if n >= since:
            out[i].append((n, cw))
    return out


def test_disable_while_moving_walks_each_drive_after_the_stop(rig):
    cfg, hx, sh, io, lp = rig()
    rows = _moving_rows(cfg, hx, sh, [40.0, 0.0, -900.0, 0.0, 0.0, 0.0])
    _push(sh, rows)
    _run(lp, len(rows) // 2)
    n0 = len(io.log)
    _cmd(sh, S.CMD_DISABLE)
    _run(lp, 1500)
    assert sh.h[S.H_STATE] == S.ST_DISABLED and lp.dwalk.timeouts == 0
    T = np.array(io.log, dtype=float)
    moving = np.any(np.diff(T, axis=0) != 0, axis=1)           # moving[k]: send k+1 differs from k
    assert moving[n0:n0 + 20].any(), "the disable came at rest: the test proves nothing"
    for i, seq in enumerate(_cw_per_drive(io, n0)):
        cws = [cw for _, cw in seq]
        assert cws == [CW_DISABLE_OPERATION, CW_DISABLE_VOLTAGE], (i, cws)
        n_off = seq[-1][0]
        assert not moving[n_off - 5:].any(), f"drive {i + 1}: 0x0000 while the targets still moved"
        assert len(io.log) > n_off + 1                            # SYNC and targets kept flowing
    assert all(cia402.state_from_status(s) == cia402.SWITCH_ON_DISABLED for s in io.statusword)


def _cmd(sh, code, arg=0):
    sh.h[S.H_CMD] = code
    sh.h[S.H_CMD_ARG] = arg
    sh.h[S.H_CMD_SEQ] += 1


def test_shutdown_exits_only_after_the_walk(rig):
    cfg, hx, sh, io, lp = rig()
    n0 = len(io.log)
    _cmd(sh, S.CMD_SHUTDOWN)
    lp.run()                                        # returns once shut down
    assert [[cw for _, cw in s] for s in _cw_per_drive(io, n0)] == \
        [[CW_DISABLE_OPERATION, CW_DISABLE_VOLTAGE]] * 6
    assert not lp.dwalk.active and sh.h[S.H_STATE] == S.ST_DISABLED


def test_heartbeat_loss_quick_stops_that_drive_the_others_take_the_loops_stop(rig):
    cfg, hx, sh, io, lp = rig()
    rows = _moving_rows(cfg, hx, sh, [40.0, 0.0, -900.0, 0.0, 0.0, 0.0], feed=60.0)
    _push(sh, rows)
    _run(lp, 200)
    n0 = len(io.log)
    io.hb_lost[2] = True
    _run(lp, int(cfg.bus.heartbeat_timeout_ms * 1e-3 / 0.0005) + 1500)
    assert sh.h[S.H_FAULT] == F_HEARTBEAT and sh.h[S.H_STATE] == S.ST_FAULT
    per = _cw_per_drive(io, n0)
    assert [cw for _, cw in per[2]][0] == CW_QUICK_STOP
    T = np.array(io.log, dtype=float)
    moving = np.any(np.diff(T, axis=0) != 0, axis=1)
    assert moving[per[2][0][0] - 3:per[2][0][0]].any(), "the fault came at rest: the test proves nothing"
    for i in (0, 1, 3, 4, 5):
        assert [cw for _, cw in per[i]] == [CW_DISABLE_OPERATION, CW_DISABLE_VOLTAGE], i
        assert per[i][0][0] > per[2][0][0] + 10     # after the loop's stop, not with the fault
        assert not moving[per[i][0][0] - 5:].any(), f"drive {i + 1}: disabled while the targets moved"
    assert io.cw_log[-1][2] == CW_DISABLE_VOLTAGE


def test_emcy_quick_stop_and_a_test_fault_does_not(rig):
    cfg, hx, sh, io, lp = rig()
    rows = _moving_rows(cfg, hx, sh, [40.0, 0.0, -900.0, 0.0, 0.0, 0.0])
    _push(sh, rows)
    _run(lp, len(rows) // 2)
    n0 = len(io.log)
    io.emcy(4, 0x2310)
    _run(lp, 800)
    assert sh.h[S.H_FAULT] == F_EMCY
    assert [cw for _, cw in _cw_per_drive(io, n0)[4]][0] == CW_QUICK_STOP
    cfg, hx, sh, io, lp = rig()
    _push(sh, _moving_rows(cfg, hx, sh, [40.0, 0.0, -900.0, 0.0, 0.0, 0.0]))
    _run(lp, 200)
    n0 = len(io.log)
    _cmd(sh, S.CMD_FAULT_TEST)
    _run(lp, 1500)
    assert sh.h[S.H_FAULT] == F_TEST and sh.h[S.H_STATE] == S.ST_FAULT
    assert all([cw for _, cw in s] == [CW_DISABLE_OPERATION, CW_DISABLE_VOLTAGE]
               for s in _cw_per_drive(io, n0))
