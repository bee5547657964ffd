"""Planner: moves between exact stops and a blended corner, measured independently.

Utilisation is measured independently: the nominal rows through ``Hexapod.inverse_batch`` and
finite differences at the cycle period (test_planner_motion.utilisation).
"""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.gcode.blocks import Block
from hexacnc.planner import plan_program
from hexacnc.planner import profile as PF
from hexacnc.pose import matrix_from_euler

from test_planner_motion import tip_of, utilisation


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def tip_home(cfg):
    return tip_of(cfg, cfg.home_pose)


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


MOVES = [(2.0, (1, 0, 0)), (30.0, (0, 1, 0)), (5.0, (0, 0, -1)), (20.0, (-1, -1, 0)), (0.5, (1, 0, 1))]


def test_exact_stop_moves_stay_within_limits_and_rest_at_every_stop(cfg):
    blocks = exact_stop_moves(cfg, MOVES)
    plan = plan_program(blocks, cfg)
    v, a, j = utilisation(cfg, plan.rows(), plan.dt)
    assert v <= 1.0 and a <= PF.ETA + 1e-3 and j <= PF.ETA + 1e-3, (v, a, j)
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


def test_blended_corner_between_exact_stops_stays_within_limits(cfg):
    """Two lines meeting at a blended right-angle corner: the speed dips at the corner (a valley
    between two plateaus)."""
    p0 = tip_home(cfg)
    p1 = p0.copy()
    p1[0] += 30.0
    p2 = p1.copy()
    p2[1] += 30.0
    blocks = [Block("line", 1, p0, p1, feed_mm_s=1e4, blend_tolerance_mm=0.2),
              Block("line", 2, p1, p2, feed_mm_s=1e4, blend_tolerance_mm=0.2)]
    plan = plan_program(blocks, cfg)
    v, a, j = utilisation(cfg, plan.rows(), plan.dt)
    assert v <= 1.0 and a <= PF.ETA + 1e-3 and j <= PF.ETA + 1e-3, (v, a, j)
