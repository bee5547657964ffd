"""Final time scaling (hexacnc.planner.retime): never slower, rows within the targets measured independently
(Hexapod.inverse_batch + finite differences at the cycle period), stops still held for as long."""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.gcode.blocks import Block
from hexacnc.planner import plan as PL
from hexacnc.planner import plan_program
from hexacnc.planner.retime import retime

from test_planner_motion import rapid_lifted, utilisation
from test_planner_sections import exact_stop_moves

TARGETS = (0.995, 0.95, 0.95)


@pytest.fixture(scope="module")
def cfg():
    return rapid_lifted(load_config(None))        # the time scaling knows the strut limits only


def _rows(plan, s):
    return plan.platform_at(s)


def _rest_runs(s: np.ndarray) -> list:
    """Lengths of the runs of consecutive equal rows (standstills) strictly inside the table."""
    still = np.concatenate([[False], s[1:] == s[:-1]])
    d = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    a, b = np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]
    return [int(y - x) for x, y in zip(a, b) if x > 1 and y < s.shape[0]]


def test_retime_faster_within_targets_and_holds_kept(cfg, monkeypatch):
    blocks = exact_stop_moves(cfg, [(2.0, (1, 0, 0)), (80.0, (0, 1, 0)), (8.0, (-1, 1, 1)), (120.0, (1, 0, 0))])
    monkeypatch.setattr(PL, "RETIME", False)            # the table before the pass
    plan = plan_program(blocks, cfg)
    dt = plan.dt
    r = retime(plan.path, plan.hexapod, plan.s_tab, dt, cfg.max_velocity_mm_s, cfg.max_acceleration_mm_s2,
               cfg.max_jerk_mm_s3, TARGETS)
    assert r.rounds >= 0, "the time scaling found no table within the targets"
    s = r.s_tab
    assert s.shape[0] < plan.s_tab.shape[0]                     # faster (rest to rest moves leave room)
    assert s[0] == plan.s_tab[0] and s[-1] == plan.s_tab[-1]
    assert np.all(np.diff(s) >= 0)
    uv, ua, uj = utilisation(cfg, _rows(plan, s), dt)
    assert uv <= TARGETS[0] + 1e-9 and ua <= TARGETS[1] + 1e-9 and uj <= TARGETS[2] + 1e-9, (uv, ua, uj)
    # every stop rests at least as long as before (the rate is 1 wherever the table rests)
    old, new = _rest_runs(plan.s_tab), _rest_runs(s)
    assert len(new) == len(old) and all(n >= o for n, o in zip(new, old)), (old, new)
    # the new time of every old row is increasing and ends at the new duration
    assert np.all(np.diff(r.t_of_old) > 0)
    assert abs(r.t_of_old[-1] - (s.shape[0] - 1) * dt) <= dt


def test_retime_keeps_a_table_without_room(cfg):
    """A table whose every moving row is at its target cannot be run faster: the pass returns it."""
    blocks = exact_stop_moves(cfg, [(10.0, (1, 0, 0))])
    plan = plan_program(blocks, cfg)
    r = retime(plan.path, plan.hexapod, plan.s_tab, plan.dt, cfg.max_velocity_mm_s, cfg.max_acceleration_mm_s2,
               cfg.max_jerk_mm_s3, (1e-3, 1e-3, 1e-3))
    assert r.rounds == -1 and r.s_tab is plan.s_tab and r.gain == 1.0


def test_plan_with_retime_is_shorter_within_limits_and_dwells_rest(cfg, monkeypatch):
    """In plan_program: never longer than without the pass, rows within the shares (independent finite
    differences), a dwell still rests for its time on its line, the table ends where it did."""
    from test_planner_motion import tip_of
    home = np.array(cfg.home_pose, dtype=float)
    t0, t1, t2 = (tip_of(cfg, home + d) for d in ([0] * 6, [60, 0, 0, 0, 0, 0], [60, 40, -20, 3, 0, 0]))
    blocks = [Block("line", 1, t0, t1, feed_mm_s=1e4, blend_tolerance_mm=0.5), Block("dwell", 2, seconds=0.3),
              Block("line", 3, t1, t2, feed_mm_s=1e4, blend_tolerance_mm=0.5),
              Block("line", 4, t2, t0, feed_mm_s=1e4, blend_tolerance_mm=0.5)]
    monkeypatch.setattr(PL, "RETIME", False)
    before = plan_program(blocks, cfg)
    monkeypatch.setattr(PL, "RETIME", True)
    plan = plan_program(blocks, cfg)
    assert plan.duration_s <= before.duration_s
    rows = plan.rows()
    uv, ua, uj = utilisation(cfg, rows, plan.dt)
    assert uv <= 0.9995 and ua <= 0.95 + 1e-9 and uj <= 0.95 + 1e-9, (uv, ua, uj)
    assert max(plan.utilisation.values()) <= 0.9995
    on2 = rows[rows[:, 6] == 2]
    assert on2.shape[0] * plan.dt >= 0.3 and np.ptp(on2[:, :3], axis=0).max() < 1e-9
    assert np.array_equal(rows[-1, :6], before.rows()[-1, :6])


def _zigzag(cfg, n=10, step_mm=6.0, blend_mm=0.05):
    """Short lines meeting at 90-degree corners with small blends (slow corners, as in dense CAM paths),
    feeds lifted so that the strut limits bind."""
    from test_planner_motion import tip_of
    home = np.array(cfg.home_pose, dtype=float)
    pts = [home.copy()]
    for k in range(n):
        d = np.zeros(6)
        d[k % 2] = step_mm * (1 if (k // 2) % 2 == 0 else -1)
        pts.append(pts[-1] + d)
    tips = [tip_of(cfg, p) for p in pts]
    return [Block("line", k + 1, tips[k], tips[k + 1], feed_mm_s=1e4, blend_tolerance_mm=blend_mm)
            for k in range(n)]


def test_shaped_rate_stays_below_the_room_and_rises_faster_on_slow_rows():
    """The shaped rate never exceeds the room R, is at least 1, and where the rows move slowly (small strut
    velocity l1) it reaches a room peak that it cannot reach where they move fast (same accelerations)."""
    from hexacnc.planner.retime import _shaped_rate, _slope_room
    n, dt = 400, 5e-4
    R = np.ones(n)
    R[170:230] = 2.0                                        # a short stretch with room
    lims = (np.full(6, 500.0), np.full(6, 5000.0), np.full(6, 2e5), (0.995, 0.95, 0.95), 1.0)
    peak = {}
    for name, l1 in (("slow", 1.0), ("fast", 200.0)):
        rates = (np.full((n, 6), l1), np.full((n, 6), 100.0), np.full((n, 6), 1000.0))
        r = _shaped_rate(R, _slope_room(R, rates, dt, lims, 12), dt, 12)
        assert np.all(r <= R + 1e-12) and np.all(r >= 1.0)
        peak[name] = float(r.max())
    assert peak["slow"] > 1.2 and peak["fast"] < peak["slow"], peak


def test_retime_on_slow_blended_corners_is_shorter_and_within_targets(cfg, monkeypatch):
    """Dense corners (the case the shaped rate is for): the retimed table is shorter than the verified one,
    never goes back, and its rows are within the targets measured independently (Hexapod.inverse_batch,
    finite differences at the cycle period).  The table is the one of the former, wider filter
    (``FILTER_JERK_SHARE`` 0.9: 0.965 s, retimed 0.9365 s), which leaves the room this pass is for; the default
    filter plans the zigzag in 0.921 s and leaves none (the pass then keeps the table: rounds -1)."""
    monkeypatch.setattr(PL, "RETIME", False)
    monkeypatch.setattr(PL, "FILTER_JERK_SHARE", 0.9)
    plan = plan_program(_zigzag(cfg), cfg)
    r = retime(plan.path, plan.hexapod, plan.s_tab, plan.dt, cfg.max_velocity_mm_s, cfg.max_acceleration_mm_s2,
               cfg.max_jerk_mm_s3, TARGETS)
    assert r.rounds >= 0 and r.s_tab.shape[0] < plan.s_tab.shape[0]
    assert np.all(np.diff(r.s_tab) >= 0) and r.s_tab[-1] == plan.s_tab[-1]
    uv, ua, uj = utilisation(cfg, _rows(plan, r.s_tab), plan.dt)
    assert uv <= TARGETS[0] + 1e-9 and ua <= TARGETS[1] + 1e-9 and uj <= TARGETS[2] + 1e-9, (uv, ua, uj)
