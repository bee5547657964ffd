"""The hot loop's steps one by one: enable walk, cycle statistics, setpoint intake, frames out."""
from __future__ import annotations

import numpy as np
import pytest

from drivers.cia402 import CW_DISABLE_VOLTAGE, CW_ENABLE_OPERATION, CW_FAULT_RESET, CW_SHUTDOWN, CW_SWITCH_ON
from hexacnc.config import load_config
from hexacnc.daemon import shm as S
from hexacnc.daemon.cyclestats import CycleStats
from hexacnc.daemon.enablewalk import ENABLE_TIMEOUT_NS, EnableWalk, next_cw
from hexacnc.daemon.faults import F_SETPOINT
from hexacnc.daemon.loop import HotLoop
from hexacnc.daemon.simio import SimIO
from hexacnc.kinematics import Hexapod


@pytest.fixture
def shared():
    sh = S.Shared(create=True)
    yield sh
    sh.close()


def test_next_controlword_walks_the_cia402_states():
    assert next_cw(0x0240, -1) == CW_SHUTDOWN               # switch on disabled -> 2
    assert next_cw(0x0221, CW_SHUTDOWN) == CW_SWITCH_ON     # ready to switch on -> 3
    assert next_cw(0x0223, CW_SWITCH_ON) == CW_ENABLE_OPERATION   # switched on -> 4
    assert next_cw(0x0208, 0) == CW_FAULT_RESET             # fault: rising edge of bit 7 (15)
    assert next_cw(0x0208, CW_FAULT_RESET) == CW_DISABLE_VOLTAGE  # re-arm the edge
    assert next_cw(0x0207, CW_ENABLE_OPERATION) == CW_ENABLE_OPERATION  # quick stop active -> 16 (drivers.cia402)
    assert next_cw(-1, 5) == 5                              # unknown: wait


class _IO:
    def __init__(self):
        self.statusword = [0x0240] * 6
        self.pos_count = [0] * 6
        self.sent = []

    def set_controlword(self, i, cw):
        self.sent.append((i, cw))


def test_enable_walk_never_enables_blind_and_targets_the_measured_position():
    io = _IO()
    w = EnableWalk(io, [700.0] * 6, [1350.0] * 6)
    w.begin(0)
    act = [1000.0 + i for i in range(6)]
    out = [0.0] * 6
    assert w.step(1000, act, out) == 0
    assert out == act and io.sent == []           # no position sample yet: no controlword
    io.pos_count = [1] * 6
    assert w.step(2000, act, out) == 0 and set(cw for _, cw in io.sent) == {CW_SHUTDOWN}
    io.statusword = [0x1237] * 6
    assert w.step(3000, act, out) == 1 and io.sent[-1] == (5, CW_ENABLE_OPERATION)


def test_enable_walk_names_the_drive_that_did_not_enable():
    io = _IO()
    w = EnableWalk(io, [700.0] * 6, [1350.0] * 6)
    w.begin(0)
    io.pos_count = [1] * 6
    io.statusword = [0x1237] * 6
    io.statusword[3] = 0x0221
    assert w.step(ENABLE_TIMEOUT_NS + 1, [1000.0] * 6, [0.0] * 6) == -1
    assert (w.bad, w.arg) == (4, 0x0221)
    act = [1000.0] * 6
    act[1] = 2000.0                                    # outside the strut range: refused, named
    w.begin(0)
    assert w.step(ENABLE_TIMEOUT_NS // 8, act, [0.0] * 6) == 0
    # refused a quarter of the time-out after the walk began, not after the whole of it
    assert w.step(ENABLE_TIMEOUT_NS // 4 + 1, act, [0.0] * 6) == -1 and (w.bad, w.arg) == (2, -2)


def test_cycle_statistics_count_overruns_and_realign_after_a_slow_path(shared):
    st = CycleStats(shared, 500_000)
    d = 1_000_000
    d = st.account(d + 10_000, d + 60_000, d, False)          # on time
    assert st.overruns == 0 and d == 1_500_000
    d = st.account(d, d + 1_600_000, d, False)                 # 1.6 ms: 3 deadlines missed
    assert st.overruns == 3 and st.in_row == 3 and shared.h[S.H_MAX_IN_ROW] == 3
    d2 = st.account(d, d + 5_000_000, d, True)                 # slow path: realigned, no overrun
    assert st.overruns == 3 and d2 == d + 5_500_000
    assert shared.h[S.H_CYCLES] == 3
    st.phase(2, 42_000)
    st.publish_phases()
    assert shared.h[S.H_PHASE_SUM_NS + 2] == 42_000 and shared.h[S.H_PHASE_MAX_NS + 2] == 42_000


def _loop(shared):
    cfg = load_config(None)
    hx = Hexapod(cfg)
    start = hx.lengths(cfg.home_pose) - cfg.strut_offset_mm
    io = SimIO(cfg, 0.0005, tau_s=0.0005, start_pos=start)
    lp = HotLoop(cfg, shared, io, period_s=0.0005)
    lp.run(max_cycles=40)
    assert lp.state == S.ST_IDLE
    return cfg, lp, io


def test_next_setpoint_takes_rows_and_an_empty_ring_while_moving_is_a_fault(shared):
    cfg, lp, io = _loop(shared)
    row = np.zeros((1, 8))
    row[0, :6] = lp.hold
    row[0, 0] += 0.01
    row[0, 6] = 7
    shared.push_rows(row)
    lp.next_setpoint(0)
    assert lp.state == S.ST_RUNNING and lp.line == 7 and lp.hold[0] == row[0, 0] and lp.streaming
    lp.l0[2] += 0.001                                   # the commands were moving
    lp.next_setpoint(1)                                 # ... and the ring is empty, no END row
    assert lp.fault == F_SETPOINT and lp.fault_arg == 1 and lp.state == S.ST_STOPPING


def test_frames_out_clamps_to_the_strut_range_and_records_the_sync(shared):
    cfg, lp, io = _loop(shared)
    n = lp.sends
    lp.out[0] = float(cfg.max_length_mm[0]) + 5.0       # never a target outside the range
    lp.frames_out()
    assert io.target[0] == lp.hi_inc[0]
    assert lp.sends == n + 1
    assert lp.sup.hist[0][lp.sends & lp.sup.mask] == lp.out[0]


class _AliasedDrive:
    """IO whose drive (the CiA 402 state machine of :mod:`drivers.cia402`) receives the controlword
    only on every ``every``-th cycle, phase ``phase`` (a bus at n loop periods, ``sync_every``), and
    answers with its statusword one bus cycle later."""

    def __init__(self, every: int, phase: int, fault_state: int):
        from drivers import cia402
        self.c = cia402
        self.every, self.phase = every, phase
        self.state = [cia402.OPERATION_ENABLED] * 6
        self.state[2] = fault_state
        self.seen = [0] * 6                 # the controlword the drive last received
        self.cw = [0] * 6
        self.statusword = [cia402.drive_statusword(s) | cia402.SW_DRIVE_FOLLOWS for s in self.state]
        self.pos_count = [1] * 6
        self.n = 0

    def set_controlword(self, i, cw):
        self.cw[i] = cw

    def bus_cycle(self):
        self.n += 1
        if self.n % self.every != self.phase:
            return
        c = self.c
        self.statusword = [c.drive_statusword(s) | c.SW_DRIVE_FOLLOWS for s in self.state]
        for i in range(6):
            for _ in range(2):
                new, num = c.drive_step(self.state[i], self.cw[i], self.seen[i])
                self.seen[i] = self.cw[i]
                if not num:
                    break
                self.state[i] = new


@pytest.mark.parametrize("phase", [0, 1])
def test_enable_walk_fault_reset_edge_reaches_a_drive_on_a_bus_at_two_loop_periods(phase):
    """Fault reset (15) on a bus running every 2nd loop cycle: bit 7 is held long enough that the
    drive sees the rising edge whatever the phase (it used to toggle every loop cycle and, in one
    phase, the drive received bit 7 low in every bus cycle: the drive stayed in Fault)."""
    from drivers import cia402
    from hexacnc.daemon.enablewalk import RESET_HOLD_NS
    io = _AliasedDrive(2, phase, cia402.FAULT)
    w = EnableWalk(io, [700.0] * 6, [1350.0] * 6)
    period_ns = 500_000
    w.begin(0)
    act, out = [1000.0] * 6, [0.0] * 6
    for k in range(1, 200):
        r = w.step(k * period_ns, act, out)
        io.bus_cycle()
        if r:
            break
    assert r == 1 and io.state == [cia402.OPERATION_ENABLED] * 6
    assert w.edges[2] == 1 and k * period_ns < RESET_HOLD_NS


def test_enable_walk_waits_for_the_fault_reaction_then_sends_a_fresh_edge():
    """A drive in Fault reaction active gets bit 7 low; once it shows Fault the edge comes."""
    from drivers import cia402
    io = _AliasedDrive(1, 0, cia402.FAULT_REACTION_ACTIVE)
    w = EnableWalk(io, [700.0] * 6, [1350.0] * 6)
    w.cw[2] = cia402.CW_FAULT_RESET                 # bit 7 already high from an earlier attempt
    w.begin(0)
    act, out = [1000.0] * 6, [0.0] * 6
    for k in range(1, 20):
        assert w.step(k * 500_000, act, out) == 0
        io.bus_cycle()
    assert io.state[2] == cia402.FAULT_REACTION_ACTIVE and io.cw[2] == 0 and w.edges[2] == 0
    io.state[2] = cia402.FAULT                      # transition 14: the reaction ended
    for k in range(20, 400):
        r = w.step(k * 500_000, act, out)
        io.bus_cycle()
        if r:
            break
    assert r == 1 and w.edges[2] == 1


def test_enable_walk_names_a_drive_that_stays_in_fault_and_counts_the_edges():
    """A drive whose fault persists: bounded by the walk's time-out, edge after edge, then named."""
    from drivers import cia402
    from hexacnc.daemon.enablewalk import RESET_HOLD_NS, RESET_LOW_NS
    from hexacnc.daemon.faults import F_ENABLE, fault_message
    io = _IO()
    io.pos_count = [1] * 6
    io.statusword = [0x1237] * 6
    io.statusword[2] = 0x0208
    w = EnableWalk(io, [700.0] * 6, [1350.0] * 6)
    w.begin(0)
    act, out = [1000.0] * 6, [0.0] * 6
    t = 0
    while (r := w.step(t, act, out)) == 0:
        t += 1_000_000
    edges = [cw for i, cw in io.sent if i == 2]
    n = edges.count(cia402.CW_FAULT_RESET)
    assert r == -1 and w.bad == 3 and n == w.edges[2] == ENABLE_TIMEOUT_NS // (RESET_HOLD_NS + RESET_LOW_NS) + 1
    assert all(a != b for a, b in zip(edges, edges[1:]))             # low and high alternate
    text = fault_message(F_ENABLE, w.bad, w.arg)
    assert "drive 3" in text and "still in Fault (statusword 0x0208)" in text and f"after {n} fault reset" in text
