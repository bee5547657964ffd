"""Numeric properties of the machine model (seeded)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.errormodel import pose_sensitivity, pose_sensitivity_numeric, reading_parameter_jacobian
from hexacnc.kinematics import FK_OK, ForwardTracker, Hexapod
from hexacnc.pose import (euler_from_matrix, matrix_from_euler, matrix_from_quaternion, pose_to_rad,
                          quaternion_from_matrix, rate_matrix)
from hexacnc import sag


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


@pytest.fixture(scope="module")
def hx(cfg):
    return Hexapod(cfg)


def random_poses(cfg, hx, n, seed):
    rng = np.random.default_rng(seed)
    P = rng.uniform(cfg.workspace_min, cfg.workspace_max, size=(3 * n, 6))
    return P[~hx.batch_violations(P)][:n]


def test_rotation_conventions():
    rng = np.random.default_rng(0)
    for _ in range(200):
        a, b, c = rng.uniform(-1.5, 1.5, 3)
        R = matrix_from_euler(a, b, c)
        # R = Rz(c) Ry(b) Rx(a)
        Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
        Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
        Rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
        assert np.allclose(R, Rz @ Ry @ Rx, atol=1e-14)
        assert np.allclose(euler_from_matrix(R), (a, b, c), atol=1e-12)
        assert np.allclose(matrix_from_quaternion(quaternion_from_matrix(R)), R, atol=1e-12)


def test_rate_matrix_maps_euler_rates_to_angular_velocity():
    rng = np.random.default_rng(1)
    h = 1e-7
    for _ in range(50):
        abc = rng.uniform(-1.2, 1.2, 3)
        rates = rng.normal(size=3)
        R0 = matrix_from_euler(*abc)
        R1 = matrix_from_euler(*(abc + h * rates))
        W = (R1 - R0) / h @ R0.T            # skew(omega)
        omega = np.array([W[2, 1], W[0, 2], W[1, 0]])
        assert np.allclose(rate_matrix(*abc) @ rates, omega, atol=1e-6)


def test_inverse_paths_agree(cfg, hx):
    P = random_poses(cfg, hx, 200, 2)
    Lb = hx.inverse_batch(P)
    for k in range(P.shape[0]):
        assert np.allclose(hx.lengths(P[k]), Lb[k], atol=1e-10)
    # definition L = |t + R p - b|
    p = P[0]
    R = matrix_from_euler(*np.radians(p[3:]))
    L = [np.linalg.norm(p[:3] + R @ hx.plat[i] - hx.base[i]) for i in range(6)]
    assert np.allclose(L, Lb[0], atol=1e-10)


def test_forward_inverse_round_trip(cfg, hx):
    P = random_poses(cfg, hx, 2000, 3)
    assert P.shape[0] == 2000
    L = hx.inverse_batch(P)
    for k in range(P.shape[0]):
        r = hx.forward(L[k], tol_mm=1e-10)
        assert r.status == FK_OK, (k, r)
        assert np.max(np.abs(r.pose[:3] - P[k, :3])) < 1e-9
        assert np.max(np.abs(r.pose[3:] - P[k, 3:])) < 1e-9
        assert r.iterations <= 6


def test_forward_failure_is_a_value(hx):
    r = hx.forward(np.full(6, 10.0))         # far too short: no assembly
    assert r.status != FK_OK
    r = hx.forward(np.array([1.0, 2, 3, 4, 5, math.nan]))
    assert r.status != FK_OK


def test_warm_start_tracker_iterations(cfg, hx):
    n = 4000
    t = np.arange(n) / 2000.0
    P = np.tile(cfg.home_pose, (n, 1)).astype(float)
    P[:, 0] += 50 * np.sin(2 * math.pi * 0.5 * t)
    P[:, 1] += 40 * np.sin(2 * math.pi * 1.0 * t)
    P[:, 3] += 6 * np.sin(2 * math.pi * 0.3 * t)
    P[:, 4] += 5 * np.cos(2 * math.pi * 0.4 * t)
    L = hx.inverse_batch(P)
    tr = ForwardTracker(hx, P[0])
    for k in range(n):
        r = tr.track(L[k])
        assert r.ok
        assert np.max(np.abs(r.pose - P[k])) < 1e-5
    assert tr.mean_iterations <= 1.5


def test_jacobian_matches_finite_differences(cfg, hx):
    for p in random_poses(cfg, hx, 20, 4):
        X = pose_to_rad(p)
        J = hx.jacobian_rad(X)
        Jn = np.empty((6, 6))
        for j in range(6):
            h = 1e-6 if j < 3 else 1e-8
            d = np.zeros(6)
            d[j] = h
            Jn[:, j] = (hx.lengths_rad(X + d) - hx.lengths_rad(X - d)) / (2 * h)
        assert np.allclose(J, Jn, rtol=1e-6, atol=1e-6)


def test_cog_jacobian_matches_finite_differences(cfg, hx):
    cog = np.asarray(cfg.center_of_gravity_mm)
    for p in random_poses(cfg, hx, 10, 5):
        Jd = hx.jacobian_cog(p)
        X = pose_to_rad(p)

        def lengths_from_cog_coords(Y):
            R = matrix_from_euler(*Y[3:])
            t = Y[:3] - R @ cog
            return hx.lengths_rad(np.concatenate([t, Y[3:]]))

        R = matrix_from_euler(*X[3:])
        Y = np.concatenate([X[:3] + R @ cog, X[3:]])
        Jn = np.empty((6, 6))
        for j in range(6):
            h = 1e-6 if j < 3 else 1e-8
            d = np.zeros(6)
            d[j] = h
            Jn[:, j] = (lengths_from_cog_coords(Y + d) - lengths_from_cog_coords(Y - d)) / (2 * h)
        assert np.allclose(Jd, Jn, rtol=1e-6, atol=1e-5)


def test_error_model_matches_finite_differences(cfg, hx):
    for p in random_poses(cfg, hx, 3, 6):
        S = pose_sensitivity(hx, p)
        Sn = pose_sensitivity_numeric(hx, p)
        assert np.max(np.abs(S - Sn)) < 1e-6 * max(1.0, np.max(np.abs(S)))
    G = reading_parameter_jacobian(hx, random_poses(cfg, hx, 5, 7))
    assert G.shape == (5, 6, 42)
    assert np.allclose(G[:, :, 36:], -np.eye(6)[None])


def test_sag_equilibrium_and_first_order_accuracy(cfg, hx):
    for p in random_poses(cfg, hx, 5, 8):
        f = sag.strut_forces_N(hx, p)
        Jt = hx.jacobian_twist_rad(pose_to_rad(p))
        w = sag.gravity_wrench(hx, pose_to_rad(p))
        assert np.allclose(Jt.T @ f, w, atol=1e-8)
        # total vertical strut force carries the weight
        assert abs(w[2] - cfg.mass_kg * cfg.gravity_mm_s2[2] * 1e-3) < 1e-9
    report = sag.first_order_error(hx, random_poses(cfg, hx, 8, 9))
    assert report["max_sag_position_mm"] > 1e-4          # the effect is real (µm)
    assert report["max_first_order_error_position_mm"] < 0.01 * report["max_sag_position_mm"]


def test_sag_compensation_removes_the_deviation(cfg, hx):
    p = random_poses(cfg, hx, 1, 10)[0]
    L = hx.lengths(p)
    # uncompensated: the pose sags; compensated command brings it back
    eq = sag.exact_equilibrium(hx, L, p)
    dev = np.max(np.abs(eq.pose[:3] - p[:3]))
    eqc = sag.exact_equilibrium(hx, L + sag.sag_compensation_mm(hx, p), p)
    devc = np.max(np.abs(eqc.pose[:3] - p[:3]))
    assert dev > 1e-3
    assert devc < 0.01 * dev


def test_joint_angles_and_limits(cfg, hx):
    ab, ap = hx.joint_angles(cfg.home_pose)
    assert np.allclose(ab, 0.0, atol=1e-4) and np.allclose(ap, 0.0, atol=1e-4)  # axes rounded to 1e-6 in the file
    far = np.array(cfg.home_pose, dtype=float)
    far[3] = 60.0
    v = hx.limit_violations(far)
    assert any("joint" in m for m in v) or any("strut" in m for m in v)
    short = np.array(cfg.home_pose, dtype=float)
    short[2] = -300.0
    v = hx.limit_violations(short)
    assert any("below min_length_mm" in m for m in v)
