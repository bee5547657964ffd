"""Short stretches between rests run as one S-curve along the path (:mod:`hexacnc.planner.reststretch`,
:mod:`hexacnc.planner.scurve`): the 1-D time against Ruckig, the rows within the strut limits by independent
inverse kinematics and finite differences, and the planned time monotonic in the length of a scaled program."""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.bench.jerkfloor import jerk_floor, rest_to_rest_time
from hexacnc.config import load_config
from hexacnc.gcode.factory import program_from_config
from hexacnc.planner import plan_program
from hexacnc.planner import plan as PL
from hexacnc.planner import scurve
from test_planner_motion import run, utilisation


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def _plan(cfg, text):
    return plan_program(program_from_config(text, "t.ngc", cfg).blocks, cfg)


def test_move_time_is_ruckigs_time_optimal_duration():
    """Every regime (jerk only, acceleration reached, velocity reached) over random bounds and lengths."""
    rng = np.random.default_rng(7)
    for _ in range(60):
        D = float(10 ** rng.uniform(-4, 2.5))
        V, A, J = float(10 ** rng.uniform(0, 3)), float(10 ** rng.uniform(2, 4.5)), float(10 ** rng.uniform(3.5, 6))
        assert float(scurve.move_time(D, V, A, J)) == pytest.approx(rest_to_rest_time(D, V, A, J), rel=1e-7, abs=1e-9)


def test_move_time_scales_and_grows():
    """T(kD, kV, kA, kJ) = T(D, V, A, J); longer is never faster; looser bounds never slower."""
    D, V, A, J = 0.37, 12.0, 900.0, 4e4
    t = float(scurve.move_time(D, V, A, J))
    for k in (0.01, 0.5, 3.0, 70.0):
        assert float(scurve.move_time(k * D, k * V, k * A, k * J)) == pytest.approx(t, rel=1e-12)
    d = np.geomspace(1e-6, 100.0, 400)
    assert np.all(np.diff(scurve.move_time(d, V, A, J)) > 0)
    assert float(scurve.move_time(D, 2 * V, A, J)) <= t and float(scurve.move_time(D, V, 2 * A, 2 * J)) <= t


@pytest.mark.parametrize("D", [1e-4, 0.05, 3.0, 80.0])
def test_positions_run_from_rest_to_rest_within_the_bounds(D):
    V, A, J = 20.0, 800.0, 2e4
    T = float(scurve.move_time(D, V, A, J))
    h = T / 4000
    s = scurve.positions(D, V, A, J, np.arange(4001) * h)
    assert s[0] == 0.0 and s[-1] == D and np.all(np.diff(s) >= 0)
    v = np.diff(s) / h
    a = np.diff(v) / h
    j = np.diff(a) / h
    assert v.max() <= V * (1 + 1e-6) and np.abs(a).max() <= A * (1 + 1e-3) and np.abs(j).max() <= J * (1 + 1e-2)


def test_a_micrometre_from_rest_plans_near_its_jerk_floor(cfg):
    """A 1 um move ran the filter's width and a plateau (86.5 ms); as an S-curve it takes a few cycles more than
    the strut floor any jerk-limited plan needs (the bench's per-strut rest-to-rest bound)."""
    for axis in ("X", "Z", "A"):
        p = _plan(cfg, f"G21 G91\nG1 {axis}0.001 F600\nM2\n")
        floor = jerk_floor(p, cfg)["jerk_floor_s"]
        assert floor <= p.duration_s <= floor + 0.008, (axis, p.duration_s, floor)


@pytest.mark.parametrize("text", [
    "G21 G91 G61\n" + "".join(f"G1 X{0.3 * np.cos(k):.4f} Y{0.3 * np.sin(1.3 * k):.4f} F3000\n" for k in range(8)),
    "G21 G91\n" + "G1 X0.07 F1200\nG1 Y0.07\nG1 X-0.07\nG1 Y-0.07\n" * 3,
    "G21 G91 G61\nG0 X2 A1\nG1 Y-1 B-1 C2 F1200\nG0 Z-3\n",
])
def test_rows_stay_within_the_limits_and_the_s_curve_is_faster(cfg, text):
    """Measured from the sampler's rows by exact inverse kinematics and finite differences at the period."""
    p = _plan(cfg, text + "M2\n")
    PL.REST_STRETCHES = False
    try:
        q = _plan(cfg, text + "M2\n")
    finally:
        PL.REST_STRETCHES = True
    assert p.duration_s < q.duration_s
    u = utilisation(cfg, run(p.sampler()), p.dt)
    assert u[0] <= 1.0 and u[1] <= 0.95 and u[2] <= 0.95, u


@pytest.mark.parametrize("body", [
    "G1 X{d:.7f} F1200\nG1 Y{d:.7f}\n",                                      # an L: dropped 17 cycles at 0.078 mm
    "G1 X{d:.7f} Y{e:.7f} F300\nG1 X-{e:.7f} Y{d:.7f}\nG1 X-{d:.7f} Y-{d:.7f}\n",   # three turns at F300
])
def test_blended_tiny_programs_are_monotonic_in_their_length(cfg, body):
    L = np.geomspace(0.005, 0.2, 60)
    dur = [_plan(cfg, "G21 G91\n" + body.format(d=d, e=0.3 * d) + "M2\n").duration_s for d in L]
    drops = [(a, b) for a, b, ta, tb in zip(L[:-1], L[1:], dur[:-1], dur[1:]) if tb < ta]
    assert not drops, drops


def test_the_table_ends_with_the_last_holds_rows_not_the_filters_width(cfg):
    """After the last stop the filtered table stood still for the filter's width (29 ms at M2)."""
    for text in ("G21 G91\nG1 X5 F3000\nG1 Y5\nM2\n", "G21 G91\nG1 X0.01 F600\nM2\n"):
        p = _plan(cfg, text)
        s = p.s_tab
        at_end = int(np.sum(s == s[-1]))
        assert 2 <= at_end <= 4, (text, at_end)
