"""Planner: strut-length and joint-angle limits along whole segments, first violation with line and limit."""
from __future__ import annotations

import socket

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.errors import PlanError
from hexacnc.gcode.blocks import Block
from hexacnc.kinematics import Hexapod
from hexacnc.pose import matrix_from_euler
from hexacnc.planner import plan_program


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def tip_of(cfg, platform_pose_deg, tool_mm=0.0):
    """Tool-tip pose (mm/deg) of a platform pose (mm/deg)."""
    P = np.asarray(platform_pose_deg, dtype=float)
    R = matrix_from_euler(*np.radians(P[3:]))
    q = np.asarray(cfg.tool.tip_platform_mm) + tool_mm * np.asarray(cfg.tool.axis_platform)
    out = P.copy()
    out[:3] = P[:3] + R @ q
    return out


def lines(cfg, platform_poses, feed_mm_s=20.0, first_line=1):
    tips = [tip_of(cfg, p) for p in platform_poses]
    return [Block("line", first_line + i, tips[i], tips[i + 1], feed_mm_s=feed_mm_s) for i in range(len(tips) - 1)]


def test_segment_leaving_strut_range_between_endpoints_is_refused(cfg):
    hx = Hexapod(cfg)
    home = np.array(cfg.home_pose, dtype=float)
    s = home[:3] + hx.plat[0] - hx.base[0]
    u = s / np.linalg.norm(s)
    mid = home.copy()
    mid[:3] -= u * (np.linalg.norm(s) - 699.0)          # strut 1 at 699 mm (< 700) in the middle
    assert hx.lengths(mid)[0] == pytest.approx(699.0)
    # a direction perpendicular to strut 1 along which both endpoints are inside every limit
    e1 = np.cross(u, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    found = None
    for ang in np.radians(np.arange(0, 180, 5)):
        n = np.cos(ang) * e1 + np.sin(ang) * e2
        A, B = mid.copy(), mid.copy()
        A[:3] += 70 * n
        B[:3] -= 70 * n
        if not hx.limit_violations(A) and not hx.limit_violations(B):
            found = (A, B)
            break
    assert found is not None, "test geometry: no direction with both endpoints inside the limits"
    A, B = found
    start = home.copy()
    blocks = lines(cfg, [home, A], first_line=3) + lines(cfg, [A, B], first_line=7) + lines(cfg, [B, home],
                                                                                                first_line=9)
    hx.check_pose(A)
    hx.check_pose(B)          # endpoint-only checking would accept the program
    with pytest.raises(PlanError) as ei:
        plan_program(blocks, cfg)
    err = ei.value
    assert err.line == 7
    assert err.limit == "strut 1 min_length_mm"
    assert "below min_length_mm 700" in str(err)
    assert start is not None


def test_joint_angle_refusal_names_line_and_joint(cfg):
    hx = Hexapod(cfg)
    home = np.array(cfg.home_pose, dtype=float)
    tilted = home + np.array([0, 0, 0, 15.0, 0, 0])
    ab, ap = hx.joint_angles(tilted)
    worst = max(ab.max(), ap.max())
    ab0, ap0 = hx.joint_angles(home)
    limit = 0.5 * (worst + max(ab0.max(), ap0.max()))
    tight = cfg.replace(max_angle_deg=np.full(6, limit))
    blocks = lines(tight, [home, home + [10, 0, 0, 0, 0, 0]], first_line=2) + \
        lines(tight, [home + [10, 0, 0, 0, 0, 0], tilted + [10, 0, 0, 0, 0, 0]], first_line=5)
    with pytest.raises(PlanError) as ei:
        plan_program(blocks, tight)
    assert ei.value.line == 5
    assert "joint" in ei.value.limit and ei.value.limit.endswith("max_angle_deg")
    assert f"over max_angle_deg {limit:g}" in str(ei.value)
    # the same program with the configured limit plans, and reports its joint margin
    plan = plan_program(blocks, cfg)
    assert 0 < plan.min_joint_margin_deg < float(np.min(cfg.max_angle_deg))


def test_violation_reports_first_offending_line(cfg):
    home = np.array(cfg.home_pose, dtype=float)
    far = home + [0, 0, -500.0, 0, 0, 0]                 # struts far too long
    blocks = lines(cfg, [home, home + [20, 0, 0, 0, 0, 0]], first_line=1)
    blocks += lines(cfg, [home + [20, 0, 0, 0, 0, 0], far], first_line=4)
    blocks += lines(cfg, [far, home], first_line=9)
    with pytest.raises(PlanError) as ei:
        plan_program(blocks, cfg)
    assert ei.value.line == 4
    assert "max_length_mm" in ei.value.limit


def test_sample_spacing_bound_holds_between_samples(cfg):
    """The stated bound: strut lengths between the check samples never leave the shrunk range."""
    from hexacnc.planner import path as P
    hx = Hexapod(cfg)
    home = np.array(cfg.home_pose, dtype=float)
    poses = [home, home + [60, -40, 30, 8, -6, 10], home + [-50, 50, -40, -10, 5, -8]]
    blocks = lines(cfg, poses)
    path, _ = P.build_path(blocks, cfg)
    h, nint, lmarg, _ = P.sample_spacing(path, hx.plat, float(np.min(hx.min_length)), cfg.planner.sample_bound_mm)
    assert np.all(lmarg <= cfg.planner.sample_bound_mm * (1 + 1e-9))
    for m in range(path.n):
        fine = np.linspace(path.s0[m], path.s0[m] + path.slen[m], int(nint[m]) * 50 + 1)
        coarse = fine[::50]
        idx = np.full(fine.shape, m)
        Lf = P.strut_lengths(path.platform(idx, fine), hx.plat, hx.base)
        Lc = Lf[::50]
        # piecewise-linear interpolation error of every strut is within the bound
        interp = np.stack([np.interp(fine, coarse, Lc[:, i]) for i in range(6)], axis=1)
        assert np.max(np.abs(Lf - interp)) <= lmarg[m] + 1e-9


def test_planner_needs_no_network(cfg, monkeypatch):
    def refuse(*a, **k):
        raise OSError("network use is forbidden in this test")
    monkeypatch.setattr(socket, "socket", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    home = np.array(cfg.home_pose, dtype=float)
    blocks = lines(cfg, [home, home + [30, 0, 0, 0, 0, 0], home + [30, 30, 0, 5, 0, 0]], feed_mm_s=40)
    plan = plan_program(blocks, cfg)
    s = plan.sampler()
    s.set_override(0.5)
    out = np.empty((256, 8))
    n = 0
    while True:
        c = s.next_rows(out)
        if c == 0:
            break
        n += c
        if n > 2000 and s.state == "running":
            s.pause()
        if s.state == "paused":
            s.resume()
    assert s.done and n > 0


def test_incremental_topp_equals_full_pass():
    from hexacnc.planner.topp import accel_coefficients, forward_backward
    from hexacnc.planner.toppvec import WavefrontTopp
    rng = np.random.default_rng(7)
    N = 2000
    h = rng.uniform(0.1, 1, N - 1)
    h[rng.integers(0, N - 1, 40)] = 0.0
    c, e, d, xm = accel_coefficients(rng.normal(size=(N, 6)), 0.01 * rng.normal(size=(N, 6)), np.full(6, 100.0))
    xl = np.minimum(rng.uniform(10, 1000, N), xm)
    xl[[0, 700, N - 1]] = 0.0
    it = WavefrontTopp(h, c, e, d)
    assert np.array_equal(it.solve(xl), forward_backward(h, xl, c, e, d))
    for _ in range(15):
        ranges = []
        for _ in range(int(rng.integers(1, 5))):
            lo = int(rng.integers(0, N - 10))
            hi = lo + int(rng.integers(0, 80))
            ranges.append((lo, hi))
            xl = xl.copy()
            xl[lo:hi + 1] *= rng.uniform(0.3, 1.0)
        assert np.array_equal(it.solve_ranges(xl, ranges), forward_backward(h, xl, c, e, d))
