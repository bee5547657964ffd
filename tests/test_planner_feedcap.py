"""The rapid feed caps every feed (hexacnc/planner/rawmoves.py, blocktime.py), as LinuxCNC's maximum velocity
caps every move: a G1 or G93 move asking more than ``[planner] rapid_feed_mm_min`` runs no faster than a G0
over the same path (before, ``G1 X100 F2400000`` planned 0.221 s against 0.450 s for ``G0 X100``); feeds
below it are untouched; the nominal seconds that bound ``max_block_s`` and feed the time estimates agree; a
feed override above 100 % stops at the rapid feed too (the sampler's override cap)."""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.gcode.factory import program_from_config
from hexacnc.planner import plan_program
from hexacnc.planner.blocktime import block_seconds
from test_planner_motion import run


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def _plan(cfg, move):
    prog = program_from_config(f"G21 G90 G64 P0.01\n{move}\nM2\n", "cap.ngc", cfg)
    moves = [b for b in prog.blocks if b.line == 2]
    return plan_program(prog.blocks, cfg), moves


def _tip_speed_mm_s(plan) -> float:
    tip = plan.path.tip(plan.path.piece_at(plan.s_tab), plan.s_tab)[:, :3]
    return float(np.max(np.linalg.norm(np.diff(tip, axis=0), axis=1)) / plan.dt)


def test_no_feed_runs_faster_than_the_rapid_feed(cfg):
    rapid_mm_s = cfg.planner.rapid_feed_mm_min / 60.0
    g0, _ = _plan(cfg, "G0 X100")
    for move in ("G1 X100 F2400000", "G93 G1 X100 F1000"):        # 40 m/s; 100 mm in 0.06 s
        p, (blk,) = _plan(cfg, move)
        assert p.duration_s >= g0.duration_s - 2 * p.dt, (move, p.duration_s, g0.duration_s)
        assert _tip_speed_mm_s(p) <= rapid_mm_s * 1.001, move
        assert block_seconds(blk, rapid_mm_s, 1.0) == pytest.approx(100.0 / rapid_mm_s)
    assert _tip_speed_mm_s(g0) > 0.9 * rapid_mm_s           # the struts let this path reach the rapid feed


def test_the_plan_summary_names_the_moves_the_rapid_feed_caps(cfg):
    text = "G21 G90\nG1 X10 F3000\nG1 X20 F2400000\nG93 G1 X30 F100000\nG93 G1 X40 F60\nG94 G0 X0\nM2\n"
    s = plan_program(program_from_config(text, "cap.ngc", cfg).blocks, cfg).summary()
    assert (s["feed_capped_moves"], s["feed_capped_first_line"]) == (2, 3)      # lines 3 and 4; not 2, 5, 6
    s = plan_program(program_from_config("G21 G90\nG1 X10 F3000\nG0 X0\nM2\n", "ok.ngc", cfg).blocks,
                     cfg).summary()
    assert (s["feed_capped_moves"], s["feed_capped_first_line"]) == (0, None)
    s = plan_program(program_from_config("G4 P0.1\nM2\n", "dwell.ngc", cfg).blocks, cfg).summary()
    assert s["feed_capped_moves"] == 0


def test_feeds_below_the_rapid_feed_are_kept(cfg):
    rapid_mm_s = cfg.planner.rapid_feed_mm_min / 60.0
    g0, _ = _plan(cfg, "G0 X100")
    p, (blk,) = _plan(cfg, "G1 X100 F3000")                  # 50 mm/s
    assert 2.0 <= p.duration_s < 2.0 + 1.0 and p.duration_s > 3 * g0.duration_s
    assert _tip_speed_mm_s(p) == pytest.approx(50.0, rel=0.01)
    assert block_seconds(blk, rapid_mm_s, 1.0) == pytest.approx(2.0)
    p, (blk,) = _plan(cfg, "G93 G1 X100 F30")                # 2 s
    assert 2.0 <= p.duration_s < 3.0
    assert block_seconds(blk, rapid_mm_s, 1.0) == pytest.approx(2.0)


def _tip_speeds_at_override(cfg, plan, feed_override: float) -> np.ndarray:
    """Tool-tip speeds (mm/s) of the sampler's rows at a feed override, from the platform rows."""
    from hexacnc.pose import matrix_from_euler
    s = plan.sampler()
    s.set_override(feed_override)
    X = run(s, chunk=4000)
    tip_platform = np.asarray(cfg.tool.tip_platform_mm, dtype=float)
    tip = np.array([x[:3] + matrix_from_euler(*x[3:6]) @ tip_platform for x in X])
    return np.linalg.norm(np.diff(tip, axis=0), axis=1) / plan.dt


@pytest.mark.parametrize("move, at_2x_mm_s", [
    ("G2 X0 Y0 I50 J0 P10 F9000", 250.0),   # 10 circles at 150 mm/s: 300 mm/s at 200 % before the cap
    ("G0 X100", 250.0),
    ("G1 X100 F600", 20.0)])                # far below the rapid feed: twice as fast
def test_a_feed_override_above_100_percent_stops_at_the_rapid_feed(cfg, move, at_2x_mm_s):
    """At 200 % feed override no move runs faster than the rapid feed (the cap's ramp may pass it by a little
    for a few cycles); below it the override still doubles the speed where the plan has headroom."""
    rapid_mm_s = cfg.planner.rapid_feed_mm_min / 60.0
    plan, _ = _plan(cfg, move)
    v2 = _tip_speeds_at_override(cfg, plan, 2.0)
    assert v2.max() <= rapid_mm_s * 1.01
    assert v2.max() == pytest.approx(at_2x_mm_s, rel=0.01), v2.max()
