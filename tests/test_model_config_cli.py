"""Config loader errors, the per-cycle transform's guards, and `hexacnc kin` from outside."""
from __future__ import annotations

import math
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from hexacnc.config import default_config_path, load_config, parse_config
from hexacnc.errors import ConfigError
from hexacnc.kinematics import Hexapod
from hexacnc import transform as T

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)

REPO = Path(__file__).resolve().parents[1]


def default_doc():
    return tomllib.loads(default_config_path().read_text())


def test_default_config_is_a_plausible_machine():
    cfg = load_config(None)
    L = Hexapod(cfg).lengths(cfg.home_pose)
    assert 800 < L.mean() < 1200          # struts around 1 m
    assert 10 <= cfg.mass_kg <= 500        # tens of kg
    assert cfg.cycle.period_s == 0.0005


@pytest.mark.parametrize("mutate, words", [
    (lambda d: d["struts"].update(bogus=1), ["[struts]", "bogus", "unknown"]),
    (lambda d: d.update(extra={"a": 1}), ["[extra]", "unknown section"]),
    (lambda d: d["geometry"].update(base_joints_mm=[[0, 0, 0]] * 5), ["base_joints_mm", "6 rows"]),
    (lambda d: d["struts"].update(max_velocity_mm_s=math.nan), ["max_velocity_mm_s", "nan"]),
    (lambda d: d["struts"].update(max_velocity_mm_s=-5.0), ["max_velocity_mm_s", "-5.0"]),
    (lambda d: d["joints"].update(max_angle_deg=[30, math.nan, 30, 30, 30, 30]),
     ["max_angle_deg", "element 2", "value nan is not finite"]),
    (lambda d: d["struts"].update(max_velocity_mm_s=[100, 100, -5, 100, 100, 100]),
     ["max_velocity_mm_s", "element 3", "value -5.0 must be greater than 0.0"]),
    (lambda d: d["struts"].update(min_length_mm="short"), ["min_length_mm", "'short'"]),
    (lambda d: d["joints"].update(base_axes=[[0, 0, 2]] * 6), ["base_axes", "unit vector"]),
    (lambda d: d["carrier"].pop("mass_kg"), ["mass_kg", "missing"]),
    (lambda d: d["planner"].update(noop_m_codes=[3]), ["noop_m_codes", "built-in"]),
    (lambda d: d["planner"].update(noop_m_codes=[428, 428]), ["noop_m_codes", "M428", "twice"]),
    (lambda d: d["planner"].update(noop_m_codes="M428"), ["noop_m_codes", "list"]),
    (lambda d: d["geometry"].update(platform_joints_mm=[[0, 0, 0]] * 6), ["singular"]),
    (lambda d: d["workspace"].update(home_pose=[0, 0, -100, 0, 0, 0]), ["home_pose", "outside", "-100"]),
    (lambda d: d["workspace"].update(home_pose=[0, 0, -100, 0, 0, 0], max=[150, 150, 0, 15, 15, 20]),
     ["home_pose", "min_length_mm"]),
])
def test_config_errors_name_file_key_and_value(mutate, words):
    doc = default_doc()
    mutate(doc)
    with pytest.raises(ConfigError) as ei:
        parse_config(doc, "machine.toml")
    msg = str(ei.value)
    assert "machine.toml" in msg
    for w in words:
        assert w.lower() in msg.lower(), msg


def test_config_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[geometry\nx=1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)


@pytest.fixture()
def ct():
    return T.CycleTransform(load_config(None))


def home_rad(cfg):
    p = np.array(cfg.home_pose, dtype=float)
    p[3:] = np.radians(p[3:])
    return [float(v) for v in p]


def test_transform_matches_model_and_compensates(ct):
    cfg, hx = ct.cfg, ct.hx
    from hexacnc import sag
    p = np.array([20.0, -30.0, -870.0, 4.0, -6.0, 12.0])
    X = p.copy()
    X[3:] = np.radians(X[3:])
    ct.set_thermal_offsets_mm([0.01, 0.02, 0.0, -0.01, 0.005, 0.0])
    assert ct.command(*X) == T.OK
    e = sag.sag_elongation_mm(hx, p)
    assert np.allclose(ct.length_mm, hx.lengths(p), atol=1e-10)
    assert np.allclose(ct.cmd_mm, hx.lengths(p) - e - np.array(ct.thermal_mm), atol=1e-10)
    # ideal drives reach the command: feedback recovers the pose
    ct.reset_pose(X)
    assert ct.feedback(ct.cmd_mm) == T.OK
    assert np.allclose(ct.pose_act, X, atol=1e-8)


def test_transform_guards(ct):
    X = home_rad(ct.cfg)
    assert ct.command(*X) == T.OK
    ct.reset(ct.cmd_mm)
    safe = list(ct.cmd_mm)
    # a jump of 5 mm in one 0.5 ms cycle is 10 m/s
    assert ct.command(X[0] + 5.0, *X[1:]) == T.LIMIT_VELOCITY
    assert ct.cmd_mm == safe and "velocity" in ct.describe(T.LIMIT_VELOCITY)
    # 0.01 mm from standstill in one cycle: 40 mm/s fine, 40000 mm/s^2 too much
    assert ct.command(X[0] + 0.01, *X[1:]) == T.LIMIT_ACCELERATION
    assert ct.command(X[0], X[1], -300.0, *X[3:]) == T.LIMIT_LENGTH
    assert "strut" in ct.describe(T.LIMIT_LENGTH)
    assert ct.command(X[0], X[1], X[2], math.radians(70), X[4], X[5]) in (T.LIMIT_JOINT, T.LIMIT_LENGTH)
    assert ct.command(math.nan, *X[1:]) == T.LIMIT_INPUT
    assert ct.cmd_mm == safe


def run_cli(*args, cwd=None):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "hexacnc", *args], capture_output=True, text=True,
                          env=env, cwd=cwd, timeout=60)


def test_kin_cli_round_trip(tmp_path):
    cfg = load_config(None)
    hx = Hexapod(cfg)
    rng = np.random.default_rng(11)
    P = rng.uniform(cfg.workspace_min, cfg.workspace_max, size=(200, 6))
    P = P[~hx.batch_violations(P)][:50]
    poses = tmp_path / "poses.csv"
    poses.write_text("x,y,z,a,b,c\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in P) + "\n")
    out = tmp_path / "lengths.csv"
    r = run_cli("kin", "inverse", "--poses", str(poses), "--out", str(out))
    assert r.returncode == 0, r.stderr
    lines = out.read_text().splitlines()
    assert lines[0] == "L1,L2,L3,L4,L5,L6,q1,q2,q3,q4,q5,q6"
    data = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    assert np.allclose(data[:, :6], hx.inverse_batch(P), atol=1e-9)
    q = tmp_path / "q.csv"
    q.write_text("q1,q2,q3,q4,q5,q6\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in data[:, 6:]) + "\n")
    r = run_cli("kin", "forward", "--readings", str(q))
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].split(",")[:7] == ["x", "y", "z", "a", "b", "c", "iterations"]
    back = np.array([[float(v) for v in ln.split(",")[:6]] for ln in lines[1:]])
    assert np.max(np.abs(back - P)) < 1e-9


@pytest.mark.parametrize("content, words", [
    ("x,y,z,a,b\n0,0,-900,0,0\n", ["missing column", "c"]),
    ("x,y,z,a,b,c\n0,0,-900,0,0,nan\n", ["line 2", "column c", "not finite"]),
    ("x,y,z,a,b,c\n0,0,-900,0,0,0\n0,0,-200,0,0,0\n", ["row 2", "min_length_mm"]),
    ("x,y,z,a,b,c\n0,0,abc,0,0,0\n", ["line 2", "column z"]),
    ("x,y,z,a,b,c\n", ["no data rows"]),
])
def test_kin_cli_bad_input_writes_nothing(tmp_path, content, words):
    poses = tmp_path / "poses.csv"
    poses.write_text(content)
    out = tmp_path / "out.csv"
    r = run_cli("kin", "inverse", "--poses", str(poses), "--out", str(out))
    assert r.returncode != 0
    for w in words:
        assert w in r.stderr, r.stderr
    assert not out.exists()
    assert list(tmp_path.iterdir()) == [poses]


def test_generated_fast_path_equals_general_path():
    cfg = load_config(None)
    hx = Hexapod(cfg)
    fast = T.CycleTransform(cfg, hx)
    slow = T.CycleTransform(cfg, hx, fast=False)
    rng = np.random.default_rng(12)
    P = rng.uniform(cfg.workspace_min, cfg.workspace_max, size=(400, 6))
    P[:, 3:] = np.radians(P[:, 3:])
    P[::7, 2] = -300.0                   # some length violations
    P[::11, 3] = math.radians(70.0)      # some joint violations
    for ct in (fast, slow):
        ct.set_thermal_offsets_mm([0.01, -0.02, 0.0, 0.03, 0.0, -0.01])
        ct.set_spindle_growth_mm(0.004)
    for X in P:
        fast._have_prev = slow._have_prev = 0      # guard tested elsewhere
        cf, cs = fast.command(*X), slow.command(*X)
        assert cf == cs
        assert fast.fail_index == slow.fail_index if cf else True
        if cf == T.OK:
            assert np.allclose(fast.cmd_mm, slow.cmd_mm, rtol=0, atol=1e-11)
            assert np.allclose(fast.sag_mm, slow.sag_mm, rtol=1e-9, atol=1e-14)
            meas = [v + 1e-4 * (i - 2.5) for i, v in enumerate(fast.cmd_mm)]
            fast.reset_pose(X)
            slow.reset_pose(X)
            assert fast.feedback(meas) == slow.feedback(meas) == T.OK
            assert np.allclose(fast.pose_act, slow.pose_act, rtol=0, atol=1e-8)


def test_packaged_default_equals_config_default():
    packaged = REPO / "hexacnc" / "data" / "default.toml"
    assert packaged.read_text() == (REPO / "config" / "default.toml").read_text(), \
        "hexacnc/data/default.toml must be a copy of config/default.toml (it serves non-editable installs)"


def test_demo_program_plans_on_the_default_machine():
    from hexacnc.gcode import program_from_config
    from hexacnc.planner import plan_program
    cfg = load_config(None)
    text = (REPO / "hexacnc" / "data" / "demo.ngc").read_text()
    plan = plan_program(program_from_config(text, "demo.ngc", cfg).blocks, cfg)
    assert plan.duration_s > 1.0
    assert max(plan.utilisation.values()) <= 1.0
