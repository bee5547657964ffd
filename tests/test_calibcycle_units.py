"""Calibration cycle pieces without a daemon: true machine, instruments, checks, fit, apply."""
from __future__ import annotations

import json
import math
import tomllib

import numpy as np
import pytest

from hexacnc.calib.apply import apply_result
from hexacnc.calib.cyclefit import fit_cycle
from hexacnc.calib.cyclerun import (RunOptions, _check_reading, approach_pose, check_reachable, load_plan,
                                    retarget_probe, tip_of)
from hexacnc.calib.measurements import Measurements, write_measurements
from hexacnc.calib.output import dumps_toml
from hexacnc.calib.synth import sample_poses
from hexacnc.config import load_config, parse_config
from hexacnc.daemon.calibops import ReadingHistory, _check_values
from hexacnc.errors import ConfigError, DataError
from hexacnc.kinematics import Hexapod
from hexacnc.sag import sag_elongation_mm
from hexacnc.sim.instruments import LaserTracker, TouchProbe, DialIndicator, noise_floor_um
from hexacnc.sim.truth import load_truth, parse_truth, synth_truth_doc
from hexacnc.strutmap import strut_map_from_config


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def commanded_readings(c, X_deg):
    """The drive readings the controller of config ``c`` commands for platform pose X (IK, sag, map)."""
    hx = Hexapod(c)
    L = hx.lengths(X_deg) - sag_elongation_mm(hx, X_deg)
    return strut_map_from_config(c).drive_from_strut(L) - np.asarray(c.strut_offset_mm)


def rad(X):
    return np.r_[X[:3], np.radians(X[3:])]


# -- true machine ---------------------------------------------------------------------------
def test_a_truth_equal_to_the_controller_puts_the_platform_exactly_where_commanded(cfg):
    tm = parse_truth(dict(cfg.raw), "<same>")
    for X in sample_poses(cfg, np.random.default_rng(0), 5):
        Xt = tm.platform_pose_rad(commanded_readings(cfg, X))
        assert np.max(np.abs(Xt[:3] - X[:3])) < 1e-6
        assert np.max(np.abs(np.degrees(Xt[3:]) - X[3:])) < 1e-7


def test_synthetic_truth_has_the_documented_tolerances_and_moves_the_tool_tip(cfg, tmp_path):
    doc = synth_truth_doc(cfg, 4)
    d = np.asarray(doc["geometry"]["base_joints_mm"]) - cfg.base_joints_mm
    assert np.all((np.abs(d) >= 0.1 - 1e-6) & (np.abs(d) <= 0.3 + 1e-6))
    k = np.asarray(doc["struts"]["stiffness_N_per_mm"]) / cfg.stiffness_N_per_mm
    assert np.all(np.abs(k - 1) <= 0.2 + 1e-9)
    g = np.abs(np.asarray(doc["calibration"]["strut_scale"]) - 1)
    assert np.all((g >= 1e-4 - 1e-12) & (g <= 1e-3 + 1e-12))
    p = tmp_path / "t.toml"
    p.write_text(dumps_toml(doc))
    tm = load_truth(p)
    X = np.asarray(cfg.home_pose, dtype=float)
    err = tm.tool_tip_mm(tm.platform_pose_rad(commanded_readings(cfg, X))) - tip_of(cfg, X)[:3]
    assert 0.05 < np.linalg.norm(err) < 5.0           # a few tenths of a mm, not nothing, not absurd
    assert synth_truth_doc(cfg, 4) == doc and synth_truth_doc(cfg, 5) != doc


def test_backlash_moves_the_true_pose_with_the_approach_direction(cfg):
    doc = dict(cfg.raw, truth={"backlash_mm": 0.01})
    tm = parse_truth(doc)
    q = commanded_readings(cfg, np.asarray(cfg.home_pose, dtype=float))
    up = tm.platform_pose_rad(q, np.ones(6))
    down = tm.platform_pose_rad(q, -np.ones(6))
    assert np.linalg.norm(up[:3] - down[:3]) > 0.005


@pytest.mark.parametrize("section,key,value,msg", [
    ("truth", "backlash_mmm", 0.1, "backlash_mmm"),
    ("truth", "backlash_mm", -0.1, "backlash_mm"),
    ("truth", "payload_kg", 5000.0, "payload_kg"),
    ("struts", "stiffness_N_per_mm", -5.0, "stiffness_N_per_mm"),
    ("geometry", "strut_offsets_mm", 650.0, "strut_offsets_mm"),
])
def test_a_truth_file_with_unknown_keys_or_impossible_values_is_refused(cfg, tmp_path, section, key, value, msg):
    doc = synth_truth_doc(cfg, 1)
    doc.setdefault(section, {})[key] = value
    p = tmp_path / "bad.toml"
    p.write_text(dumps_toml(doc))
    with pytest.raises(ConfigError, match=msg) as ei:
        load_truth(p)
    assert str(p) in str(ei.value)


def test_simulation_truth_key_resolves_relative_to_the_config_and_must_exist(cfg, tmp_path):
    doc = dict(cfg.raw, simulation={"truth": "true.toml"})
    with pytest.raises(ConfigError, match=r"\[simulation\] truth"):
        parse_config(dict(doc), str(tmp_path / "m.toml"))
    (tmp_path / "true.toml").write_text("")
    c = parse_config(dict(doc), str(tmp_path / "m.toml"))
    assert c.simulation_truth == str(tmp_path / "true.toml")


# -- instruments ----------------------------------------------------------------------------
def test_instrument_noise_follows_the_documented_model(cfg):
    X = rad(np.asarray(cfg.home_pose, dtype=float))
    tip = np.asarray(cfg.tool.tip_platform_mm)
    tr = LaserTracker(seed=1)
    xs = np.array([[tr.read(X, tip).values[k] for k in "xa"] for _ in range(3000)])
    assert abs(np.std(xs[:, 0]) / tr.sigma_mm(X) - 1) < 0.08
    assert abs(np.std(xs[:, 1]) / tr.sigma_deg - 1) < 0.08
    ind = DialIndicator(seed=2)
    zs = np.array([ind.read(X, tip).values["z"] for _ in range(3000)])
    assert set(ind.read(X, tip).values) == {"z"} and abs(np.std(zs) / ind.sigma_mm - 1) < 0.08
    pr = TouchProbe(seed=3)
    assert pr.read(X + np.r_[50.0, 0, 0, 0, 0, 0], tip).values == {}   # between spheres: no probing
    Xs = rad(retarget_probe(cfg, np.asarray(cfg.home_pose, dtype=float)[None], pr.spheres)[0])
    v = pr.read(Xs, tip).values
    assert set(v) == {"x", "y", "z"}
    floor = noise_floor_um("tracker", X[None], tip)
    assert 0.5 * math.sqrt(3) * tr.sigma_mm(X) * 1e3 < floor < 2 * math.sqrt(3) * tr.sigma_mm(X) * 1e3


# -- run checks -----------------------------------------------------------------------------
def test_unreachable_plan_poses_are_refused_before_any_motion(cfg, tmp_path):
    P = sample_poses(cfg, np.random.default_rng(1), 4)
    P[2, 2] = -2000.0
    with pytest.raises(DataError, match=r"rows 3\b.*nothing moved"):
        check_reachable(cfg, P, 0.3, "plan.csv")
    p = tmp_path / "plan.csv"
    p.write_text("x,y,z,a,b,c\n" + "".join(",".join(map(str, r)) + "\n" for r in P))
    from hexacnc.cli import main
    assert main(["calib", "run", str(p), "--out", str(tmp_path / "m.csv"), "--socket", str(tmp_path / "none.sock")]) == 2
    assert not (tmp_path / "m.csv").exists()
    assert load_plan(p).shape == (4, 6)


def test_approach_pose_makes_every_strut_arrive_extending(cfg):
    hx = Hexapod(cfg)
    for X in sample_poses(cfg, np.random.default_rng(2), 5):
        pre = approach_pose(hx, X, 0.3)
        s = np.linspace(0, 1, 21)[:, None]
        L = hx.inverse_batch(pre[None] + s * (X - pre)[None])
        assert np.all(np.diff(L, axis=0) > 0)


def test_missing_late_and_outlier_readings_are_flagged(cfg):
    hx = Hexapod(cfg)
    X = np.asarray(cfg.home_pose, dtype=float)
    q = (hx.lengths(X) - cfg.strut_offset_mm).tolist()
    good = {"values": dict(zip("xyzabc", X)), "q_mm": q, "target": "platform", "t_s": 100.0, "pair_gap_s": 0.0}
    o = RunOptions()
    assert _check_reading(cfg, hx, good, 99.0, o) == ""
    assert _check_reading(cfg, hx, dict(good, values={}), 99.0, o).startswith("missing")
    assert _check_reading(cfg, hx, dict(good, pair_gap_s=0.5), 99.0, o).startswith("late")
    assert _check_reading(cfg, hx, good, 101.0, o).startswith("late")
    far = dict(good, values=dict(good["values"], z=X[2] + 5.0))
    assert _check_reading(cfg, hx, far, 99.0, o).startswith("outlier")


def test_measurement_op_values_and_time_pairing():
    assert _check_values({"x": 1, "c": 2.5}) == {"x": 1.0, "c": 2.5}
    for bad in ({"w": 1.0}, {"x": float("nan")}, {"x": "1"}, {}):
        with pytest.raises(ValueError):
            _check_values(bad)

    class D:
        class cfg:
            strut_offset_mm = [0.0] * 6
    h = ReadingHistory(D())
    import time
    now = time.time()
    for k in range(5):
        h.t.append(now - 0.4 + 0.1 * k)
        h.q.append(np.full(6, float(k)))
    q, gap = h.at(now - 0.25)
    assert np.allclose(q, 1.5) and gap == pytest.approx(0.05, abs=1e-6)
    with pytest.raises(ValueError, match="late"):
        h.at(now - 100.0)
    with pytest.raises(ValueError, match="future"):
        h.at(now + 10.0)


# -- fit and apply, offline -----------------------------------------------------------------
def _simulated_file(cfg, tm, inst, poses, path):
    tip = np.asarray(cfg.tool.tip_platform_mm)
    qs, ys = [], []
    for X in poses:
        q = commanded_readings(cfg, X)
        r = inst.read(tm.platform_pose_rad(q), tip)
        qs.append(q)
        ys.append([r.values.get(k, np.nan) for k in "xyzabc"])
    write_measurements(path, Measurements(str(path), np.array(qs), np.array(ys)))
    path.with_name(path.name + ".json").write_text(json.dumps({"target": inst.target}))


def _true_rms_um(cfg, tm, poses):
    e = [np.linalg.norm(tm.tool_tip_mm(tm.platform_pose_rad(commanded_readings(cfg, X))) - tip_of(cfg, X)[:3])
         for X in poses]
    return 1e3 * float(np.sqrt(np.mean(np.square(e))))


@pytest.mark.parametrize("seed,magnitude,inst", [(11, 1.0, "tracker"), (12, 2.5, "tracker"), (13, 1.0, "probe"),
                                                 (14, 0.5, "probe")])
def test_fitted_calibration_removes_the_true_machines_errors_on_unseen_poses(cfg, tmp_path, seed, magnitude, inst):
    tm = parse_truth(synth_truth_doc(cfg, seed, magnitude))
    rng = np.random.default_rng(seed)
    fitp, valid = sample_poses(cfg, rng, 40), sample_poses(cfg, rng, 15)
    instrument = LaserTracker(seed) if inst == "tracker" else TouchProbe(seed)
    if inst == "probe":
        fitp, valid = retarget_probe(cfg, fitp, instrument.spheres), retarget_probe(cfg, valid, instrument.spheres)
    _simulated_file(cfg, tm, instrument, fitp, tmp_path / "m.csv")
    cf = fit_cycle(cfg, tmp_path / "m.csv")
    cal = parse_config(tomllib.loads(cf.written["config"]), "<cal>")
    before, after = _true_rms_um(cfg, tm, valid), _true_rms_um(cal, tm, valid)
    assert before > 100.0 * magnitude
    assert after < (0.05 if inst == "tracker" else 0.2) * before      # targets: >= 95 % / >= 80 %
    if inst == "tracker":
        floor = noise_floor_um(inst, np.array([rad(X) for X in valid]), cfg.tool.tip_platform_mm)
        assert after < 1.12 * floor                  # measured: sqrt(after^2 + floor^2) <= 1.5 floor


def test_apply_keeps_the_machine_and_the_old_file_and_refuses_a_bad_result(cfg, tmp_path):
    doc = dict(cfg.raw, daemon=dict(cfg.raw.get("daemon", {}), socket_path="/tmp/own.sock"))
    mach = tmp_path / "machine.toml"
    mach.write_text(dumps_toml(doc))
    res = synth_truth_doc(cfg, 2)
    res.pop("truth")
    res["daemon"] = {"socket_path": "/tmp/other.sock"}
    rp = tmp_path / "fit.toml"
    rp.write_text(dumps_toml(res))
    out = tmp_path / "cal.toml"
    out.write_text("old\n")
    rep = apply_result(rp, mach, out)
    new = load_config(out)
    assert new.daemon.socket_path == "/tmp/own.sock"
    assert np.allclose(new.base_joints_mm, res["geometry"]["base_joints_mm"])
    assert np.allclose(new.calibration.strut_scale, res["calibration"]["strut_scale"])
    assert rep["kept"] and open(rep["kept"]).read() == "old\n"
    assert any("base_joints_mm 1" in ln and "um" in ln for ln in rep["changes"])
    res["calibration"]["strut_scale"] = 5.0
    rp.write_text(dumps_toml(res))
    text = out.read_text()
    with pytest.raises(DataError, match="strut_scale"):
        apply_result(rp, mach, out)
    assert out.read_text() == text


def test_probe_op_fields_are_checked_and_the_model_pose_inverts_the_commands(cfg, tmp_path):
    from hexacnc.daemon.calibprobe import _check, model_tip_pose
    tip, feed, mode = _check({"tip_mm": [1, 2, 3, 0, 0, 0], "feed_mm_min": 300})
    assert mode == "38.2" and feed == 300.0
    for bad in ({"tip_mm": [1, 2, 3], "feed_mm_min": 300}, {"tip_mm": [1, 2, 3, 0, 0, float("inf")], "feed_mm_min": 1},
                {"tip_mm": [0] * 6, "feed_mm_min": 0}, {"tip_mm": [0] * 6, "feed_mm_min": 1e6},
                {"tip_mm": [0] * 6, "feed_mm_min": 10, "mode": "38.6"}):
        with pytest.raises(ValueError):
            _check(bad)
    doc = synth_truth_doc(cfg, 6)              # a calibrated-looking config: strut scale, per-strut stiffness
    doc.pop("truth")
    c = parse_config(doc, "<cal>")
    for X in sample_poses(c, np.random.default_rng(3), 4):
        assert model_tip_pose(c, commanded_readings(c, X)) == pytest.approx(tip_of(c, X), abs=1e-6)
