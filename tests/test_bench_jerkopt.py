"""The jerk-limited optimum peer of ``hexacnc bench plan`` (:mod:`hexacnc.bench.jerkopt`): validated against
Ruckig on one-axis problems (within 1 %), against TOPP-RA with the jerk limit lifted (within 2 %), and for the
same optimum from different starts.  Needs the bench extra (casadi; toppra for the TOPP-RA check): the tests
skip with that reason where it is absent."""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.bench import jerkopt as JO
from hexacnc.bench.jerkfloor import _rest_points, _sections, rest_to_rest_time
from hexacnc.config import load_config
from hexacnc.gcode.factory import program_from_config
from hexacnc.planner import plan_program

casadi = pytest.importorskip("casadi", reason="the jerk-limited optimum needs casadi (pip install 'hexacnc[bench]')")


@pytest.mark.parametrize("d,v,a,j", [(0.01, 500, 5000, 2e5), (1.0, 500, 5000, 2e5), (40.0, 500, 5000, 2e5),
                                     (120.0, 300, 8000, 5e4), (5.0, 100, 20000, 1e5)])
def test_one_axis_optimum_matches_ruckig_within_1_percent(d, v, a, j):
    opt = JO.solve(JO.one_axis(d, 800), [v], [a], [j])
    assert opt.status == "Solve_Succeeded"
    ref = rest_to_rest_time(d, v, a, j)
    assert opt.duration_s == pytest.approx(ref, rel=0.01)
    assert opt.duration_s >= ref * (1 - 1e-6)           # Ruckig is optimal: the NLP cannot beat it
    # the solution respects its limits at the nodes
    assert np.max(np.abs(opt.v)) <= v * (1 + 1e-6) and np.max(np.abs(opt.a)) <= a * (1 + 1e-6)
    assert np.max(np.abs(opt.j)) <= j * (1 + 1e-6)


def test_same_optimum_from_different_starts():
    pd = JO.one_axis(25.0, 400)
    V, A, J = np.array([400.0]), np.array([6000.0]), np.array([1.5e5])
    o1 = JO.solve(pd, V, A, J)
    v, a, jj, T = JO._guess(pd, V, A, J)
    o2 = JO.solve(pd, V, A, J, guess=(0.2 * v, 0.04 * a, 0.008 * jj, 5.0 * T))
    assert o1.status == o2.status == "Solve_Succeeded"
    assert o1.duration_s == pytest.approx(o2.duration_s, rel=1e-5)


@pytest.fixture(scope="module")
def arc_plan():
    """A helical arc and a line from rest to rest, feeds and angular velocity lifted."""
    import dataclasses
    from hexacnc.bench.toppra_peer import _lifted_config
    cfg = _lifted_config(load_config(None), False)
    cfg = cfg.replace(planner=dataclasses.replace(cfg.planner, default_feed_mm_min=6e7))
    text = "G21 G90 G64 P0.5\nG1 X20 F6000000\nG2 X-20 Y0 Z-10 I-20 J0\nG1 X-20 Y-30\nM2\n"
    plan = plan_program(program_from_config(text, "arc.ngc", cfg).blocks, cfg)
    return cfg, plan, _sections(_rest_points(plan))


@pytest.mark.slow
def test_optimum_with_jerk_lifted_matches_toppra_within_2_percent(arc_plan):
    pytest.importorskip("toppra", reason="the TOPP-RA check needs toppra (pip install 'hexacnc[bench]')")
    from hexacnc.bench.toppra_peer import TOPPRA_PIECE_POINTS, _toppra_section
    cfg, plan, secs = arc_plan
    r = JO.jerk_optimum(plan, cfg, secs, jerk_scale=1e4)
    assert r["ok"]
    tt = sum(_toppra_section(plan, cfg, a, b, 2000, False, TOPPRA_PIECE_POINTS).duration_s for a, b in secs)
    assert r["duration_s"] == pytest.approx(tt, rel=0.02)


@pytest.mark.slow
def test_optimum_is_a_lower_bound_for_hexacnc_and_above_the_rest_to_rest_floor(arc_plan):
    from hexacnc.bench.jerkfloor import jerk_floor
    cfg, plan, secs = arc_plan
    r = JO.jerk_optimum(plan, cfg, secs)
    assert r["ok"]
    floor = jerk_floor(plan, cfg)["jerk_floor_s"]
    assert floor * (1 - 1e-3) <= r["duration_s"] < plan.duration_s
    u = JO.utilisation(plan.path, plan.hexapod, cfg, r["sections"])
    assert 0.9 < max(u.values()) < 1.1          # at the limits (between nodes it may exceed slightly)


@pytest.mark.slow
def test_optimum_at_the_planners_shares_lies_between_the_full_optimum_and_its_time_scaling():
    """Lower limits cannot be faster; the full optimum slowed by c = min(0.995, sqrt(0.95), cbrt(0.95)) keeps
    every limit within its share, so the optimum at the shares takes at most 1 / c times as long."""
    from hexacnc.bench.toppra_peer import _lifted_config, stops_path_blocks
    cfg = _lifted_config(load_config(None), False)
    plan = plan_program(stops_path_blocks(cfg, moves=((5.0, (1, 0, 0)),)), cfg)
    secs = _sections(_rest_points(plan))
    full = JO.jerk_optimum(plan, cfg, secs)
    part = JO.jerk_optimum(plan, cfg, secs, shares=JO.PLAN_SHARES)
    assert full["ok"] and part["ok"]
    c = min(JO.PLAN_SHARES[0], JO.PLAN_SHARES[1] ** 0.5, JO.PLAN_SHARES[2] ** (1 / 3))
    assert full["duration_s"] * (1 - 1e-6) <= part["duration_s"] <= full["duration_s"] / c * (1 + 1e-4)


def test_jerk_terms_bounded_one_by_one_change_nothing_on_one_axis():
    """One axis has no curvature terms (L'' = L''' = 0): bounding the terms one by one is the same problem."""
    pd = JO.one_axis(12.0, 400)
    V, A, J = np.array([400.0]), np.array([6000.0]), np.array([1.5e5])
    signed = JO.solve(pd, V, A, J)
    terms = JO.solve(pd, V, A, J, jerk_by_terms=True)
    assert signed.status == terms.status == "Solve_Succeeded"
    assert terms.duration_s == pytest.approx(signed.duration_s, rel=1e-5)
    assert terms.duration_s == pytest.approx(rest_to_rest_time(12.0, 400.0, 6000.0, 1.5e5), rel=0.01)


@pytest.mark.slow
def test_jerk_terms_bounded_one_by_one_cost_time_and_hold_term_by_term(arc_plan):
    """On a curved path the signed optimum is at most the one with the terms bounded one by one, and that
    solution keeps |L'''| v^3 + 3 |L''| v |a| + |L'| |j| within every strut's limit at the nodes (derivatives
    of the departing interval, taken here again from the path)."""
    cfg, plan, secs = arc_plan
    signed = JO.jerk_optimum(plan, cfg, secs)
    terms = JO.jerk_optimum(plan, cfg, secs, jerk_by_terms=True)
    assert signed["ok"] and terms["ok"]
    assert signed["duration_s"] <= terms["duration_s"] * (1 + 1e-6)
    J = np.asarray(cfg.max_jerk_mm_s3, dtype=float)
    worst = 0.0
    for (a, b), o in zip(secs, terms["sections"]):
        pd = JO.section_derivs(plan.path, plan.hexapod, a, b, JO.section_step(a, b))
        assert np.allclose(pd.s, o.s)
        v, acc = o.v[:-1, None], o.a[:-1, None]
        sums = (np.abs(pd.L3b[:-1]) * v ** 3 + 3 * np.abs(pd.L2b[:-1]) * v * np.abs(acc)
                + np.abs(pd.L1b[:-1]) * np.abs(o.j)[:, None])
        worst = max(worst, float(np.max(sums / J[None])))
    assert 0.9 < worst <= 1 + 1e-5



@pytest.mark.slow
def test_the_report_gives_terms_one_by_one_at_the_shares():
    """A 2 mm move from rest to rest: with both options the report's floor (each jerk term bounded on its own, at
    the plan's shares) is no faster than either relaxation alone (terms one by one at the full limits, signed
    sum at the shares), and at most the terms-one-by-one optimum slowed by c = min(0.995, sqrt(0.95),
    cbrt(0.95)), which keeps every term within its share (each scales with a power >= 1 of the slowing); its
    cost and ratio are its duration against the optimum's and hexacnc's."""
    from hexacnc.bench.toppra_peer import _lifted_config, stops_path_blocks
    cfg = _lifted_config(load_config(None), False)
    plan = plan_program(stops_path_blocks(cfg, moves=((2.0, (1, 0, 0)),)), cfg)
    rep = JO.jerk_optimum_report(plan, cfg, _rest_points(plan), at_shares=True, by_terms=True)
    assert rep["by_terms_at_shares_solver_ok"]
    both = rep["jerk_optimum_by_terms_at_shares_s"]
    assert both >= max(rep["jerk_optimum_at_shares_s"], rep["jerk_optimum_by_terms_s"]) * (1 - 1e-5)
    c = min(JO.PLAN_SHARES[0], JO.PLAN_SHARES[1] ** 0.5, JO.PLAN_SHARES[2] ** (1 / 3))
    assert both <= rep["jerk_optimum_by_terms_s"] / c * (1 + 1e-4)
    assert rep["by_terms_at_shares_cost"] == pytest.approx(both / rep["jerk_optimum_s"], rel=1e-4)
    assert rep["jerk_optimum_by_terms_at_shares_ratio"] == pytest.approx(plan.duration_s / both, rel=1e-4)
    assert rep["jerk_optimum_by_terms_at_shares_ratio"] > 1.0

