"""Grid points at the ends of the speed limits' spreading (hexacnc.planner.reachgrid) and the interpolated
limit just beyond an end (profile.reach_end_limits): the inserted points get exactly the derivatives and
limits a grid built with them has, they lie on reach ends, and the limits change continuously as a reach
grows across grid points."""
from __future__ import annotations

import math

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.gcode.factory import program_from_config
from hexacnc.kinematics import Hexapod
from hexacnc.planner import path as P
from hexacnc.planner.consts import FILTER_JERK_SHARE, SPREAD_REACH
from hexacnc.planner.grid import Grid, build_grid, derivatives
from hexacnc.planner.holds import rests
from hexacnc.planner.profile import _accel_cap
from hexacnc.planner.spread import (dilate_min, reach_end_limits, reach_ends, rest_ramp_ceiling, rest_ramp_sides,
                                   spread_cap)
from hexacnc.planner.reachgrid import (REST_RAMP_POINTS, end_positions, insert_points, rest_ramp_positions,
                                      spread_frame, with_reach_points)
from hexacnc.planner.speeds import speed_limits

PROGRAM = """G21 G90 G64 P0.05
G1 X10 Y0 Z-1150 F3000
G1 X10.4 Y0.3 A0.5
G1 X11 Y0.2 B-0.3
G2 X13 Y0.2 I1 J0
G1 X14 Y2 C0.4
G61
G1 X14 Y4
G64 P0.02
G1 X14.05 Y4.02
G1 X14.1 Y4.0
G1 X20 Y4
M2
"""


def planner_stages(cfg, text: str) -> tuple:
    """The planner's stages before the grid's reach points (as plan_program runs them) on a program text:
    (hx, path, events, dt, lims, nf, grid, derivatives, (xlim, c, e, dd), rests)."""
    hx = Hexapod(cfg)
    path, events = P.build_path(program_from_config(text, "t.ngc", cfg).blocks, cfg)
    dt = float(cfg.cycle.period_s)
    lims = tuple(np.asarray(v, dtype=float) for v in (cfg.max_velocity_mm_s, cfg.max_acceleration_mm_s2,
                                                      cfg.max_jerk_mm_s3))
    nf = int(math.ceil(float(np.max(lims[1] / lims[2])) / FILTER_JERK_SHARE / dt))
    g = build_grid(path, hx, cfg, events)
    dv = derivatives(path, hx, g)
    limits = speed_limits(path, cfg, g, dv, dt, *lims)
    rs = rests(path, events, g, nf * dt + 2 * dt, dt)
    return hx, path, events, dt, lims, nf, g, dv, limits, rs


@pytest.fixture(scope="module")
def setup():
    cfg = load_config(None)
    return (cfg, *planner_stages(cfg, PROGRAM))


def test_inserted_points_have_the_derivatives_and_limits_of_a_grid_built_with_them(setup):
    cfg, hx, path, _events, dt, lims, _nf, g, dv, limits, _rs = setup
    rng = np.random.default_rng(5)
    kk = np.sort(rng.choice(np.nonzero(g.h > 0)[0], 40, replace=False))
    kk = np.concatenate([kk, kk[:5]])                        # two points in some intervals
    t = rng.uniform(0.05, 0.95, kk.size)
    order = np.lexsort((t, kk))
    kk, t = kk[order], t[order]
    s = g.sg[kk] + t * (g.sg[kk + 1] - g.sg[kk])
    g2, dv2, lim2 = insert_points(path, hx, cfg, g, dv, lims, dt, kk, s, limits)
    assert g2.n == g.n + kk.size
    assert np.all(np.diff(g2.sg) >= 0)
    # junctions stay duplicated points with zero spacing; every piece still ends on its last point
    assert int(np.sum(g2.h == 0)) == int(np.sum(g.h == 0))
    np.testing.assert_allclose(g2.sg[g2.last], path.s0 + path.slen, rtol=0, atol=1e-12)
    assert np.all(g2.pidx[g2.last] == np.arange(path.n))
    # the same as derivatives and speed limits evaluated on the refined grid from scratch
    fresh = derivatives(path, hx, Grid(g2.sg, g2.pidx, g2.h, g2.last, g.lmarg, g.amarg))
    for name in ("Lp", "Lpp", "Lppp", "Xg", "dtip"):
        np.testing.assert_allclose(getattr(dv2, name), getattr(fresh, name), rtol=1e-12, atol=1e-12)
    again = speed_limits(path, cfg, g2, fresh, dt, *lims)
    for a, b in zip(lim2, again):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=0)


def test_points_lie_on_the_ends_of_binding_reaches(setup):
    cfg, hx, path, events, dt, lims, nf, g, dv, limits, rs = setup
    T = SPREAD_REACH * nf * dt
    kk, s = end_positions(g, rs, limits[0], T)
    assert kk.size > 0
    assert np.all((s > g.sg[kk]) & (s < g.sg[kk + 1]))
    # every position is where some limit's reach ends (in the stop-separated frame)
    sg_sep, _keep, reach_mm = spread_frame(g, rs)
    xw = limits[0].copy()
    xw[rs.stop_all] = np.inf
    fin = np.isfinite(xw)
    r = np.minimum(np.sqrt(np.maximum(np.where(fin, xw, 0.0), 0.0)) * T, reach_mm)
    ends = np.concatenate([sg_sep[fin] + r[fin], sg_sep[fin] - r[fin]])
    s_sep = sg_sep[kk] + (s - g.sg[kk])
    gap = np.min(np.abs(s_sep[:, None] - ends[None, :]), axis=1)
    assert gap.max() < 1e-9 * max(1.0, float(g.sg[-1]))
    g2, _dv2, rs2, lim2 = with_reach_points(path, hx, cfg, events, g, dv, rs, limits, lims, dt, T,
                                            nf * dt + 2 * dt)
    kr, _sr = rest_ramp_positions(g, dv, rs, limits, lims[2], 2.0 * T)
    assert g2.n == g.n + kk.size + (kr.size if REST_RAMP_POINTS else 0)
    assert len(rs2.stop_idx) == len(rs.stop_idx)
    assert np.all(g2.sg[rs2.stop_idx] == g.sg[rs.stop_idx])


def _spread_with_ends(sg, x, T):
    out = dilate_min(sg, x, T)
    return np.minimum(out, reach_end_limits(sg, x, x, T))


def test_limits_change_continuously_as_a_reach_crosses_grid_points():
    """One slow spot among fast points on an uneven grid, a duplicated point among them: as the reach grows,
    without the interpolation the limit of each point it passes drops at once; with it, continuously."""
    sg = np.array([0.0, 0.7, 1.3, 2.0, 2.0, 2.6, 3.5, 4.1, 5.0])
    x = np.array([100.0, 90.0, 80.0, 95.0, 85.0, 1.0, 70.0, 60.0, 100.0])
    Ts = np.linspace(0.01, 4.0, 4000)       # the slow spot's reach sqrt(1) T: 0.01 to 4 around s = 2.6
    plain = np.array([dilate_min(sg, x, T) for T in Ts])
    soft = np.array([_spread_with_ends(sg, x, T) for T in Ts])
    # the interpolation's slope: (upper - x_j) / h per unit of reach, reach sqrt(x_j) per unit of T
    h_min = np.min(np.diff(sg)[np.diff(sg) > 0])
    slope = np.max((x.max() - x) * np.sqrt(x)) / h_min
    assert np.abs(np.diff(plain, axis=0)).max() > 20.0                 # the plain spreading steps
    assert np.abs(np.diff(soft, axis=0)).max() <= 1.01 * slope * (Ts[1] - Ts[0])
    assert np.all(soft <= plain + 1e-12)
    assert np.all(soft[:, 5] == 1.0)
    # the two copies of the duplicated point at s = 2.0 start to fall at the same reach
    assert np.argmax(soft[:, 3] < x[3]) == np.argmax(soft[:, 4] < x[4])
    kk, t, xs, b = reach_ends(sg, x, 0.5)
    slow = xs == 1.0                       # the slow spot's reach 0.5 ends in (2.0, 2.6) and (2.6, 3.5)
    assert sorted(kk[slow].tolist()) == [4, 5]
    np.testing.assert_allclose(np.sort(t[slow]), [0.1 / 0.6, 0.5 / 0.9])


def test_acceleration_caps_change_continuously_as_a_reach_crosses_grid_points():
    """The acceleration cap of each interval (at its first point) as one low cap's reach grows across the
    points of an uneven grid with a duplicated point: continuous, never above the interval's own end caps,
    the low cap on every interval its reach covers whole.  A whole interval used to take the cap as soon as
    the reach touched it (seed 127 of a G64 P0.2 sweep: 75 cycles shorter for a 0.06 % longer move)."""
    sg = 0.1 * np.array([0.0, 0.7, 1.3, 2.0, 2.0, 2.6, 3.5, 4.1, 5.0])      # reaches below SPREAD_CAP_MM
    ecap = np.array([900.0, 800.0, 1000.0, 950.0, 700.0, 100.0, 850.0, 990.0, 600.0])
    x = np.ones_like(ecap)                     # reach T at speed 1 (T < SPREAD_CAP_MM)
    Ts = np.linspace(0.001, 0.19, 3000)
    caps = np.array([spread_cap(sg, ecap, x, T) for T in Ts])
    h_min = np.min(np.diff(sg)[np.diff(sg) > 0])
    slope = (ecap.max() - ecap.min()) / h_min          # per unit of reach
    assert np.abs(np.diff(caps, axis=0)).max() <= 1.01 * slope * (Ts[1] - Ts[0])
    own = np.minimum(ecap[:-1], ecap[1:])
    assert np.all(caps[:, :-1] <= own + 1e-9)
    for T, c in zip(Ts, caps):
        inside = (sg[:-1] >= 0.26 - T) & (sg[1:] <= 0.26 + T)    # intervals the low cap covers whole
        assert np.all(c[:-1][inside] == 100.0)
    # before: the plain spreading and a neighbour's cap, twice, stepped by whole intervals
    plain = np.array([dilate_min(sg, ecap, T, speed2=x) for T in Ts])
    assert np.abs(np.diff(plain, axis=0)).max() > 100.0


def test_a_point_where_the_ramp_from_each_rest_reaches_its_speed(setup):
    """On every interval beside a rest, a point where a ramp at the largest acceleration there (the TOPP bound
    or the filter's cap, the smaller) from rest reaches the far point's speed limit, at most a quarter in."""
    cfg, hx, path, events, dt, lims, nf, g, dv, limits, rs = setup
    w = nf * dt
    kk, s = rest_ramp_positions(g, dv, rs, limits, lims[2], w)
    rest = set(rs.stop_all.tolist())
    sides = [(i, r, a) for i in range(g.n - 1) for r, a in ((i, i + 1), (i + 1, i))
             if r in rest and a not in rest and g.sg[i + 1] > g.sg[i]]
    assert len(sides) > 0 and kk.size == len(sides)
    for (i, r, a), k, sp in zip(sides, kk, s):
        assert k == i
        u = min(float(np.min(limits[2][r])),
                float(_accel_cap(dv.Lp[[r]], dv.Lpp[[r]], dv.Lppp[[r]], limits[0][[a]], lims[2], w)[0]))
        d = abs(sp - g.sg[r])
        h = g.sg[i + 1] - g.sg[i]
        assert d == pytest.approx(min(limits[0][a] / (2 * u), 0.25 * h), rel=1e-12)
        assert g.sg[i] < sp < g.sg[i + 1]


def test_rest_ramp_sides_and_their_ceilings_by_hand():
    """Rests at both ends of five 0.01 mm intervals, one low cap (100 against 1000) at 0.03 mm, 4 mm/s, T = 14 ms
    (reach 0.056 mm): from the first rest its distance from the ramp's far point is 0.02 mm, from the last 0.01 mm;
    keeping it off asks every point between no faster than distance / T."""
    sg = np.array([0.0, 0.01, 0.02, 0.03, 0.04, 0.05])
    h = np.diff(sg)
    at_rest = np.array([True, False, False, False, False, True])
    ecap = np.array([1000.0, 1000.0, 1000.0, 100.0, 1000.0, 1000.0])
    x = np.full(6, 16.0)
    T = 0.014
    sides = rest_ramp_sides(sg, h, at_rest, ecap, x, T)
    assert [(r, a, step) for r, a, step, _p, _l in sides] == [(0, 1, 1), (5, 4, -1)]
    assert [[k for k, _d, _c in sd[3]] for sd in sides] == [[3], [3]]
    assert sides[0][3][0][1] == pytest.approx(0.02) and sides[1][3][0][1] == pytest.approx(0.01)
    assert sides[0][4] == [100.0]
    out = np.full(6, np.inf)
    rest_ramp_ceiling(T, sides[0], 100.0, out)
    np.testing.assert_allclose(out[1:4], (0.02 / T) ** 2, rtol=1e-5)
    assert np.all(np.isinf(out[[0, 4, 5]]))
    rest_ramp_ceiling(T, sides[1], 100.0, out)
    np.testing.assert_allclose(out[3:5], (0.01 / T) ** 2, rtol=1e-5)
    # a cap too far to reach the ramp, or not low, asks nothing
    assert rest_ramp_sides(sg, h, at_rest, ecap, np.full(6, 0.5), T) == []
    assert rest_ramp_sides(sg, h, at_rest, np.full(6, 1000.0), x, T) == []
