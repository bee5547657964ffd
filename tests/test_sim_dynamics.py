"""Coupled strut/carrier dynamics: eigenvalues vs a nonlinear ring-down, tuning, path simulation."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from hexacnc.config import load_config
from hexacnc.sim.dynamics import (CoupledModel, discretise_fast, drive_transfer_functions, eigen_grid,
                                  gains_from_bandwidth, simulate_path, tune_conventional, workspace_grid)
from hexacnc.sim.nonlinear import ringdown
from hexacnc.sim.program import synthetic_program, trajectory


@pytest.fixture(scope="module")
def setup():
    cfg = load_config()
    model = CoupledModel(cfg)
    grid = workspace_grid(cfg, n_xyz=3)
    eg = eigen_grid(model, grid)
    worst = np.asarray(eg["worst_pose"])
    gains, crit = tune_conventional(model, worst)
    return cfg, model, grid, eg, worst, gains, crit


def test_worst_position_is_the_grid_minimum(setup):
    cfg, model, grid, eg, worst, gains, crit = setup
    f = np.array([model.locked_modes(p)[0][0] for p in grid])
    assert eg["worst_lowest_hz"] == pytest.approx(f.min())
    assert eg["range_lowest_hz"][1] > eg["range_lowest_hz"][0] * 1.1     # real position dependence
    assert not model.hx.batch_violations(worst[None])[0]


@pytest.mark.parametrize("mode", [0, 1])
def test_linear_eigenfrequencies_match_nonlinear_ringdown(setup, mode):
    cfg, model, grid, eg, worst, gains, crit = setup
    r = ringdown(model, gains, worst, mode_index=mode, amplitude_mm=1e-3, periods=4, h=1e-4)
    assert r["ringdown_hz"] == pytest.approx(r["linear_hz"], rel=5e-3)
    assert r["ringdown_damping"] == pytest.approx(r["linear_damping"], rel=0.05, abs=2e-3)


def test_conventional_tuning_is_stable_at_worst_and_margin_is_real(setup):
    cfg, model, grid, eg, worst, gains, crit = setup
    assert model.is_stable(worst, gains)
    assert not model.is_stable(worst, gains_from_bandwidth(cfg, crit * 1.05))
    eg2 = eigen_grid(model, grid, gains)
    assert eg2["closed_loop_stable_everywhere"]


def test_drive_transfer_functions_limits(setup):
    cfg, model, grid, eg, worst, gains, crit = setup
    tf = drive_transfer_functions(model, gains, np.array([1e-3, 1.0, 1e4]))
    assert tf["Gs_mag"][0] == pytest.approx(1.0, abs=1e-4)
    assert tf["Gz_mag_mm_N"][0] == pytest.approx(1.0 / cfg.stiffness_N_per_mm[0], rel=1e-3)
    assert tf["Gs_mag"][2] < 1e-3


def test_fast_discretisation_close_to_exact(setup):
    cfg, model, grid, eg, worst, gains, crit = setup
    A, B = model.at(worst, gains)
    Ad, Bd = discretise_fast(A, B, 5e-4)
    n, m = B.shape
    Mx = np.zeros((n + m, n + m)); Mx[:n, :n] = A; Mx[:n, n:] = B
    E = expm(Mx * 5e-4)
    assert np.max(np.abs(Ad - E[:n, :n])) < 2e-2 * np.max(np.abs(E[:n, :n]))
    # same steady state gain (Tustin is exact there)
    xs_f = np.linalg.solve(np.eye(n) - Ad, Bd[:, :6] @ np.ones(6))
    xs_e = np.linalg.solve(np.eye(n) - E[:n, :n], E[:n, n:n + 6] @ np.ones(6))
    assert np.allclose(xs_f, xs_e, atol=1e-8)


def test_path_simulation_chunks_and_errors(setup):
    cfg, model, grid, eg, worst, gains, crit = setup
    tr = trajectory(cfg, synthetic_program(cfg, 12, seed=2), dt_s=cfg.cycle.period_s)
    n = min(len(tr.t_s), 16000)
    a = simulate_path(model, gains, tr.poses[:n], tr.dt_s, tr.line[:n])
    b = simulate_path(model, gains, tr.poses[:n], tr.dt_s, tr.line[:n], chunk_samples=3000)
    assert a["path_error_um"]["max"] == pytest.approx(b["path_error_um"]["max"], rel=1e-9)
    assert np.allclose(a["following_error_um"]["max_per_strut"], b["following_error_um"]["max_per_strut"])
    # moving machine: errors exist but stay in a physical range (um, not mm)
    assert 0.01 < a["path_error_um"]["max"] < 500.0
    assert a["contour_error_um"]["max"] <= a["path_error_um"]["max"] + 1e-9
    assert a["following_error_um"]["largest_strut"] in range(1, 7)
    # stiffer struts -> smaller elastic path error
    stiff = CoupledModel(cfg.replace(stiffness_N_per_mm=np.asarray(cfg.stiffness_N_per_mm) * 10))
    c = simulate_path(stiff, gains, tr.poses[:n], tr.dt_s)
    assert max(c["strut_length_error_um"]["max_per_strut"]) < max(a["strut_length_error_um"]["max_per_strut"])


def test_planner_trajectory_passes_through_program_poses():
    from hexacnc.sim.program import program_trajectory
    cfg = load_config()
    moves = synthetic_program(cfg, 10, seed=5)
    tr, desc = program_trajectory(cfg, moves, 0.01, "planner")
    assert "planner" in desc
    assert np.allclose(tr.poses[-1], moves[-1].target, atol=1e-3)
    # every programmed corner is visited (within the blend tolerance) in order
    for m in moves:
        d = np.min(np.linalg.norm(tr.poses[:, :3] - m.target[:3], axis=1))
        assert d < 0.5
