"""Planner: short moves (down to 1 um, from rest and back to back), programs without motion, Cartesian
soft limits.  Utilisation measured from the sampler's rows by exact inverse kinematics and finite differences
(:func:`test_planner_motion.utilisation`)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.errors import PlanError
from hexacnc.gcode.factory import machine_defaults, program_from_config
from hexacnc.planner import FLAG_END, plan_program
from hexacnc.planner.softlimits import outside
from test_planner_motion import run, utilisation

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def _plan(cfg, text, **kw):
    return plan_program(program_from_config(text, "t.ngc", cfg).blocks, cfg, **kw)


def _single(cfg, axis: str, length: float):
    return _plan(cfg, f"G21 G91\nG1 {axis}{length:.7f} F6000\nM2\n")


@pytest.mark.parametrize("axis", ["X", "Z"])
def test_single_moves_from_rest_are_planned_and_time_is_monotonic_in_length(cfg, axis):
    """1 um .. 30 mm from rest to rest (before: <= 0.1 mm refused, time falling with length around 0.1 mm)."""
    lengths = np.geomspace(1e-3, 30.0, 24)
    dur = []
    for d in lengths:
        p = _single(cfg, axis, d)
        dur.append(p.duration_s)
        assert max(p.utilisation.values()) <= 1.0
    assert np.all(np.diff(dur) >= 0), list(zip(lengths.round(6), dur))


def test_a_1um_move_moves_1um_within_limits(cfg):
    p = _single(cfg, "X", 0.001)
    rows = run(p.sampler())
    tip = p.path.tip(p.path.piece_at(np.array([0.0, p.path.total])), np.array([0.0, p.path.total]))
    assert np.linalg.norm(tip[1, :3] - tip[0, :3]) == pytest.approx(0.001, abs=1e-9)
    assert int(rows[-1, 7]) & FLAG_END
    uv, ua, uj = utilisation(cfg, rows, p.dt)
    assert max(uv, ua, uj) <= 1.0


@pytest.mark.parametrize("mode", ["G61", "G64 P0.01"])
def test_back_to_back_tiny_moves_are_planned_within_limits(cfg, mode):
    dirs = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (-1, 0, 1), (0, -1, -1)]
    for d in (0.001, 0.01, 0.1):
        lines = ["G21 G91", mode]
        for k in range(12):
            u = np.array(dirs[k % 6], float)
            u = d * u / np.linalg.norm(u)
            lines.append(f"G1 X{u[0]:.7f} Y{u[1]:.7f} Z{u[2]:.7f} F3000")
        p = _plan(cfg, "\n".join(lines) + "\nM2\n")
        rows = run(p.sampler())
        assert max(utilisation(cfg, rows, p.dt)) <= 1.0
        assert p.path.total == pytest.approx(12 * d, rel=0.05)


def test_back_to_back_exact_stop_moves_time_is_monotonic(cfg):
    dur = []
    for d in np.geomspace(1e-3, 5.0, 12):
        lines = ["G21 G91 G61"] + [f"G1 X{d:.7f} F3000", f"G1 Y{d:.7f}", f"G1 Z{d:.7f}"] * 3
        dur.append(_plan(cfg, "\n".join(lines) + "\nM2\n").duration_s)
    assert np.all(np.diff(dur) >= 0), dur


@pytest.mark.parametrize("text", ["", "(only a comment)\n", "M2\n", "G21 G90\nM2\n", "%\n%\n"])
def test_programs_without_motion_finish_cleanly_where_the_machine_stands(cfg, text):
    start = [3.0, -2.0, -1120.0, 1.0, 0.0, 0.0]
    p = _plan(cfg, text, start_pose=start)
    assert p.duration_s >= 0 and max(p.utilisation.values()) == 0.0
    rows = run(p.sampler())
    assert rows.shape[0] >= 1 and int(rows[-1, 7]) & FLAG_END
    tip = p.path.tip(np.zeros(1, dtype=np.int64), np.zeros(1))[0]
    assert np.allclose(tip[:3], start[:3]) and np.allclose(np.degrees(tip[3:]), start[3:])
    assert np.ptp(rows[:, :6], axis=0).max() == 0.0          # no motion at all
    json.dumps(p.summary())                                   # a plain JSON summary


def test_a_dwell_and_m0_without_motion(cfg):
    p = _plan(cfg, "G4 P0.2\nM0\nM3 S1000\nM2\n")
    assert p.duration_s >= 0.2
    assert len(p.pause_idx) == 1
    assert [e[2] for e in p.events][:2] == ["dwell", "pause"]
    s = p.sampler()
    out = np.empty((100, 8))
    n = 0
    while not s.done and n < 5000:
        n += s.next_rows(out)
        if s.state == "program_paused":
            s.resume()
    assert s.done


def test_empty_program_on_the_cli_exits_0(tmp_path):
    f = tmp_path / "empty.ngc"
    f.write_text("")
    r = subprocess.run([sys.executable, "-m", "hexacnc", "plan", "--json", str(f)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["duration_s"] >= 0
    assert "Traceback" not in r.stderr


def test_x400_beyond_a_150mm_workspace_is_refused_naming_line_and_limit(cfg):
    assert cfg.workspace_max[0] == 150.0
    with pytest.raises(PlanError) as ei:
        _plan(cfg, "G21 G90\nG1 X10 F600\nG0 X400\nM2\n")
    assert ei.value.line == 3
    assert ei.value.limit == "workspace max x"
    assert "150" in str(ei.value)


def test_an_arc_bulging_out_of_the_workspace_is_refused_though_its_end_points_are_inside(cfg):
    # a half circle of radius 140 mm around the home tip: both ends at x = +-140, its top at y = 140 + 20
    text = "G21 G90\nG1 X140 Y20 F3000\nG3 X-140 Y20 I-140 J0\nM2\n"
    with pytest.raises(PlanError) as ei:
        _plan(cfg, text)
    assert ei.value.line == 3 and ei.value.limit == "workspace max y"


def test_the_box_holds_exactly_where_the_platform_pose_is_inside(cfg):
    home = np.asarray(cfg.home_pose, dtype=float)
    under, over = outside(cfg, np.array([home, home + [151, 0, 0, 0, 0, 0], home + [0, 0, 0, 0, -16, 0]]))
    assert not under[0].any() and not over[0].any()
    assert over[1, 0] and under[2, 4]
    # inside the box: planned
    start = machine_defaults(cfg)["start_pose"]
    assert start[0] == 0.0
    _plan(cfg, "G21 G90\nG1 X140 Y-140 F3000\nM2\n")
