"""The synthetic generator's physics and the model's evaluation agree with themselves (issue 17).

Backlash: the approach direction the diagnosis recovers from the readings is the one the generator
used, even where a strut moves less than the gap between rows.  Pose-dependent causes: the forward
kinematics reaches the fixed point from a cold start (held-out rows are evaluated cold).
"""
from __future__ import annotations

import os

import numpy as np
import pytest

from hexacnc.calib import synth
from hexacnc.calib.measurements import Measurements
from hexacnc.calib.model import Context, Evaluator, build_layout, strut_geometry
from hexacnc.config import load_config


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def fresh_seed() -> int:
    return int.from_bytes(os.urandom(4), "little")


def test_backlash_readings_agree_with_their_own_approach_direction():
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    n = 200
    # backlash-free readings that often move less than the gap between rows, in three sessions
    p = np.cumsum(rng.normal(0.0, 0.05, (n, 6)), axis=0) + 300.0
    half = -rng.uniform(0.01, 0.1, 6)
    session = np.array(["a"] * 70 + ["b"] * 60 + ["c"] * 70, dtype=object)
    q = synth.backlash_readings(p, half, session)
    m = Measurements("<test>", q, np.zeros((n, 6)), session=session)
    d = m.direction()
    np.testing.assert_allclose(q + half[None] * d, p, atol=1e-12, err_msg=f"seed {seed}")
    assert np.all(d[[0, 70, 130]] == 1.0), seed           # each session approached from home
    small = np.abs(np.diff(p, axis=0)) < 2 * np.abs(half)[None]
    assert small.any() and (np.diff(d, axis=0) != 0).any(), seed   # the case that used to go wrong is there
    with pytest.raises(ValueError, match="lags the motor"):
        synth.backlash_readings(p, -half, session)


def test_pose_dependent_causes_reach_the_fixed_point_from_a_cold_start(cfg):
    seed = fresh_seed()
    s = synth.generate(cfg, seed, "joint_offset", n_fit=30, n_holdout=10)
    ctx = Context(cfg, s.holdout, s.noise_mm, s.noise_deg)
    lay = build_layout(cfg, ctx, ["joint_offset"])
    theta = lay.theta0.copy()
    theta[lay.causes["joint_offset"]] = np.random.default_rng(seed).normal(0.0, 20.0, 12)   # large offsets
    ev = Evaluator(cfg, lay, ctx)                          # cold: every row starts at home
    X = ev.poses(theta)
    L_model, _ = ev.lengths_from_readings(theta, X)
    base, plat = theta[:18].reshape(6, 3), theta[18:36].reshape(6, 3)
    _, _, _, L_geom = strut_geometry(base, plat, X)
    assert np.max(np.abs(L_model - L_geom)) < 1e-7, seed  # the poses close the loop with their own lengths


def test_exact_joint_offsets_linearise_to_the_basis(cfg):
    s = synth.generate(cfg, fresh_seed(), "joint_offset", n_fit=20, n_holdout=5)
    ctx = Context(cfg, s.fit, s.noise_mm, s.noise_deg)
    lay = build_layout(cfg, ctx, ["joint_offset"])
    cm = lay.cause_models["joint_offset"]
    X = Evaluator(cfg, lay, ctx).poses(lay.theta0)
    base, plat = lay.theta0[:18].reshape(6, 3), lay.theta0[18:36].reshape(6, 3)
    dl0, B0 = cm.exact(ctx, X, base, plat, np.zeros(12))
    np.testing.assert_allclose(dl0, 0.0, atol=1e-9)
    np.testing.assert_allclose(B0, cm.build(ctx, X, base, plat), atol=1e-12)
    th = np.full(12, 0.01)
    dl, B = cm.exact(ctx, X, base, plat, th)
    np.testing.assert_allclose(dl, np.einsum("nik,k->ni", B0, th), atol=1e-6)   # second order: d^2 / L
