"""Standard errors of every parameter, the tool-tip uncertainty map, and ``calib plan --separate`` (issue 17)."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from hexacnc.calib import synth
from hexacnc.calib.diagnose import Options, fit_model
from hexacnc.calib.model import Context, forward_batch
from hexacnc.calib.uncertainty import grid_poses, tool_tip_covariance
from hexacnc.cli import main as cli
from hexacnc.config import load_config
from hexacnc.kinematics import Hexapod
from hexacnc.pose import matrices_from_euler


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def tip_error(cfg, theta_fit, theta_true, P):
    """Tool-tip position error (N,3) of the true machine driven by the calibrated model's readings."""
    hf, ht = Hexapod.from_parameters(cfg, theta_fit), Hexapod.from_parameters(cfg, theta_true)
    q = hf.inverse_batch(P) - hf.offset[None]
    X0 = P.copy()
    X0[:, 3:] = np.radians(X0[:, 3:])
    X, ok = forward_batch(ht.base, ht.plat, q + ht.offset[None], X0)
    assert ok.all()
    tip = np.asarray(cfg.tool.tip_platform_mm, dtype=float)
    return (X[:, :3] + matrices_from_euler(X[:, 3:]) @ tip) - (P[:, :3] + matrices_from_euler(X0[:, 3:]) @ tip)


def test_tool_tip_uncertainty_matches_the_errors_of_refits(cfg):
    """Over noise realisations, the tool-tip errors of the calibrated machine scatter as the map predicts."""
    seed = int.from_bytes(os.urandom(4), "little")
    P = grid_poses(cfg, 5, 2)
    z2 = []
    for k in range(6):
        s = synth.generate(cfg, seed + k, "none", n_fit=60, n_holdout=1, sessions=1)
        ctx = Context(cfg, s.fit, s.noise_mm, s.noise_deg)
        r = fit_model(cfg, ctx, [], None, Options())
        C = tool_tip_covariance(cfg, r, P)
        e = tip_error(cfg, r.theta[:42], s.theta_true, P)
        z2.append(np.einsum("ni,nij,nj->n", e, np.linalg.inv(C), e))   # chi^2 with 3 dof per pose
    m = float(np.mean(z2))
    assert 1.0 < m < 6.0, (seed, m)     # 3 expected (30 seeds: 2.7); the grid points of one fit are correlated


def test_every_parameter_has_a_standard_error_and_the_map_is_reported(cfg, tmp_path):
    s = synth.generate(cfg, int.from_bytes(os.urandom(4), "little") % 100000, "elastic_sag", n_fit=60,
                       n_holdout=20)
    fit_csv, hold_csv = tmp_path / "fit.csv", tmp_path / "hold.csv"
    synth.write_set(s, fit_csv, hold_csv)
    out, rep = tmp_path / "d.json", tmp_path / "rep"
    assert cli(["diagnose", "--config", cfg.path, "--data", str(fit_csv), "--holdout", str(hold_csv),
                "--noise-mm", str(s.noise_mm), "--noise-deg", str(s.noise_deg), "--frame", "base",
                "--causes", "elastic_sag,strut_scale", "--json", str(out), "--report", str(rep)]) == 0
    j = json.loads(out.read_text())
    names = [p["name"] for p in j["parameters"]]
    assert len(names) == 43 and "compliance_mm_per_kN" in names
    assert all(p["std"] > 0 for p in j["parameters"])
    tm = j["uncertainty"]["tool_tip_map"]
    assert tm["points"] == len(tm["rows"]) > 20 and tm["columns"][-1] == "sigma_position_mm"
    assert 0 < tm["sigma_position_mm"]["median"] <= tm["sigma_position_mm"]["max"] < 0.05
    data = np.genfromtxt(rep / "uncertainty_map.csv", delimiter=",", names=True)
    assert len(data) == tm["points"] and (rep / "uncertainty_map.png").exists()


def test_plan_separate_beats_a_random_plan(cfg, tmp_path):
    out = tmp_path / "sep.csv"
    js = tmp_path / "sep.json"
    assert cli(["calib", "plan", "--config", cfg.path, "--poses", "50", "--measure", "xyz", "--candidates", "400",
                "--separate", "elastic_sag,strut_scale", "--out", str(out), "--json", str(js),
                "--seed", str(int.from_bytes(os.urandom(2), "little"))]) == 0
    j = json.loads(js.read_text())
    for c in ("elastic_sag", "strut_scale"):
        assert j["separation_planned"][c]["parameter_std_rms"] < j["separation_random_plan"][c]["parameter_std_rms"]
    rows = np.genfromtxt(out, delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert len(rows) == 50 and {0.0} < set(rows["payload_kg"].tolist())   # both payload levels planned
    assert cli(["calib", "plan", "--config", cfg.path, "--poses", "5", "--separate", "gravity"]) == 2
