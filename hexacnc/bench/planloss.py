"""Where the planner loses time against the jerk-limited optimum (``time_loss`` in ``hexacnc bench plan``).

The planner's stages are re-run on the bench path (the same functions as :func:`hexacnc.planner.plan_program`)
and the time after each is reported, so that the gap to the optimum splits into its causes:

- ``topp_at_limits_s``: TOPP (acceleration-limited, no jerk) on the planner's speed limits before they are
  spread: feed, strut velocity (99.5 %), the curvature jerk ``|L'''| s_dot^3`` (its share), the junction
  curvature steps and the acceleration bounds (ETA * ACC_SHARE and the filter's acceleration cap);
- ``topp_spread_s``: the same with the limits spread over the filter's reach (every slow spot held for
  about a filter width around it, so that the moving average stays below it);
- ``raw_s``: the raw profile as verified: plateaus at speed peaks and the verification's local lowering
  (``holds_s``: its rests at stops);
- ``hexacnc_s``: the smoothed table (the filter's width and the holds added).

``rows``: per limit the share of moving rows at >= 90 % of it, measured from the rows (exact inverse
kinematics, finite differences), the share of moving rows with every limit below 76 % (80 % of the shares:
slack), and ``time_scaling_bound_s``: the time a pointwise time scaling of the
rows could save at most (each row run at its own room ``min(V/v, sqrt(A/a), cbrt(J/j))``, no transitions).
"""
from __future__ import annotations

import math

import numpy as np

from ..planner import path as P
from ..planner.consts import ETA_V, FILTER_JERK_SHARE, SPREAD_REACH
from ..planner.grid import build_grid, check_grid, derivatives
from ..planner.holds import rests
from ..planner.plan import REACH_POINTS
from ..planner.profile import ETA
from ..planner.reachgrid import with_reach_points
from ..planner.retime import row_utilisation
from ..planner.speeds import speed_limits
from ..planner.tighten import Tightener, tighten
from ..planner.topp import interval_times

NOTE = ("the planner's stages re-run on the path: TOPP on its speed limits before spreading (topp_at_limits_s), "
        "after spreading (topp_spread_s), the raw profile with plateaus and the verification's lowering (raw_s), "
        "the rests at stops (holds_s), the filtered table (hexacnc_s); rows: shares of moving rows at >= 90 % of "
        "each limit and with every limit below 76 % (slack), measured from the rows; time_scaling_bound_s: the most a pointwise "
        "time scaling of the rows could save")
#: a row runs "at" a limit from this fraction of it on (the planning shares are v 0.995, a and j 0.95, the
#: acceleration of the raw profile ETA * ACC_SHARE = 0.92)
AT_LIMIT = 0.9
#: a row has slack when every limit is below this share of its planning share
SLACK = 0.8 * ETA


def time_loss(blocks, cfg) -> dict:
    """The stage times (s) of planning ``blocks`` on ``cfg`` and the rows' use of the limits."""
    from ..kinematics import Hexapod
    hx = Hexapod(cfg)
    dt = float(cfg.cycle.period_s)
    lims = tuple(np.asarray(v, dtype=float) for v in (cfg.max_velocity_mm_s, cfg.max_acceleration_mm_s2,
                                                      cfg.max_jerk_mm_s3))
    path, events = P.build_path(blocks, cfg)
    if path.n == 0:
        return {"skipped": "no motion"}
    w_f = float(np.max(lims[1] / lims[2])) / FILTER_JERK_SHARE
    nf = max(1, int(math.ceil(w_f / dt)))
    g = build_grid(path, hx, cfg, events)
    dv = derivatives(path, hx, g)
    check_grid(path, hx, cfg, g, dv.Xg, dv.tip_g)
    xlim, c, e, dd = speed_limits(path, cfg, g, dv, dt, *lims)
    rs = rests(path, events, g, nf * dt + 2 * dt, dt)
    if REACH_POINTS:
        g, dv, rs, (xlim, c, e, dd) = with_reach_points(path, hx, cfg, events, g, dv, rs, (xlim, c, e, dd), lims,
                                                        dt, SPREAD_REACH * nf * dt, nf * dt + 2 * dt)
    tt = Tightener(path, hx, g, dv, rs, xlim, c, e, dd, lims, dt, nf, nf * dt + 2 * dt)
    x0 = xlim.copy()
    x0[rs.stop_all] = 0.0
    t_limits = float(interval_times(g.h, tt.topp.solve(np.minimum(x0, tt.xcapf))).sum())
    t_spread = float(interval_times(g.h, tt.solve(True, [], [])).sum())     # the first pass's TOPP, as tighten runs it
    prof = tighten(tt)
    t_holds = float(rs.holds_s.sum())
    t_raw = float(interval_times(g.h, prof.x).sum())
    t_plan = (prof.s_f.shape[0] - 1) * dt
    uv, ua, uj = row_utilisation(path, hx, prof.s_f, dt, *lims)
    moving = np.concatenate([[False], np.diff(prof.s_f) > 0])
    n_mov = max(int(moving.sum()), 1)
    with np.errstate(divide="ignore"):
        room = np.minimum(np.minimum(ETA_V * 0.995 / uv, np.sqrt(ETA / ua)), np.cbrt(ETA / uj))
    room = np.maximum(room[moving], 1.0)
    return {
        "topp_at_limits_s": round(t_limits, 4), "topp_spread_s": round(t_spread, 4), "raw_s": round(t_raw, 4),
        "holds_s": round(t_holds, 4), "hexacnc_s": round(t_plan, 4),
        "spreading_s": round(t_spread - t_limits, 4), "plateaus_and_lowering_s": round(t_raw - t_spread, 4),
        "filter_and_holds_s": round(t_plan - t_raw, 4),
        "rows": {"at_velocity": round(float((uv[moving] >= AT_LIMIT).sum()) / n_mov, 4),
                 "at_acceleration": round(float((ua[moving] >= AT_LIMIT).sum()) / n_mov, 4),
                 "at_jerk": round(float((uj[moving] >= AT_LIMIT).sum()) / n_mov, 4),
                 "slack": round(float((np.maximum(np.maximum(uv, ua), uj)[moving] < SLACK).sum()) / n_mov, 4),
                 "time_scaling_bound_s": round(float(np.sum(dt * (1.0 - 1.0 / room))), 4)},
        "note": NOTE,
    }
