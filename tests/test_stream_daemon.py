"""Streamed programs in the daemon (hexacnc/daemon/planstream.py): validation of the whole program before
motion by default, with memory bounded by the window; ``[planner] start_before_validated``: motion starts at
the first window and a program found bad ahead stops before the bad line, reported with line and reason;
``[daemon] max_plan_s`` bounds each window, not the program.  Children are forkserver processes."""
from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from hexacnc.bench.camgen import cam_program
from hexacnc.config import load_config
from hexacnc.daemon.planstream import StreamPlan
from hexacnc.daemon.program import program_source
from hexacnc.errors import ConfigError, PlanError
from hexacnc.gcode import program_from_config
from hexacnc.setpoint import FLAG_END
from test_planner_motion import utilisation

ENDLESS = "#1=0\no100 while [1]\n#1=[#1+1]\no100 endwhile\nM2\n"


def _cfg(before=False, window_blocks=60, **daemon):
    base = load_config(None)
    return base.replace(planner=dataclasses.replace(base.planner, window_blocks=window_blocks,
                                                    start_before_validated=before),
                        daemon=dataclasses.replace(base.daemon, **daemon))


def _home(cfg):
    return np.array([*cfg.home_pose[:3], *np.radians(cfg.home_pose[3:])])


def _start(cfg, text):
    sp = StreamPlan(cfg, text, "cam.ngc", _home(cfg), cfg.cycle.period_s)
    return sp, program_source(sp, "cam.ngc", _home(cfg), cfg.cycle.period_s)


def test_default_validates_the_whole_program_before_any_motion():
    cfg = _cfg()
    with pytest.raises(PlanError) as e:
        _start(cfg, cam_program(900, bad_line=850))
    assert e.value.line == 850 and "max_length_mm" in e.value.limit
    text = cam_program(300)
    sp, (src, info) = _start(cfg, text)
    try:
        n = len(program_from_config(text, "cam.ngc", cfg).blocks)
        assert info["validated"] and info["blocks"] == n and not info["duration_exact"]
        assert sp.validation["state"] == "valid" and sp.end_rad is not None
    finally:
        src.close()
    assert not sp.alive()


def test_the_estimated_duration_follows_the_planned_windows_not_the_programmed_feeds():
    """A program of many windows at a feed the struts cannot follow (as 3D_Chips.ngc's F4.5e6): the
    validation's nominal seconds at the programmed feeds (capped at the rapid feed) are a third of the
    planned time; the answer's ``duration_s`` and the time left extrapolate the windows planned so far (a
    fit to nominal seconds and blocks, however many windows are planned when the answer is given: the
    bound holds after any prefix, tests/test_timefit.py) and converge as the planner gets ahead."""
    cfg = _cfg()
    dt = cfg.cycle.period_s
    text = cam_program(800, feed_scale=1000)
    sp, (src, info) = _start(cfg, text)
    totals = []                                   # (elapsed s, elapsed + time left s)
    try:
        assert not info["duration_exact"]
        n, t_end = 0, time.monotonic() + 300
        while not src.finished and time.monotonic() < t_end:
            n += len(src.next_rows(200))           # 0.1 s of motion per 5 ms
            moved = (n - src.sampler.starved_rows) * dt     # rows at rest waiting for the planner left out
            totals.append((moved, moved + src.sampler.progress[1]))
            time.sleep(0.005)
        assert src.finished and sp.error is None
        planned, nominal = sp.planned_s, sp.validation["estimate_s"]
    finally:
        src.close()
    assert planned > 2.5 * nominal, (planned, nominal)           # the feeds say little about the time
    # the first windows hold the approach from home (a rapid: more time per block than the raster)
    assert abs(info["duration_s"] - planned) <= 0.3 * planned, (info["duration_s"], planned, nominal)
    assert abs(totals[0][1] - planned) <= 0.3 * planned, (totals[0], planned)
    half = [tot for t, tot in totals if t >= 0.5 * planned]
    assert half and abs(half[0] - planned) <= 0.1 * planned, (half[:1], planned)


def test_start_before_validated_moves_then_stops_before_the_bad_line():
    cfg = _cfg(before=True)
    bad = 11_000
    sp, (src, info) = _start(cfg, cam_program(12_000, bad_line=bad))
    found = []
    sp.on_invalid = found.append
    rows = []
    try:
        assert not info["validated"]             # moving before the validation got there
        t_end = time.monotonic() + 300
        while not src.finished and time.monotonic() < t_end:
            if found and not src.stopping:
                src.fail(found[0])                # what the daemon does (FeedMixin._program_invalid)
            rows.append(src.next_rows(200))       # 0.1 s of motion per 5 ms: 20x real time
            time.sleep(0.005)
    finally:
        src.close()
    rows = np.vstack(rows)
    # the validator usually finds the bad line first; on a loaded machine the planner's own window
    # check gets there first (consuming at 20x real time): either way the motion stops before it
    assert src.finished and (not found or found[0].line == bad)
    assert isinstance(src.error, PlanError) and src.error.line == bad and "length" in str(src.error)
    assert rows[:, 6].max() < bad
    assert int(rows[-1, 7]) & FLAG_END
    assert max(utilisation(cfg, rows, cfg.cycle.period_s)) <= 1.0
    assert not sp.alive()


@pytest.mark.slow
def test_time_bound_applies_per_window_and_names_the_line():
    cfg = _cfg(max_plan_s=1.0)
    with pytest.raises(PlanError) as e:
        _start(cfg, ENDLESS)
    assert e.value.limit == "max_plan_s" and e.value.line in (2, 3, 4)


def test_new_planner_keys_are_range_checked(tmp_path, repo_root):
    base = (repo_root / "config" / "default.toml").read_text()
    for body, key in (("window_blocks = 3", "window_blocks"), ("window_s = 0.1", "window_s"),
                      ("start_before_validated = 1", "start_before_validated")):
        p = tmp_path / "m.toml"
        p.write_text(base.replace("[planner]\n", f"[planner]\n{body}\n", 1))
        with pytest.raises(ConfigError, match=key):
            load_config(str(p))
    p.write_text(base.replace("[planner]\n", "[planner]\nwindow_blocks = 8\nstart_before_validated = true\n", 1))
    pc = load_config(str(p)).planner
    assert pc.window_blocks == 8 and pc.start_before_validated is True
