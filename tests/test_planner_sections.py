"""Planner: rest-to-rest sections with one speed peak are smoothed by the narrow filter (A/J wide).

Utilisation is measured independently: the nominal rows through ``Hexapod.inverse_batch`` and
finite differences at the cycle period (as in test_planner_motion).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.gcode.blocks import Block
from hexacnc.kinematics import Hexapod
from hexacnc.planner import plan as PP
from hexacnc.planner import plan_program
from hexacnc.pose import matrix_from_euler


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def tip_home(cfg):
    P = np.asarray(cfg.home_pose, dtype=float)
    out = P.copy()
    out[:3] = P[:3] + matrix_from_euler(*np.radians(P[3:])) @ np.asarray(cfg.tool.tip_platform_mm)
    return out


def exact_stop_moves(cfg, moves, feed_mm_s=1e4):
    """Tool-tip translations ``[(length_mm, direction)]`` from the home tip, each ending in an exact stop."""
    p = tip_home(cfg)
    blocks = []
    for i, (d, u) in enumerate(moves):
        u = np.asarray(u, dtype=float)
        q = p.copy()
        q[:3] += d * u / np.linalg.norm(u)
        blocks.append(Block("line", i + 1, p.copy(), q.copy(), feed_mm_s=feed_mm_s, exact_stop=True))
        p = q
    return blocks


def measured(cfg, plan):
    rows = plan.rows()
    P = rows[:, :6].copy()
    P[:, 3:] = np.degrees(P[:, 3:])
    L = Hexapod(cfg).inverse_batch(P)
    dt = plan.dt
    v = np.diff(L, axis=0) / dt
    a = np.diff(v, axis=0) / dt
    j = np.diff(a, axis=0) / dt
    return (float(np.max(np.abs(v) / cfg.max_velocity_mm_s)), float(np.max(np.abs(a) / cfg.max_acceleration_mm_s2)),
            float(np.max(np.abs(j) / cfg.max_jerk_mm_s3)))


MOVES = [(2.0, (1, 0, 0)), (30.0, (0, 1, 0)), (5.0, (0, 0, -1)), (20.0, (-1, -1, 0)), (0.5, (1, 0, 1))]


def test_unimodal():
    assert PP._unimodal(np.array([0.0, 1.0, 3.0, 3.0, 2.0, 0.0]))
    assert PP._unimodal(np.array([0.0, 1.0, 1.0, 0.0]))
    assert not PP._unimodal(np.array([0.0, 3.0, 1.0, 2.0, 0.0]))       # a valley inside
    assert PP._unimodal(np.array([0.0, 0.0]))


@pytest.mark.parametrize("T", [0.005, 0.02, 0.05, 0.2])
def test_plateau_cap_holds_the_peak_for_T(T):
    rng = np.random.default_rng(3)
    sg = np.concatenate([[0.0], np.cumsum(rng.uniform(0.05, 2.0, 60))])
    A = 8000.0
    # a triangle in time: x rises at 2A per mm from both ends (constant acceleration)
    x = np.minimum(2 * A * sg, 2 * A * (sg[-1] - sg))
    c = PP._plateau_cap(sg, x, T)
    assert 0.0 < c <= math.sqrt(x.max())
    flat = (x[:-1] >= c * c) & (x[1:] >= c * c)
    assert np.sum(np.diff(sg)[flat]) / c >= T * (1 - 1e-12)
    # and it is the largest such cap (to the bisection's resolution): 1 % more no longer holds
    c2 = c * 1.01
    flat2 = (x[:-1] >= c2 * c2) & (x[1:] >= c2 * c2)
    assert np.sum(np.diff(sg)[flat2]) / c2 < T


def test_plateau_cap_keeps_a_long_cruise():
    sg = np.linspace(0.0, 100.0, 201)
    x = np.minimum(np.minimum(2e4 * sg, 2e4 * (100.0 - sg)), 250.0 ** 2)
    assert PP._plateau_cap(sg, x, 0.0275) == pytest.approx(250.0)


def test_exact_stop_moves_use_the_narrow_filter_and_stay_within_limits(cfg, monkeypatch):
    blocks = exact_stop_moves(cfg, MOVES)
    calls = []
    orig = PP._filtered_table

    def spy(*a):
        r = orig(*a)
        calls.append(r[3])
        return r

    monkeypatch.setattr(PP, "_filtered_table", spy)
    plan = plan_program(blocks, cfg)
    assert all(calls[-1]), f"every rest-to-rest straight move has one speed peak: {calls[-1]}"
    v, a, j = measured(cfg, plan)
    assert v <= 1.0 and a <= PP.ETA + 1e-3 and j <= PP.ETA + 1e-3, (v, a, j)
    assert max(plan.utilisation.values()) <= 1.0
    # the motion really rests at every exact stop (at least two rows at the same pose)
    rows = plan.rows()
    ends = [b.end for b in blocks]
    for e in ends[:-1]:
        d = np.linalg.norm(rows[:, :3] - _platform_xyz(cfg, e)[None, :], axis=1)
        assert np.count_nonzero(d < 1e-9) >= 2


def _platform_xyz(cfg, tip):
    tip = np.asarray(tip, dtype=float)
    R = matrix_from_euler(*np.radians(tip[3:]))
    return tip[:3] - R @ np.asarray(cfg.tool.tip_platform_mm)


def test_narrow_filter_is_faster_than_the_full_one(cfg, monkeypatch):
    blocks = exact_stop_moves(cfg, MOVES)
    narrow = plan_program(blocks, cfg)
    monkeypatch.setattr(PP, "NARROW_MARGIN", 1e9)          # never narrower than the full filter
    full = plan_program(blocks, cfg)
    # measured 0.510 s against 0.5665 s: each section ends one filter width (2 A/J -> 1.1 A/J) sooner,
    # less what capping the short moves' peaks costs
    assert narrow.duration_s < 0.95 * full.duration_s, (full.duration_s, narrow.duration_s)
    assert measured(cfg, full)[2] <= PP.ETA + 1e-3


def test_a_section_with_a_valley_keeps_the_full_filter(cfg, monkeypatch):
    """Two lines meeting at a blended right-angle corner: the speed dips at the corner, so the
    section has a valley and is smoothed by the full filter."""
    p0 = tip_home(cfg)
    p1 = p0.copy()
    p1[0] += 30.0
    p2 = p1.copy()
    p2[1] += 30.0
    blocks = [Block("line", 1, p0, p1, feed_mm_s=1e4, blend_tolerance_mm=0.2),
              Block("line", 2, p1, p2, feed_mm_s=1e4, blend_tolerance_mm=0.2)]
    calls = []
    orig = PP._filtered_table

    def spy(*a):
        r = orig(*a)
        calls.append(r[3])
        return r

    monkeypatch.setattr(PP, "_filtered_table", spy)
    plan = plan_program(blocks, cfg)
    assert calls[-1] == [False]
    assert measured(cfg, plan)[2] <= PP.ETA + 1e-3
