"""Hot loop logic in-process: the cycle against the in-process drive model (no bus, no second process).

Each fault path must end in the controlled stop with the cause latched, drives disabled, and every
command sent inside the strut length range and the velocity/acceleration limits.
"""
import dataclasses
import math

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.daemon import shm as S
from hexacnc.daemon.faults import (F_DEADLINE, F_EMCY, F_FOLLOWING, F_HEARTBEAT, F_LIMIT, F_SETPOINT)
from hexacnc.daemon.feed import ArraySource, check_rows, point_to_point
from hexacnc.daemon.loop import CMD_STALL, HotLoop
from hexacnc.daemon.simio import SimIO
from hexacnc.daemon.stopgen import STOP_SHARE, StrutStop
from hexacnc.kinematics import Hexapod
from hexacnc.transform import LIMIT_ACCELERATION, LIMIT_LENGTH, LIMIT_VELOCITY

PERIOD = 0.0005


def _cfg(**cycle):
    cfg = load_config(None)
    c = dict(max_overruns_in_row=100000)    # in-process without RT: no deadline faults unless asked
    c.update(cycle)
    return cfg.replace(cycle=dataclasses.replace(cfg.cycle, **c))


class RecordingIO(SimIO):
    """SimIO that keeps every target it sent."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.log = []
        self.cw_log = []

    def send(self):
        self.log.append(list(self.target))
        return super().send()

    def set_controlword(self, i, cw):
        self.cw_log.append((len(self.log), i, cw))
        super().set_controlword(i, cw)


@pytest.fixture
def rig():
    made = []

    def make(cfg=None, tau_s=0.0005):
        cfg = cfg or _cfg()
        hx = Hexapod(cfg)
        start = hx.lengths(cfg.home_pose) - cfg.strut_offset_mm
        sh = S.Shared(create=True)
        io = RecordingIO(cfg, PERIOD, tau_s=tau_s, start_pos=start)
        lp = HotLoop(cfg, sh, io, period_s=PERIOD)
        made.append(sh)
        lp.run(max_cycles=40)                 # enable walk and seed
        assert sh.h[S.H_STATE] == S.ST_IDLE and sh.h[S.H_READY] == 1
        return cfg, hx, sh, io, lp

    yield make
    for sh in made:
        sh.close()


def _pose(sh):
    h, s = sh.read_status()
    return np.array(s[S.S_POSE_CMD:S.S_POSE_CMD + 6])


def _run(lp, n):
    lp.run(max_cycles=lp.sh.h[S.H_CYCLES] + n)


def assert_commands_within_limits(cfg, io, skip=0):
    """Every target inside the increments of the length range; steps within v and a limits."""
    k = cfg.bus.increments_per_mm
    T = np.array(io.log[skip:], dtype=float)
    assert len(T) > 3
    L = T / k + np.asarray(cfg.strut_offset_mm)
    assert np.all(L >= np.asarray(cfg.min_length_mm) - 1e-9)
    assert np.all(L <= np.asarray(cfg.max_length_mm) + 1e-9)
    v = np.abs(np.diff(L, axis=0)) / PERIOD
    assert np.all(v <= np.asarray(cfg.max_velocity_mm_s) * 1.02 + 2.0 / k / PERIOD)
    a = np.abs(np.diff(L, 2, axis=0)) / PERIOD ** 2
    assert np.all(a <= np.asarray(cfg.max_acceleration_mm_s2) * 1.05 + 4.0 / k / PERIOD ** 2)


def _moving_rows(cfg, hx, sh, target_deg, feed=300.0):
    rows = point_to_point(cfg, hx, _pose(sh), target_deg, feed, PERIOD)
    return rows


def _push(sh, rows):
    assert sh.push_rows(rows) == len(rows)


# -- controlled stop profile -------------------------------------------------------------------
def test_strut_stop_respects_limits_from_random_feasible_states():
    cfg = load_config(None)
    vmax, amax, jmax = 500.0, 5000.0, 2e5
    st = StrutStop([vmax] * 6, [amax] * 6, [jmax] * 6, [700.0] * 6, [1350.0] * 6, PERIOD)
    rng = np.random.default_rng(7)
    for _ in range(300):
        v = rng.uniform(-vmax, vmax, 6)
        a = rng.uniform(-amax, amax, 6)
        ok = np.abs(v + a * np.abs(a) / (2 * jmax)) <= vmax     # could still stop within vmax
        v, a = np.where(ok, v, 0.0), np.where(ok, a, 0.0)
        l0 = np.full(6, 1000.0)
        l1 = l0 - v * PERIOD
        l2 = l1 - (v - a * PERIOD) * PERIOD
        st.start(l0, l1, l2)
        hist = [l1.copy(), l0.copy()]
        out = [0.0] * 6
        n = 0
        while st.step(out):
            hist.append(np.array(out))
            n += 1
            assert n < 5000
        hist += [np.array(out)] * 3
        H = np.array(hist)
        V = np.diff(H, axis=0) / PERIOD
        A = np.diff(V, axis=0) / PERIOD
        J = np.diff(A, axis=0) / PERIOD
        assert np.abs(V).max() <= vmax + 1e-6
        assert np.abs(A).max() <= amax + 1e-6
        assert np.abs(J[1:]).max() <= jmax * (1 + 1e-6)
        assert np.all(V[-2:] == 0.0)                           # at rest at the end
        # stopping time close to the time-optimal bound (v + a^2/2j)/amax + 2 amax/jmax at the stop's share
        am, jm = STOP_SHARE * amax, STOP_SHARE * jmax
        bound = np.max((np.abs(v) + a * a / (2 * jm)) / am) + 2 * am / jm + 0.01
        assert n * PERIOD <= bound


def test_ring_and_histogram_percentiles():
    sh = S.Shared(create=True)
    try:
        rows = np.arange(40, dtype=float).reshape(5, 8)
        assert sh.push_rows(rows) == 5 and sh.ring_fill() == 5
        assert [sh.ring[8 * 4 + j] for j in range(8)] == rows[4].tolist()
        hist = [0] * S.HIST_BINS
        hist[10] = 998
        hist[200] = 1
        hist[4095] = 1
        assert S.percentiles_us(hist) == [11.0, 11.0, 201.0]
        assert S.percentiles_us([0] * 16) == [None, None, None]
        # rows written across the ring's end, in order; the write index published once
        sh.h[S.H_RING_R] = sh.h[S.H_RING_W] = S.RING_ROWS - 3
        more = np.random.default_rng(3).normal(size=(7, 8))
        assert sh.push_rows(more) == 7 and sh.h[S.H_RING_W] == S.RING_ROWS + 4
        got = [[sh.ring[((S.RING_ROWS - 3 + k) % S.RING_ROWS) * 8 + j] for j in range(8)] for k in range(7)]
        assert got == more.tolist()
        assert sh.push_rows(np.zeros((0, 8))) == 0 and sh.ring_fill() == 7
    finally:
        sh.close()


# -- normal motion -------------------------------------------------------------------------------
def test_move_follows_ik_and_ends_idle(rig):
    cfg, hx, sh, io, lp = rig()
    target = [20.0, -10.0, -880.0, 2.0, -1.0, 3.0]
    rows = _moving_rows(cfg, hx, sh, target)
    n0 = len(io.log)
    _push(sh, rows)
    _run(lp, len(rows) + 50)
    assert sh.h[S.H_FAULT] == 0 and sh.h[S.H_STATE] == S.ST_IDLE
    # the last targets equal the IK (with sag) of the end pose within one increment
    from hexacnc.transform import CycleTransform
    ct = CycleTransform(cfg, period_s=PERIOD)
    X = rows[-1, :6]
    assert ct.command(*X) == 0
    want = [round((ct.cmd_mm[i] - cfg.strut_offset_mm[i]) * cfg.bus.increments_per_mm) for i in range(6)]
    assert all(abs(a - b) <= 1 for a, b in zip(io.log[-1], want))
    assert_commands_within_limits(cfg, io, n0 - 2)
    h, s = sh.read_status()
    assert np.allclose(s[S.S_POSE_ACT:S.S_POSE_ACT + 3], target[:3], atol=0.01)


# -- faults --------------------------------------------------------------------------------------
def _fault_then_checks(cfg, sh, io, lp, code, n0):
    assert sh.h[S.H_FAULT] == code, (sh.h[S.H_FAULT], code)
    assert sh.h[S.H_STATE] == S.ST_FAULT
    assert io.cw_log and io.cw_log[-1][2] == 0x0000                 # disable voltage sent
    assert all((sw & 0x6F) != 0x27 for sw in io.statusword)          # nobody enabled any more
    assert_commands_within_limits(cfg, io, max(0, n0 - 2))


def test_setpoint_outside_limits_stops_from_motion(rig):
    cfg, hx, sh, io, lp = rig()
    rows = _moving_rows(cfg, hx, sh, [60.0, 0.0, -880.0, 0.0, 0.0, 0.0], feed=400.0)
    half = len(rows) // 2
    bad = rows[:half].copy()
    bad[-1, 0] += 5.0                        # a jump: velocity far beyond the strut limit
    n0 = len(io.log)
    _push(sh, bad)
    _run(lp, half + 600)
    _fault_then_checks(cfg, sh, io, lp, F_LIMIT, n0)
    assert sh.h[S.H_FAULT_ARG] in (LIMIT_VELOCITY, LIMIT_ACCELERATION)
    # it was moving when it faulted: the stop took more than a few cycles
    L = np.array(io.log[n0:], float)
    moving = np.any(np.abs(np.diff(L, axis=0)) > 0, axis=1)
    assert moving[half:].sum() > 20


def test_unreachable_setpoint_is_refused_without_motion(rig):
    cfg, hx, sh, io, lp = rig()
    p = _pose(sh)
    row = np.zeros((1, 8))
    row[0, :6] = p
    row[0, 2] = -2000.0                      # struts far beyond max length
    n0 = len(io.log)
    _push(sh, row)
    _run(lp, 100)
    _fault_then_checks(cfg, sh, io, lp, F_LIMIT, n0)
    assert sh.h[S.H_FAULT_ARG] == LIMIT_LENGTH


def test_heartbeat_loss_during_motion(rig):
    cfg, hx, sh, io, lp = rig()
    rows = _moving_rows(cfg, hx, sh, [40.0, 0.0, -900.0, 0.0, 0.0, 0.0])
    n0 = len(io.log)
    _push(sh, rows)
    _run(lp, len(rows) // 2)
    io.hb_lost[2] = True
    _run(lp, int(cfg.bus.heartbeat_timeout_ms * 1e-3 / PERIOD) + 600)
    _fault_then_checks(cfg, sh, io, lp, F_HEARTBEAT, n0)
    assert sh.h[S.H_FAULT_STRUT] == 3


def test_emcy_during_motion(rig):
    cfg, hx, sh, io, lp = rig()
    rows = _moving_rows(cfg, hx, sh, [40.0, 0.0, -900.0, 0.0, 0.0, 0.0])
    n0 = len(io.log)
    _push(sh, rows)
    _run(lp, len(rows) // 2)
    io.emcy(4, 0x2310)
    _run(lp, 600)
    _fault_then_checks(cfg, sh, io, lp, F_EMCY, n0)
    assert sh.h[S.H_FAULT_STRUT] == 5 and sh.h[S.H_FAULT_ARG] == 0x2310


def test_following_error_of_a_stuck_strut(rig):
    cfg, hx, sh, io, lp = rig()
    rows = _moving_rows(cfg, hx, sh, [60.0, 0.0, -900.0, 0.0, 0.0, 0.0], feed=300.0)
    n0 = len(io.log)
    _push(sh, rows)
    _run(lp, 100)
    io.stuck[0] = True
    _run(lp, len(rows) + 600)
    _fault_then_checks(cfg, sh, io, lp, F_FOLLOWING, n0)
    assert sh.h[S.H_FAULT_STRUT] == 1
    assert sh.h[S.H_FAULT_ARG] > cfg.cycle.following_error_mm * 1000


def test_dead_setpoint_source_while_moving_and_at_rest(rig):
    cfg, hx, sh, io, lp = rig()
    rows = _moving_rows(cfg, hx, sh, [40.0, 0.0, -900.0, 0.0, 0.0, 0.0])
    n0 = len(io.log)
    _push(sh, rows[: len(rows) // 2])        # the source dies half-way, no END row
    _run(lp, len(rows) // 2 + 600)
    _fault_then_checks(cfg, sh, io, lp, F_SETPOINT, n0)
    assert sh.h[S.H_FAULT_ARG] == 1          # ran empty while moving
    # reset: fault reset + re-enable by controlword, then a stream that stalls at rest
    sh.command(S.CMD_RESET)
    _run(lp, 60)
    assert sh.h[S.H_STATE] == S.ST_IDLE and sh.h[S.H_FAULT] == 0
    p = _pose(sh)
    hold = np.zeros((10, 8))
    hold[:, :6] = p                           # standing still, not flagged END
    _push(sh, hold)
    _run(lp, 10 + int(cfg.cycle.setpoint_timeout_s / PERIOD) + 50)
    assert sh.h[S.H_FAULT] == F_SETPOINT and sh.h[S.H_FAULT_ARG] == 2


def test_deadline_burst_while_moving(rig):
    cfg, hx, sh, io, lp = rig(_cfg(max_overruns_in_row=3))
    rows = _moving_rows(cfg, hx, sh, [40.0, 0.0, -900.0, 0.0, 0.0, 0.0])
    n0 = len(io.log)
    _push(sh, rows)
    _run(lp, len(rows) // 3)
    sh.command(CMD_STALL, 20_000)            # the loop sleeps 20 ms once: 40 deadlines missed
    _run(lp, 600)
    _fault_then_checks(cfg, sh, io, lp, F_DEADLINE, n0)
    assert sh.h[S.H_FAULT_ARG] > 3 and sh.h[S.H_MAX_IN_ROW] > 3


# -- feeding ----------------------------------------------------------------------------------
def test_point_to_point_rows_within_limits_and_refusal():
    cfg = load_config(None)
    hx = Hexapod(cfg)
    start = np.r_[cfg.home_pose[:3], np.radians(cfg.home_pose[3:])]
    rows = point_to_point(cfg, hx, start, [100.0, 50.0, -800.0, 10.0, -5.0, 15.0], 1000.0, PERIOD)
    check_rows(cfg, hx, rows, PERIOD)
    assert rows[-1, 7] == S.FLAG_END and np.allclose(rows[-1, :3], [100.0, 50.0, -800.0])
    from hexacnc.errors import KinematicsError
    with pytest.raises(KinematicsError, match="strut"):
        point_to_point(cfg, hx, start, [0.0, 0.0, -2000.0, 0.0, 0.0, 0.0], 100.0, PERIOD)


def test_array_source_pause_decelerates_along_the_path():
    cfg = load_config(None)
    hx = Hexapod(cfg)
    start = np.r_[cfg.home_pose[:3], np.radians(cfg.home_pose[3:])]
    rows = point_to_point(cfg, hx, start, [100.0, 0.0, -900.0, 0.0, 0.0, 0.0], 200.0, PERIOD)
    src = ArraySource(cfg, hx, rows, PERIOD)
    out = [src.next_rows(int(0.2 / PERIOD))]
    src.pause()
    out.append(src.next_rows(int(1.0 / PERIOD)))
    assert src.at_rest and not src.finished
    src.resume()
    while not src.finished:
        out.append(src.next_rows(1000))
    allrows = np.vstack(out)
    check_rows(cfg, hx, allrows, PERIOD)                 # the warp stays within the strut limits
    assert np.allclose(allrows[:, 1:3], rows[0, 1:3])    # on the path (a line along x)
    assert np.all(np.diff(allrows[:, 0]) >= -1e-12)      # never backwards
    assert allrows[-1, 7] == S.FLAG_END and allrows[-1, 0] == pytest.approx(100.0)


def test_thermal_and_spindle_offsets_are_slewed_into_the_commands(rig):
    cfg, hx, sh, io, lp = rig()
    before = np.array(io.log[-1], float)
    for i in range(6):
        sh.s[S.S_THERMAL_TGT + i] = 0.010 * (i + 1)      # struts grew 10..60 um
    n0 = len(io.log)
    _run(lp, 2000)                                       # 1 s: at most 2 um/s of slew
    h, s = sh.read_status()
    app = np.array(s[S.S_THERMAL_APP:S.S_THERMAL_APP + 6])
    assert np.all(app > 0.0015) and np.all(app <= 0.002 * 1.03 + 2e-5)     # slew-limited
    after = np.array(io.log[-1], float)
    # a longer strut is commanded shorter by the growth (increments of 0.1 um)
    assert np.allclose((before - after) / cfg.bus.increments_per_mm, app, atol=2e-4)
    assert_commands_within_limits(cfg, io, n0)
    assert sh.h[S.H_FAULT] == 0
