"""``time_loss`` of ``hexacnc bench plan`` (hexacnc.bench.planloss): the planner's stages re-run on a path give
times that only grow from stage to stage and end at the planner's own duration."""
from __future__ import annotations

import pytest

from hexacnc.bench.planloss import time_loss
from hexacnc.config import load_config
from hexacnc.planner import plan as PL
from hexacnc.planner import plan_program

from test_planner_retime import _zigzag


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def test_stage_times_grow_and_end_at_the_plan(cfg, monkeypatch):
    monkeypatch.setattr(PL, "RETIME", False)
    blocks = _zigzag(cfg, n=6)
    r = time_loss(blocks, cfg)
    plan = plan_program(blocks, cfg)
    assert r["hexacnc_s"] == round(plan.duration_s, 4)
    assert 0 < r["topp_at_limits_s"] <= r["topp_spread_s"] + 1e-9 <= r["raw_s"] + 2e-9
    assert r["raw_s"] + r["holds_s"] <= r["hexacnc_s"] + 1e-9
    rows = r["rows"]
    assert all(0.0 <= rows[k] <= 1.0 for k in ("at_velocity", "at_acceleration", "at_jerk", "slack"))
    assert 0.0 <= rows["time_scaling_bound_s"] < r["hexacnc_s"]
