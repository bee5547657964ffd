"""Identification of the 42 parameters, calibrated config, test plan (hexacnc.calib)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from hexacnc.calib import synth
from hexacnc.calib.diagnose import Options, fit_model
from hexacnc.calib.identify import parameter_table, unidentifiable_directions
from hexacnc.calib.measurements import write_measurements
from hexacnc.calib.model import Context, initial_frame
from hexacnc.calib.plan import plan
from hexacnc.cli import main as cli
from hexacnc.config import load_config
from hexacnc.errors import DataError


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def test_full_pose_fit_recovers_geometry_within_reported_uncertainty(cfg):
    s = synth.generate(cfg, 11, "none", n_fit=100, n_holdout=10, sessions=1)
    ctx = Context(cfg, s.fit, s.noise_mm, s.noise_deg)
    res = fit_model(cfg, ctx, [], None, Options(prior_joint_mm=5.0))
    err = res.theta[:42] - s.theta_true
    sd = np.array([p["std"] for p in parameter_table(res)])[:42]
    z = err / sd
    # normalised errors behave like N(0,1): RMS near 1, nothing wild
    assert 0.6 < np.sqrt(np.mean(z ** 2)) < 1.5, z
    assert np.max(np.abs(z)) < 4.5
    assert 0.7 < res.chi2_red < 1.3
    # the fit moved the parameters from nominal by much more than it is now wrong
    assert np.sqrt(np.mean((s.theta_true - res.layout.theta0[:42]) ** 2)) > 10 * np.sqrt(np.mean(err ** 2))


def test_registered_frame_fit(cfg):
    s = synth.generate(cfg, 12, "none", n_fit=80, n_holdout=10, registration=True, sessions=1)
    ctx = Context(cfg, s.fit, s.noise_mm, s.noise_deg)
    res = fit_model(cfg, ctx, [], initial_frame(cfg, s.fit), Options())
    r = res.rms()
    assert r["position_mm"] < 2.0 * s.noise_mm * np.sqrt(3)
    assert r["strut_mm"] is not None and r["strut_mm"] < 0.02
    # registration and a rigid motion of all base joints are the same thing: reported as unidentified
    dirs = unidentifiable_directions(res)
    assert len(dirs) >= 6
    names = {c["name"] for d in dirs for c in d["combination"]}
    assert any(n.startswith("frame_") for n in names) and any(n.startswith("base") for n in names)


def test_cli_fit_writes_loadable_config_and_report(cfg, tmp_path):
    s = synth.generate(cfg, 13, "none", n_fit=60, n_holdout=5, sessions=1)
    data = tmp_path / "m.csv"
    write_measurements(data, s.fit)
    out = tmp_path / "cal.toml"
    rep = tmp_path / "rep"
    hold = tmp_path / "h.csv"
    write_measurements(hold, s.holdout)
    rc = cli(["calib", "fit", "--config", cfg.path, "--data", str(data), "--out", str(out), "--report", str(rep),
              "--noise-mm", "0.005", "--noise-deg", "0.0005", "--frame", "base", "--holdout", str(hold)])
    assert rc == 0
    cal = load_config(out)
    err_before = np.abs(np.r_[cfg.base_joints_mm.ravel(), cfg.platform_joints_mm.ravel()] - s.theta_true[:36])
    err_after = np.abs(np.r_[cal.base_joints_mm.ravel(), cal.platform_joints_mm.ravel()] - s.theta_true[:36])
    assert np.sqrt(np.mean(err_after ** 2)) < 0.1 * np.sqrt(np.mean(err_before ** 2))
    assert np.allclose(cal.strut_offset_mm, s.theta_true[36:], atol=0.2)
    j = json.loads((rep / "report.json").read_text())
    assert j["rms_fit"]["strut_mm"] < 0.02 and len(j["parameters"]) == 42
    assert j["holdout"]["rows_evaluated"] == 5 and j["holdout"]["rms"]["position_mm"] < 0.03
    assert (rep / "report.md").exists() and (rep / "residuals_workspace.png").stat().st_size > 1000


def test_too_few_measurements_is_a_clear_error_and_writes_nothing(cfg, tmp_path):
    s = synth.generate(cfg, 14, "none", n_fit=20, n_holdout=5, measure_set="z", sessions=1)
    data = tmp_path / "m.csv"
    write_measurements(data, s.fit)
    out = tmp_path / "cal.toml"
    with pytest.raises(DataError, match="20 measured coordinates"):
        from hexacnc.commands import calib
        import argparse
        p = argparse.ArgumentParser()
        calib.configure(p)
        args = p.parse_args(["fit", "--config", cfg.path, "--data", str(data), "--out", str(out),
                             "--report", str(tmp_path / "rep")])
        calib.main(args)
    assert not out.exists()
    assert not (tmp_path / "rep").exists()
    assert [f.name for f in tmp_path.iterdir()] == ["m.csv"]


def test_plan_beats_random_and_names_what_z_only_cannot_identify(cfg):
    full = plan(cfg, 30, "xyzabc", candidates=600, seed=1)
    assert full["indices"]["unidentifiable"] == 0
    assert full["indices"]["O1"] > full["indices_random_plan"]["O1"]
    assert full["indices"]["condition_number"] < full["indices_random_plan"]["condition_number"]
    hx_ok = np.all(np.isfinite(full["readings_mm"]))
    assert hx_ok and len(full["poses"]) == 30
    z = plan(cfg, 60, "z", candidates=600, seed=1)
    # a z probe cannot see x/y translations of the whole machine nor rotations about z
    assert z["indices"]["unidentifiable"] >= 3
    assert z["indices"]["condition_number"] == np.inf
    names = {c["name"] for d in z["unidentifiable"] for c in d["combination"]}
    assert any(n.startswith("base") for n in names)
    with pytest.raises(DataError, match="xyzabc"):
        plan(cfg, 10, "q")


def test_cli_plan_and_synth_write_files(cfg, tmp_path):
    out = tmp_path / "plan.csv"
    rep = tmp_path / "plan.json"
    assert cli(["calib", "plan", "--config", cfg.path, "--poses", "12", "--measure", "xyzabc",
                "--candidates", "300", "--out", str(out), "--json", str(rep)]) == 0
    lines = out.read_text().splitlines()
    assert lines[0] == "x,y,z,a,b,c,q1,q2,q3,q4,q5,q6" and len(lines) == 13
    from hexacnc.kinematics import Hexapod
    hx = Hexapod(cfg)
    for ln in lines[1:]:
        v = [float(x) for x in ln.split(",")]
        assert hx.limit_violations(v[:6]) == []
        assert np.allclose(hx.readings(v[:6]), v[6:], atol=1e-5)
    assert json.loads(rep.read_text())["indices"]["rank"] == 42
    f, h, t = tmp_path / "f.csv", tmp_path / "h.csv", tmp_path / "t.json"
    assert cli(["calib", "synth", "--config", cfg.path, "--effect", "backlash", "--seed", "3", "--poses", "20",
                "--holdout-poses", "5", "--out", str(f), "--holdout", str(h), "--truth", str(t)]) == 0
    assert json.loads(t.read_text())["effect"] == "backlash"
    from hexacnc.calib.measurements import load_measurements
    assert load_measurements(f).n == 20 and load_measurements(h).n == 5
    assert cli(["calib", "synth", "--config", cfg.path, "--effect", "gremlins", "--out", str(f),
                "--holdout", str(h)]) == 2


def test_sag_signature_matches_static_strut_forces(cfg):
    """The elastic_sag basis (batch) equals hexacnc.sag.strut_forces_N (per pose), payload at the tool tip."""
    from hexacnc.calib.measurements import Measurements
    from hexacnc.calib.model import _sag_basis
    from hexacnc.kinematics import Hexapod
    from hexacnc.sag import strut_forces_N
    hx = Hexapod(cfg)
    P = synth.sample_poses(cfg, np.random.default_rng(1), 6)
    m = Measurements("x", np.zeros((6, 6)), np.zeros((6, 6)))
    m.payload_kg = np.array([0.0, 5.0, 10.0, 0.0, 3.0, 40.0])
    ctx = Context(cfg, m, 0.01, 0.001)
    X = P.copy()
    X[:, 3:] = np.radians(X[:, 3:])
    B = _sag_basis(ctx, X, hx.base, hx.plat)[..., 0] * 1e3
    ref = np.array([strut_forces_N(hx, p, payload_kg=w) for p, w in zip(P, m.payload_kg)])
    assert np.allclose(B, ref, rtol=1e-9, atol=1e-9)


def test_z_probe_fit_reports_what_it_cannot_see(cfg, tmp_path):
    s = synth.generate(cfg, 15, "none", n_fit=120, n_holdout=5, measure_set="z", sessions=1)
    data = tmp_path / "z.csv"
    write_measurements(data, s.fit)
    out = tmp_path / "cal.toml"
    js = tmp_path / "fit.json"
    assert cli(["calib", "fit", "--config", cfg.path, "--data", str(data), "--out", str(out),
                "--noise-mm", "0.005", "--json", str(js)]) == 0
    rep = json.loads(js.read_text())
    assert rep["frame_registration"] is False and rep["rms_fit"]["strut_mm"] is None
    assert rep["rms_fit"]["position_mm"] < 2 * 0.005
    # a z probe cannot tell x/y translations of the whole machine: held by the priors, named
    assert len(rep["unidentifiable"]) >= 3
    load_config(out)
