"""Planner: the time parameterisation against TOPP-RA and on dynamics-bound random paths.

Strut utilisation is measured independently (rows -> ``Hexapod.inverse_batch`` -> finite differences
at the cycle period); TOPP-RA (``toppra``) is the external peer where installed.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hexacnc.bench import toppra_peer
from hexacnc.config import load_config
from hexacnc.gcode.blocks import Block
from hexacnc.planner import plan_program

from test_planner_motion import run, tip_of, utilisation


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


@pytest.fixture(scope="module")
def cfg_free(cfg):
    """Feed and angular-velocity limits lifted: only the strut limits bind (as in ``hexacnc bench plan``)."""
    pc = dataclasses.replace(cfg.planner, max_angular_velocity_deg_s=1e6, rapid_feed_mm_min=1e9)
    return cfg.replace(planner=pc)


def fast_random_path(cfg, seed, n=10):
    """Short moves with rotations and arcs at a feed far above what the struts allow."""
    rng = np.random.default_rng(seed)
    home = np.array(cfg.home_pose, dtype=float)
    prev = home
    blocks = []
    for line in range(1, n + 1):
        nxt = home + np.concatenate([rng.uniform(-40, 40, 3), rng.uniform(-6, 6, 3)])
        a, b = tip_of(cfg, prev), tip_of(cfg, nxt)
        tol = float(rng.choice([0.05, 0.2, 1.0]))
        if rng.random() < 0.3 and np.linalg.norm(b[:2] - a[:2]) > 5:
            ctr = 0.5 * (a[:3] + b[:3])
            ctr[2] = a[2]
            r0 = np.linalg.norm((a[:3] - ctr)[:2])
            d = (b[:3] - ctr)[:2]
            b[:2] = ctr[:2] + d / np.linalg.norm(d) * r0
            blocks.append(Block("arc", line, a, b, feed_mm_s=1e5, center=ctr, normal=np.array([0, 0, 1.0]),
                                clockwise=bool(rng.integers(2)), blend_tolerance_mm=tol))
        else:
            blocks.append(Block("line", line, a, b, feed_mm_s=1e5, blend_tolerance_mm=tol))
        prev = b.copy()
        from hexacnc.pose import matrix_from_euler
        prev[:3] = b[:3] - matrix_from_euler(*np.radians(b[3:])) @ np.asarray(cfg.tool.tip_platform_mm)
    return blocks


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_dynamics_bound_random_paths_stay_within_strut_limits(cfg_free, seed):
    """Where only strut limits bind, velocity, acceleration and jerk of the sampled table stay <= 1
    (measured here by exact inverse kinematics), the plan runs the struts hard, and its own figures
    are those measurements."""
    cfg = cfg_free
    plan = plan_program(fast_random_path(cfg, seed), cfg)
    rows = run(plan.sampler())
    uv, ua, uj = utilisation(cfg, rows, plan.dt)
    assert uv <= 1.0 and ua <= 1.0 and uj <= 1.0, (uv, ua, uj)
    # dynamics-bound: some limit is used to at least 90 %
    assert max(uv, ua, uj) > 0.9, (uv, ua, uj)
    assert uv == pytest.approx(plan.utilisation["velocity"], rel=2e-3, abs=1e-6)
    assert uj <= plan.utilisation["jerk"] + 0.01


def test_topp_pass_against_toppra_and_the_jerk_cost(cfg_free):
    """Our forward-backward pass at full strut v/a matches TOPP-RA on the same path within 2 %; the plan
    is never faster than that jerk-free optimum; each added requirement (planning shares, constant-speed
    jerk bound, the jerk filter) can only lengthen it."""
    pytest.importorskip("toppra")
    res = toppra_peer._bench_topp(cfg_free, 1000, toppra_peer.topp_path_blocks(cfg_free), "corners")
    dec = res["topp_decomposition_s"]
    ref = res["toppra_duration_s"]
    assert dec["va_full"] == pytest.approx(ref, rel=0.02)
    assert res["hexacnc_duration_s"] >= 0.99 * ref
    assert dec["va_full"] <= dec["va_plan"] + 1e-6
    assert dec["va_full"] < dec["va_full_jerk_const_speed"] <= dec["plan_limits"] + 1e-6
    # spreading slow spots over the filter's reach only lowers limits; the plan starts from there
    assert dec["plan_limits"] < dec["plan_limits_spread"] <= res["hexacnc_topp_profile_s"] + 1e-6
    assert res["hexacnc_topp_profile_s"] <= res["hexacnc_duration_s"] + 1e-6
    assert res["utilisation_ok"]


def test_corpus_comparison_keys_and_lifted_feeds(cfg, tmp_path):
    """bench_topp_corpus plans a program placed by the bench with feeds lifted and dwells zeroed."""
    pytest.importorskip("toppra")
    (tmp_path / "tiny.ngc").write_text("G21 G90 G64 P0.2\nG1 X0 Y0 Z0 F600\nG1 X20 Y0\nG4 P0.5\n"
                                       "G2 X40 Y0 I10 J0\nG1 X40 Y15 A3\nM2\n")
    out = toppra_peer.bench_topp_corpus(cfg, 500, tmp_path, ("tiny.ngc", "missing.ngc"))
    r = out["tiny.ngc"]
    assert "skipped" in out["missing.ngc"]
    for k in ("hexacnc_duration_s", "toppra_duration_s", "ratio", "within_5_percent", "hexacnc_utilisation",
              "utilisation_ok", "topp_decomposition_s", "work_offset_mm"):
        assert k in r, k
    assert r["utilisation_ok"] and r["toppra_duration_s"] > 0
    # feeds lifted: far faster than at F600 (10 mm/s over ~75 mm would take 7.5 s)
    assert r["hexacnc_duration_s"] < 3.0
    lifted = toppra_peer._lift_feeds([Block("line", 1, np.zeros(6), np.ones(6), feed_mm_s=5.0),
                                Block("dwell", 2, seconds=2.0)])
    assert lifted[0].feed_mm_s == toppra_peer.FEED_LIFTED and lifted[1].seconds == 0.0
