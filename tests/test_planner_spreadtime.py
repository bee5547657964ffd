"""Speed limits spread over the filter's reach measured in time (tighten.Tightener._spread_in_time,
spread.time_coordinate): every limit holds within T seconds of travel at the speeds of the TOPP solution under
the distance spreading, the result only relaxes that spreading, and it plans slow-cornered paths shorter within
the strut limits (measured from the sampler's rows)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.gcode.factory import program_from_config
from hexacnc.planner import plan_program
from hexacnc.planner import tighten as TG
from hexacnc.planner.consts import SPREAD_REACH
from hexacnc.planner.reachgrid import with_reach_points
from hexacnc.planner.spread import time_coordinate
from hexacnc.planner.toppvec import WavefrontTopp
from test_planner_motion import run, utilisation
from test_planner_reachgrid import planner_stages


def _zigzag(seed: int, n: int = 24, tol: float = 0.01) -> str:
    """Short lines (0.5-3 mm) turning 20-70 deg, small rotations on some, G64 P tol, a G61 stop halfway: CAM-like
    slow blended corners."""
    rng = np.random.default_rng(seed)
    lines = ["G21 G90 G64 P%g" % tol, "G1 X0 Y0 Z0 F6000"]
    p, ang = np.zeros(2), 0.0
    for k in range(n):
        ang += math.radians(rng.uniform(20, 70)) * rng.choice([-1, 1])
        p = p + rng.uniform(0.5, 3.0) * np.array([math.cos(ang), math.sin(ang)])
        a = " A%.3f" % rng.uniform(-0.3, 0.3) if k % 3 == 0 else ""
        lines.append("G1 X%.4f Y%.4f%s" % (p[0], p[1], a))
        if k == n // 2:
            lines.append("G61")
        elif k == n // 2 + 1:
            lines.append("G64 P%g" % tol)
    return "\n".join(lines) + "\nM2\n"


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def test_time_coordinate_is_travel_time_with_a_gap_at_rest():
    sg = np.array([0.0, 1.0, 3.0, 3.0, 4.0, 1004.0, 1006.0])
    x = np.array([4.0, 4.0, 16.0, 16.0, 0.0, 0.0, 1.0])          # speeds 2, 2, 4, 4, 0, 0, 1
    tau = time_coordinate(sg, x, gap_s=50.0)
    # constant acceleration between points: 2 h / (v_k + v_k+1)
    np.testing.assert_allclose(np.diff(tau), [0.5, 2 * 2.0 / 6.0, 0.0, 2 * 1.0 / 4.0, 50.0, 2 * 2.0 / 1.0])


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_limits_spread_in_time_hold_within_t_seconds_at_the_distance_spreadings_speeds(cfg, seed):
    """Checked by brute force: for every grid point j, every moving point whose position is within T seconds of
    j's at the speeds of the TOPP solution under the distance spreading has a spread limit no higher than j's
    own limit; on the planner's grid (points at the distance spreading's reach ends) they are never below the
    distance spreading's limits, and above them beside the slow corners."""
    hx, path, events, dt, lims, nf, g, dv, (xlim, c, e, dd), rs = planner_stages(cfg, _zigzag(seed))
    # the grid with its points at the distance spreading's reach ends, as plan_program builds it
    g, dv, rs, (xlim, c, e, dd) = with_reach_points(path, hx, cfg, events, g, dv, rs, (xlim, c, e, dd), lims, dt,
                                                    SPREAD_REACH * nf * dt, nf * dt + 2 * dt)
    tt = TG.Tightener(path, hx, g, dv, rs, xlim, c, e, dd, lims, dt, nf, nf * dt + 2 * dt)
    x = xlim.copy()
    x[rs.stop_all] = 0.0
    dist = tt._spread(x.copy(), x.copy())                 # the distance spreading
    x0 = WavefrontTopp(g.h, c, e, dd).solve(dist)
    p1 = tt._spread_in_time(x, x0)
    own = x.copy()
    own[rs.stop_all] = np.inf
    tau = time_coordinate(tt.sg_sep, x0)
    T = SPREAD_REACH * nf * dt
    moving = np.ones(g.n, dtype=bool)
    moving[rs.stop_all] = False
    worst = 0.0
    for j in np.nonzero(np.isfinite(own))[0]:
        win = (np.abs(tau - tau[j]) <= T) & moving
        worst = max(worst, float(np.max(p1[win] / own[j])))
    assert worst <= 1.0 + 1e-12
    assert np.all(p1[moving] >= dist[moving] * (1 - 1e-6))     # a relaxation of the distance spreading
    assert np.sum(p1 > dist * 1.01) > 0
    assert np.all(tt.xlim <= p1)                          # the planner's limits: these, lowered by the cap


@pytest.mark.parametrize("seed", [4, 5])
def test_spreading_in_time_plans_slow_corners_shorter_within_the_limits(cfg, seed, monkeypatch):
    blocks = program_from_config(_zigzag(seed), "t.ngc", cfg).blocks
    fast = plan_program(blocks, cfg)
    monkeypatch.setattr(TG, "SPREAD_IN_TIME", False)
    slow = plan_program(blocks, cfg)
    assert fast.duration_s < 0.98 * slow.duration_s
    u = utilisation(cfg, run(fast.sampler()), fast.dt)
    assert max(u) <= 0.96
