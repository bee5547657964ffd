"""CAM smoothing (``[planner] smooth_max_segment_mm``): runs of short lines become one C2 curve.

The tolerance, continuity and utilisation checks are independent of the smoothing code: the
programmed polyline, finite differences of the pieces and ``Hexapod.inverse_batch`` of the rows.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.errors import ConfigError
from hexacnc.gcode.blocks import Block
from hexacnc.planner import path as P
from hexacnc.planner import plan_program
from hexacnc.planner.profile import ETA

from test_planner_motion import tip_of, utilisation

TOL = 0.1


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def smoothing(cfg, mm=2.0):
    return cfg.replace(planner=dataclasses.replace(cfg.planner, smooth_max_segment_mm=mm))


def polyline(cfg, pts, feed=1e4, tol=TOL, exact_after=()):
    """Lines through tool-tip points ``pts`` (n, 3) mm around the home tip, home orientation."""
    home = tip_of(cfg, cfg.home_pose)
    P6 = np.repeat(home[None, :], len(pts), axis=0)
    P6[:, :3] = home[:3] + np.asarray(pts)
    return [Block("line", i + 1, P6[i], P6[i + 1], feed_mm_s=feed, blend_tolerance_mm=tol,
                  exact_stop=(i in exact_after)) for i in range(len(pts) - 1)]


def cam_arc(n=40, radius=3.0, chord=0.25, seed=0):
    """Points of an arc of ``radius`` every ``chord`` mm, rounded to 0.001 mm as CAM output is,
    after a 5 mm lead-in line (which is longer than the smoothing limit)."""
    dth = chord / radius
    th = np.arange(n) * dth
    arc = np.stack([radius * np.sin(th), radius * (1 - np.cos(th)), np.zeros(n)], axis=1)
    pts = np.vstack([[-5.0, 0.0, 0.0], arc])
    return np.round(pts, 3)


def dist_to_polyline(x, A, B):
    """Distance (n,) of points x (n, 3) to the polyline of segments A[i] -> B[i]."""
    AB = B - A
    t = np.clip(np.einsum("nij,ij->ni", x[:, None, :] - A[None], AB) / np.einsum("ij,ij->i", AB, AB), 0, 1)
    Q = A[None] + t[..., None] * AB[None]
    return np.min(np.linalg.norm(x[:, None, :] - Q, axis=2), axis=1)


def test_off_by_default(cfg):
    assert cfg.planner.smooth_max_segment_mm == 0.0
    path, _ = P.build_path(polyline(cfg, cam_arc()), cfg)
    assert not np.any(path.kind == P.SPLINE)


def test_arc_becomes_c2_and_stays_within_half_the_tolerance(cfg):
    c = smoothing(cfg)
    blocks = polyline(c, cam_arc())
    path, _ = P.build_path(blocks, c)
    spl = np.nonzero(path.kind == P.SPLINE)[0]
    assert spl.size == len(blocks) - 1          # every short line of the arc; the lead-in stays a line
    assert path.kind[0] == P.LINE
    # C2 at the interior vertices: first and second derivatives of neighbouring pieces agree
    # (finite differences of the pieces' own evaluation, both sides)
    e = 1e-4
    for a, b in zip(spl[:-1], spl[1:]):
        if b != a + 1:
            continue
        s = path.s0[b]
        left = path.tip(np.array([a] * 3), np.array([s - 2 * e, s - e, s]))[:, :3]
        right = path.tip(np.array([b] * 3), np.array([s, s + e, s + 2 * e]))[:, :3]
        np.testing.assert_allclose(left[2], right[0], atol=1e-9)
        np.testing.assert_allclose((left[2] - left[1]) / e, (right[1] - right[0]) / e, atol=2e-3)
    # each smoothed piece within TOL/2 of its programmed line at 200 points (same s and nearest)
    A = np.array([b.start[:3] for b in blocks])
    B = np.array([b.end[:3] for b in blocks])
    for k in spl:
        s = path.s0[k] + np.linspace(0, path.slen[k], 200)
        x = path.tip(np.full(200, k), s)[:, :3]
        assert np.max(dist_to_polyline(x, A, B)) <= 0.5 * TOL + 1e-9


def test_smoothed_arc_plans_faster_within_limits_and_tolerance(cfg):
    pts = cam_arc(n=60)
    plain = plan_program(polyline(cfg, pts), cfg)
    c = smoothing(cfg)
    blocks = polyline(c, pts)
    smooth = plan_program(blocks, c)
    assert smooth.n_smoothed > 0 and plain.n_smoothed == 0
    assert smooth.duration_s < 0.9 * plain.duration_s, (plain.duration_s, smooth.duration_s)
    v, a, j = utilisation(c, smooth.rows(), smooth.dt)
    assert v <= 1.0 and a <= ETA + 1e-3 and j <= ETA + 1e-3, (v, a, j)
    # the tool tip of every row stays within G64 P of the programmed polyline
    rows = smooth.rows()
    poses = rows[:, :6].copy()
    poses[:, 3:] = np.degrees(poses[:, 3:])
    tips = np.array([tip_of(c, p)[:3] for p in poses[::5]])
    A = np.array([b.start[:3] for b in blocks])
    B = np.array([b.end[:3] for b in blocks])
    assert np.max(dist_to_polyline(tips, A, B)) <= TOL + 1e-6


def test_sharp_corner_exact_stop_and_long_lines_are_not_smoothed_across(cfg):
    c = smoothing(cfg)
    # two short-line runs meeting at a right angle, an exact stop inside the second, a long line at the end
    run1 = np.stack([np.arange(8) * 0.3, np.zeros(8), np.zeros(8)], axis=1)
    run2 = run1[-1] + np.stack([np.zeros(8), np.arange(8) * 0.3, np.zeros(8)], axis=1)[1:]
    pts = np.vstack([run1, run2, run2[-1] + [10.0, 10.0, 0.0]])
    blocks = polyline(c, pts, exact_after=(10,))
    path, _ = P.build_path(blocks, c)
    # raw move i is a piece of kind LINE or SPLINE; blends sit between them
    moves = np.nonzero(path.kind != P.BLEND)[0]
    kinds = path.kind[moves]
    assert kinds[-1] == P.LINE                               # 14 mm line: longer than the limit
    assert np.all(kinds[:-1] == P.SPLINE)
    # the right-angle corner (after move 6) is blended, not smoothed through
    assert path.kind[moves[6] + 1] == P.BLEND
    # the exact stop after move 10 is a stop of the path
    assert int(moves[10]) in path.stops_after
    # the path rests exactly at the programmed stop (a run end keeps its programmed vertex)
    m = moves[10]
    end = path.tip(np.array([m]), np.array([path.s0[m] + path.slen[m]]))[0, :3]
    np.testing.assert_allclose(end, blocks[10].end[:3], atol=1e-9)


def test_config_rejects_a_negative_length(tmp_path):
    from importlib.resources import files
    text = files("hexacnc").joinpath("data/default.toml").read_text()
    bad = text.replace("smooth_max_segment_mm = 0.0", "smooth_max_segment_mm = -1.0")
    assert bad != text
    f = tmp_path / "m.toml"
    f.write_text(bad)
    with pytest.raises(ConfigError, match="smooth_max_segment_mm"):
        load_config(str(f))


def test_a_run_whose_system_breaks_down_stays_lines_and_the_others_are_smoothed():
    """The banded solve of a run of 1 nm lines breaks down in floating point (its jerk energy's entries are
    ~1e30, its smoothing weights ~1e-6): that run keeps its lines, a normal run solved beside it gets the same
    spline as on its own."""
    from hexacnc.planner import smooth as S
    rng = np.random.default_rng(3)
    ok_run = np.cumsum(rng.normal(size=(6, 6)) * 0.2, axis=0)
    tiny = np.cumsum(np.random.default_rng(4).normal(size=(5, 6)) * 1e-6, axis=0)
    h_ok = np.linalg.norm(np.diff(ok_run[:, :3], axis=0), axis=1)
    h_tiny = np.linalg.norm(np.diff(tiny[:, :3], axis=0), axis=1)
    alone = S._fit_runs(ok_run, h_ok, np.array([6]), np.array([1.0]))
    assert alone is not None
    assert S._fit_runs(tiny, h_tiny, np.array([5]), np.array([1.0])) is None
    V, T, K, fitted = S._fit_each(np.vstack([ok_run, tiny]), np.concatenate([h_ok, h_tiny]), np.array([6, 5]),
                                  np.array([1.0, 1.0]))
    assert fitted.tolist() == [True, False]
    for got, want in zip((V, T, K), alone):
        assert np.allclose(got[:6], want, rtol=1e-12, atol=1e-12)
    assert np.isnan(V[6:]).all()


@pytest.mark.parametrize("d_mm", [1e-5, 1e-4, 1e-3])
def test_micrometre_and_smaller_runs_are_planned_with_smoothing_on(cfg, d_mm):
    """Twelve G64 P0.01 moves (turns of at most 20 deg, so they form one run) of 10 nm to 1 um with smoothing on
    plan within the limits: the factorisation broke down on such runs with an uncaught LinAlgError (here at
    10 and 100 nm; 1 um moves in random directions, seed 105 of the monotonicity tests) until its rows were
    scaled; a run that still breaks down keeps its lines."""
    c = smoothing(cfg)
    rng = np.random.default_rng(7)
    ang = np.cumsum(np.radians(rng.uniform(-20, 20, size=12)))
    pts = np.vstack([[0.0, 0.0, 0.0], np.cumsum(d_mm * np.stack([np.cos(ang), np.sin(ang), 0 * ang], 1), 0)])
    plan = plan_program(polyline(c, pts, tol=0.01), c)
    assert plan.duration_s > 0
    assert max(plan.utilisation.values()) <= ETA + 1e-9


def test_a_run_smooths_the_same_wherever_it_lies_in_the_machine():
    """A translation of a run's vertices translates its smoothing spline (the energy sees only differences).
    300 lines of about 8 um smoothed over 1 mm: at the machine's z of -1150 mm the positions came out up to 270 mm
    off the same run's solution near the origin (the system's low modes carry ~1e-16 cond ~ 4e12 of its
    right-hand side, then ~1000 mm); positions are now taken relative to the run's first vertex."""
    from hexacnc.planner import smooth as S
    rng = np.random.default_rng(11)
    th = np.cumsum(np.full(300, 0.008 / 2.0)) + rng.normal(scale=1e-4, size=300)
    V0 = np.zeros((300, 6))
    V0[:, 0], V0[:, 1] = 2.0 * np.sin(th), 2.0 * (1 - np.cos(th))
    V0[:, :2] = np.round(V0[:, :2], 3)                      # CAM output's 1 um grid
    h = np.linalg.norm(np.diff(V0[:, :3], axis=0), axis=1)
    keep = np.concatenate([[True], h > 0])
    V0 = V0[keep]
    h = np.linalg.norm(np.diff(V0[:, :3], axis=0), axis=1)
    shift = np.array([37.0, -12.0, -1150.0, 0.2, -0.1, 0.3])
    near = S._fit_runs(V0, h, np.array([V0.shape[0]]), np.array([1.0]))
    far = S._fit_runs(V0 + shift, h, np.array([V0.shape[0]]), np.array([1.0]))
    assert near is not None and far is not None
    assert np.abs(far[0] - shift - near[0]).max() < 1e-9
    assert np.abs(far[1] - near[1]).max() < 1e-9 and np.abs(far[2] - near[2]).max() < 1e-6
