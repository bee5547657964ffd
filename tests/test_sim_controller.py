"""Figure 7: the coupled state controller settles faster than the per-strut cascade at the worst position."""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.sim.controller import StepExperiment, compare, step_metrics
from hexacnc.sim.dynamics import CoupledModel, eigen_grid, tune_conventional, workspace_grid


@pytest.fixture(scope="module")
def result():
    cfg = load_config()
    model = CoupledModel(cfg)
    worst = np.asarray(eigen_grid(model, workspace_grid(cfg, n_xyz=3))["worst_pose"])
    gains, _ = tune_conventional(model, worst)
    return compare(model, gains, worst, dz_mm=0.05, duration_s=0.25, rhos=(1.0, 3.0, 10.0, 100.0)), model, gains, worst


def test_coupled_settles_faster_than_cascade(result):
    r, *_ = result
    assert r["dead_time_s"] == pytest.approx(0.0015)
    assert np.isfinite(r["conventional"]["settling_time_s"])
    assert r["coupled"]["settling_time_s"] < r["conventional"]["settling_time_s"]
    assert r["coupled"]["overshoot_pct"] <= 10.0
    for k in ("conventional", "coupled"):
        assert r[k]["final_um"] == pytest.approx(50.0, abs=1.0)
    assert r["coupled"]["peak_drive_force_N"] <= r["force_budget"] * r["conventional"]["peak_drive_force_N"]


def test_coupled_controller_survives_model_error(result):
    # heavier carrier, softer struts than designed for: still stable, settled, and faster
    m = result[0]["model_error_check"]
    assert np.isfinite(m["coupled"]["settling_time_s"])
    assert m["coupled"]["final_um"] == pytest.approx(50.0, abs=1.0)
    assert m["coupled"]["settling_time_s"] < m["conventional"]["settling_time_s"]


def test_dead_time_matters(result):
    # with a much longer dead time in the loop the same aggressive design is no longer good
    r, model, gains, worst = result
    ex = StepExperiment(model, gains, worst, dead_time_s=0.0)
    ex_slow = StepExperiment(model, gains, worst, dead_time_s=0.0015)
    fast = ex.simulate(0.05, 0.1, ex.design(1.0))
    slow = ex_slow.simulate(0.05, 0.1, ex_slow.design(1.0))
    assert fast["rise_time_s"] < slow["rise_time_s"]


def test_step_metrics():
    t = np.linspace(0, 1, 1001)
    y = 50 * (1 - np.exp(-t / 0.05))
    m = step_metrics(t, y, 50.0)
    assert m["settling_time_s"] == pytest.approx(0.05 * np.log(50), abs=2e-3)
    assert m["overshoot_pct"] == 0.0
