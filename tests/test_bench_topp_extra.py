"""``hexacnc bench plan`` extras: the rest-to-rest jerk floor, TOPP-RA with programmed feeds, the peer's
own strut jerk.

The floor's 1-DOF times (Ruckig) are checked against an independent closed form; the bench figures
that need TOPP-RA (``toppra``, a bench extra) skip cleanly where it is not installed.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from hexacnc.bench import jerkfloor, toppra_peer
from hexacnc.config import load_config
from hexacnc.gcode.blocks import Block
from hexacnc.kinematics import Hexapod
from hexacnc.planner import plan_program
from hexacnc.pose import matrix_from_euler

from test_planner_motion import tip_of
from test_planner_topp import cfg_free  # noqa: F401  (fixture: feed and angular-velocity limits lifted)


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def _home_tip(cfg):
    return tip_of(cfg, cfg.home_pose)


def _closed_form(d, v, a, j):
    """Rest-to-rest minimum time, written out separately from the bench's: the three double-S cases."""
    if j * v >= a * a:
        d_v = v * (v / a + a / j)          # distance to reach v and stop again, a_max reached
    else:
        d_v = 2.0 * v * math.sqrt(v / j)
    if d >= d_v:
        return d / v + (v / a + a / j if j * v >= a * a else 2.0 * math.sqrt(v / j))
    if d >= 2.0 * a ** 3 / j ** 2:
        vp = (-a * a / j + math.sqrt(a ** 4 / j ** 2 + 4.0 * a * d)) / 2.0
        return 2.0 * (vp / a + a / j)
    return 4.0 * (d / (2.0 * j)) ** (1.0 / 3.0)


@pytest.mark.parametrize("d", [1e-3, 0.5, 2.0, 10.0, 40.0, 400.0])
@pytest.mark.parametrize("vaj", [(500.0, 5000.0, 2e5), (50.0, 5000.0, 2e5), (300.0, 800.0, 1e4)])
def test_ruckig_rest_to_rest_time_is_the_double_s_time(d, vaj):
    v, a, j = vaj
    t = jerkfloor.rest_to_rest_time(d, v, a, j)
    assert t == pytest.approx(_closed_form(d, v, a, j), abs=1e-6)
    assert jerkfloor.double_s_time(d, v, a, j) == pytest.approx(t, abs=1e-6)
    # without a jerk limit: bang-bang, never slower
    bb = jerkfloor.rest_to_rest_time(d, v, a, math.inf)
    assert bb == pytest.approx(d / v + v / a if d >= v * v / a else 2.0 * math.sqrt(d / a), rel=1e-12)
    assert bb < t


def test_floor_of_a_strut_aligned_move_is_that_struts_double_s_time(cfg_free):
    """An exact-stop translation along strut 0 lengthens it by exactly d (the others by less): the floor
    is that strut's rest-to-rest time, and the jerk-limited plan of the move cannot beat it."""
    cfg = cfg_free
    hx = Hexapod(cfg)
    home = np.asarray(cfg.home_pose, dtype=float)
    R = matrix_from_euler(*np.radians(home[3:]))
    u = home[:3] + R @ hx.plat[0] - hx.base[0]
    u /= np.linalg.norm(u)
    d = 20.0
    a = _home_tip(cfg)
    b = a.copy()
    b[:3] += d * u
    plan = plan_program([Block("line", 1, a, b, feed_mm_s=toppra_peer.FEED_LIFTED, exact_stop=True)], cfg)
    fl = jerkfloor.jerk_floor(plan, cfg)
    assert fl["rest_to_rest_sections"] == 1
    assert fl["moves"][0]["max_abs_dL_mm"] == pytest.approx(d, abs=1e-6)
    v, am, j = cfg.max_velocity_mm_s[0], cfg.max_acceleration_mm_s2[0], cfg.max_jerk_mm_s3[0]
    assert fl["jerk_floor_s"] == pytest.approx(_closed_form(d, v, am, j), abs=1e-6)
    assert fl["bang_bang_floor_s"] == pytest.approx(2.0 * math.sqrt(d / am), abs=1e-9)
    assert fl["jerk_floor_s"] <= plan.duration_s


def test_stops_path_floor_toppra_and_the_peers_jerk(cfg):
    """On rest-to-rest moves: bang-bang floor <= TOPP-RA, jerk floor <= hexacnc; the peer's profile,
    sampled at the cycle period through the exact kinematics, exceeds the jerk limit many times."""
    pytest.importorskip("toppra")
    moves = toppra_peer.STOP_MOVES[:4]
    r = toppra_peer._bench_topp(cfg, 500, toppra_peer.stops_path_blocks(cfg, moves=moves), "stops")
    fl = r["jerk_floor"]
    for k in ("jerk_floor_s", "bang_bang_floor_s", "toppra_duration_s", "hexacnc_duration_s", "floor_over_toppra",
              "hexacnc_over_floor", "bang_bang_floor_le_toppra", "floor_excludes_5_percent", "note", "moves"):
        assert k in fl, k
    assert fl["rest_to_rest_sections"] == len(moves) == len(fl["moves"])
    assert fl["bang_bang_floor_s"] <= r["toppra_duration_s"] * (1 + 1e-9)
    assert fl["bang_bang_floor_le_toppra"]
    assert fl["bang_bang_floor_s"] < fl["jerk_floor_s"] <= r["hexacnc_duration_s"]
    assert fl["floor_over_toppra"] == pytest.approx(fl["jerk_floor_s"] / r["toppra_duration_s"], rel=1e-5)
    tu = r["toppra_utilisation"]
    assert set(tu) == {"velocity", "acceleration", "jerk"} and "toppra_utilisation_note" in r
    assert tu["jerk"] > 5.0 and 0.9 < tu["acceleration"] < 1.1
    assert max(r["hexacnc_utilisation"].values()) <= 1.0


def test_programmed_feed_binds_toppra_like_the_planner(cfg):
    """A 30 mm line at F600 (10 mm/s): both take ~3 s; TOPP-RA runs at the feed almost all the way."""
    pytest.importorskip("toppra")
    a = _home_tip(cfg)
    b = a.copy()
    b[:3] += [30.0, 0.0, 0.0]
    r = toppra_peer._bench_topp(cfg, 500, [Block("line", 1, a, b, feed_mm_s=10.0)], "slow", programmed_feeds=True)
    for k in ("hexacnc_duration_s", "toppra_duration_s", "ratio", "within_5_percent", "toppra_utilisation",
              "feed_bound", "jerk_floor", "hexacnc_utilisation", "utilisation_ok"):
        assert k in r, k
    # (TOPP-RA's first and last grid cells, 0.06 mm here, start from rest: h / F each)
    assert 3.0 <= r["toppra_duration_s"] < 3.02
    assert 3.0 <= r["hexacnc_duration_s"] < 3.1
    assert r["within_5_percent"] and r["feed_bound"]["share"] > 0.99
    assert r["toppra_utilisation"]["velocity"] < 0.05


def test_lifted_feed_leaves_the_strut_problem_unchanged(cfg_free):
    """The feed pseudo-coordinate with a lifted feed gives TOPP-RA's strut-only duration."""
    pytest.importorskip("toppra")
    blocks = toppra_peer.stops_path_blocks(cfg_free, moves=toppra_peer.STOP_MOVES[:2])
    plan = plan_program(blocks, cfg_free)
    secs = jerkfloor._sections(jerkfloor._rest_points(plan))
    for a, b in secs:
        s6 = toppra_peer._toppra_section(plan, cfg_free, a, b, 500, False)
        s7 = toppra_peer._toppra_section(plan, cfg_free, a, b, 500, True)
        assert s7.duration_s == pytest.approx(s6.duration_s, rel=1e-9)


def test_feed_speed_limit_reads_rotary_only_feeds_in_degrees(cfg):
    """A rotary-only move: the feed is deg/s over the angular path (s in degrees), as the planner reads it."""
    a = _home_tip(cfg)
    b = a.copy()
    b[3] += 10.0
    plan = plan_program([Block("line", 1, a, b, feed_mm_s=5.0, feed_deg_s=5.0)], cfg)
    s = np.linspace(0.0, plan.path.total, 7)
    assert np.allclose(toppra_peer.feed_speed_limit(plan.path, s, 0.01), 5.0, rtol=1e-6)


def test_piece_grid_resolves_short_blends_the_uniform_grid_steps_over(cfg_free):
    """A zigzag with G64 P0.01 (blends far shorter than TOPP-RA's 0.25 mm grid step): on the uniform
    grid TOPP-RA's profile exceeds the strut acceleration limit at the blends, on the piece grid it
    does not (beyond its constant-acceleration cells), and it is not faster there."""
    pytest.importorskip("toppra")
    cfg = cfg_free
    tip = _home_tip(cfg)
    blocks = []
    for i in range(6):
        nxt = tip.copy()
        nxt[:3] += [12.0, 12.0 if i % 2 == 0 else -12.0, 0.0]
        blocks.append(Block("line", i + 1, tip, nxt, feed_mm_s=toppra_peer.FEED_LIFTED, blend_tolerance_mm=0.01))
        tip = nxt
    plan = plan_program(blocks, cfg)
    assert np.min(plan.path.slen) < 0.25        # the blends
    (a, b), = jerkfloor._sections(jerkfloor._rest_points(plan))
    uni = toppra_peer._toppra_section(plan, cfg, a, b, 200, False)
    fine = toppra_peer._toppra_section(plan, cfg, a, b, 200, False, piece_points=toppra_peer.TOPPRA_PIECE_POINTS)
    s_ends = plan.path.s0[1:]
    assert np.all(np.min(np.abs(a + fine.grid[:, None] * (b - a) - s_ends[None]), axis=0) < 1e-9)
    assert toppra_peer.toppra_utilisation(plan, cfg, [uni])["acceleration"] > 1.5
    assert toppra_peer.toppra_utilisation(plan, cfg, [fine])["acceleration"] < 1.05
    assert fine.duration_s > uni.duration_s
