"""Tuning constants of the planning stages (see :mod:`hexacnc.planner.plan` for the method).

ETA (the share of the acceleration and jerk limits) is defined in profile.py, whose acceleration cap uses it;
FD_STEP (the central differences' step) in verify.py, which checks pieces shorter than its stencil.
"""
from __future__ import annotations

import numpy as np

from .profile import ETA

#: fraction of the velocity limit the nominal plan may use
ETA_V = 1.0
#: share of the jerk limit a full acceleration change through the smoothing filter may take: the moving
#: average's width is ``w = max(a_max / j_max) / FILTER_JERK_SHARE`` (a one-sided change of the path
#: acceleration by A then gives path jerk A / w; reversals are kept out of every window by plateaus).  The raw
#: profile uses at most ETA * ACC_SHARE (0.92) of each strut's acceleration limit, so through a window of
#: ``max(A/J)`` a full change reads at most 0.92 of the jerk limit; the curvature terms beside it are held by the
#: acceleration cap and the verification.  1.0 (25 ms on the default machine) since the sixteenth session; at
#: 0.9 (28 ms) the bench paths planned 0.4-3.8 % longer (tort 25-45 3.0595 s instead of 2.9825 s, whole
#: 3D_Chips.ngc 88.35 s instead of 86.97 s)
FILTER_JERK_SHARE = 1.0
#: a jerk-only violation lowers the acceleration cap by the verification's factor f and the speed limit
#: by f ** CAP_JERK_SPEED (the filter's |L'| du / w hardly changes with speed)
CAP_JERK_SPEED = 0.75
#: reach of the spreading, in filter widths: the window's w/2.  It was 0.55 while the ramp out of a slow spot
#: could start at the last grid point inside the reach; with a grid point at every reach end (reachgrid.py) the
#: ramp starts there, and 0.5 plans the bench paths as fast as 0.55 did before or faster (tort 25-45 3.5735 ->
#: 3.5075 s; 0.55 with the points: 3.5995 s; 0.45: smooth 1.9125 -> 1.947 s, more verification passes)
SPREAD_REACH = 0.5
#: the speed limits spread over the filter's reach in time at the speeds of a TOPP solution (tighten.py
#: ``_spread_in_time``), not only over the distance ``T sqrt(x_j)`` travelled at each limit's own speed
SPREAD_IN_TIME = True
#: the filter's acceleration cap (profile._accel_cap) is taken at x0, the speeds of the uncapped TOPP solution,
#: and only grows as speeds drop; where the capped solution y runs slower, it is taken again at the speeds
#: ``v_y + CAP_SPEED_SHARE (v_0 - v_y)``, which become a ceiling there (tighten.Tightener.__init__; 1: off).  On
#: blends that run at their curvature jerk limit in x0 the cap kept 10 % of the jerk budget (25 mm/s^2 against
#: ~1000 beside them) while the capped profile ran at half that speed: twelve G64 P0.05 moves planned 0.6535 s
#: at 0.21 mm and 0.6450 s at 0.24 mm as a line's ramp left the low caps' reach (now 0.6240 / 0.6275 s)
CAP_SPEED_SHARE = 0.5
#: rounds of peak caps per pass (a re-solve moves a ramp by up to a grid step: the second catches that)
CAP_ROUNDS = 2
#: share of the jerk limit the curvature term |L'''| s_dot^3 may take in the TOPP pass
RHO_J = 0.9     # 0.9: 3D_Chips 1.5 % shorter than at 0.8; the verification keeps the total jerk <= ETA
#: share of the jerk limit an acceleration step at a junction may take
RHO_STEP = 0.5
#: share of the planned acceleration (ETA a_max) the TOPP pass may use (the rest absorbs smoothing)
ACC_SHARE = 0.97
#: extra grid offsets from both ends of every piece (s-units)
GRADE_MM = np.array([0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5])
#: the derivatives' step on a piece shorter than FD_PIECE_STEPS * FD_STEP is its length / FD_PIECE_STEPS,
#: at least FD_MIN_STEP (mm; the third difference's rounding, ~1e-16 L / step^3, stays below 1 mm^-2)
FD_PIECE_STEPS = 8
FD_MIN_STEP = 1e-4
#: the shortest derivative step on a corner blend (mm).  A blend's L''' varies on the blend's own length
#: (about its turn / length^2, ~1e10 mm^-2 on a 0.2 um blend), so its step must scale with it: at FD_MIN_STEP
#: the stencil (+-2 steps) of a blend shorter than 0.8 um read its quintic up to a blend's length beyond its
#: ends (a 0.2 um blend's L''' 1.53x too large at its worst point, 1.37x at 0.24 um), an error that shrank as
#: the blend grew, so the limits of tiny blends rose faster than their length: twelve G64 P0.01 moves with
#: rotations planned 0.2555 s at 1.27 um and 0.2530 s at 1.53 um (now 0.2270 / 0.2345 s).  The rounding at
#: this step, ~1e-16 L / step^3 ~ 1e5 mm^-2, stays far below such a blend's L'''; lines, arcs and smoothed
#: pieces keep FD_MIN_STEP (their L''' can be ~0: at length / 8 the rounding of a 0.07 um line's third
#: difference is 80-330 mm^-2, a speed limit of 8-12 mm/s)
FD_MIN_STEP_BLEND = 1e-6
#: grid intervals at least on a piece that rests at both ends (short moves from rest to rest)
REST_PIECE_INTERVALS = 32
#: grid intervals at least on every other programmed piece (not on corner blends: on 1 um G64 moves, whose
#: blends take the whole path, that moved the hills' plateaus and opened a four-cycle dip) shorter than
#: PIECE_MIN_INTERVALS * GRADE_MM[0] (0.2 mm), spaced
#: by a fraction of it: the grid of a short piece scales with the piece, and at that length its points are
#: those the GRADE_MM offsets give a longer one (with one interval a 0.1 mm line from rest ran at one constant
#: path acceleration to the blend after it, about twice the time of a ramp, until its length passed 0.1 mm and
#: a GRADE_MM point split it: twelve random G64 moves planned 16 % shorter for 1 % longer lines).  Not on
#: longer pieces: points at fractions of a piece move against the speed limits spread from the blends at its
#: ends as it grows (twelve 0.84 mm G64 moves then planned 1 % longer than 0.86 mm ones)
PIECE_MIN_INTERVALS = 4
#: the verification's lowering factor at a small violation: the target ratio r (target / measured) times
#: ``1 - LOWER_MARGIN_SLOPE (1/r - 1)``, at least the class's fixed margin (v 0.98, a 0.97, j 0.9), so that a
#: limit is lowered by little where a sample barely crosses its target (a fixed margin lowered it by at
#: least 2-10 % as soon as a sample crossed it: the planned time jumped there)
LOWER_MARGIN_SLOPE = 5.0
#: the verification lowers a violating sample's limit towards this much below its target: a sample a hair over
#: the target (jerk 0.9501 of a 0.95 target) was otherwise lowered by a hair, and stayed over it for pass after
#: pass (3D_Chips.ngc with CAM smoothing: 11 passes, 5 of them for 2 samples at 0.9501; now 8, 1.86 -> 1.32 s CPU,
#: the planned time 60.295 -> 60.3045 s)
LOWER_AIM = 1e-3
#: samples whose interval bound stays below this are not measured by exact inverse kinematics
SCREEN = 0.5
#: thresholds above which a model pass evaluates a sample (v, a, j): its violation thresholds
#: (the bounds are upper bounds of the model, so a sample below them cannot violate), 1e-9 lower
MODEL_SCREEN = (ETA_V * 0.9995 * (1 - 1e-9), ETA * (1 - 1e-9), ETA * (1 - 1e-9))
#: iterations of the tightening loop (steps 3-5) before the plan is refused
MAX_ITERATIONS = 40

#: where a corner's low acceleration cap reaches the ramp from or to a rest, also try the stretch to the corner
#: slow enough to keep it off the ramp, and take the faster (spread.rest_ramp_sides, tighten.Tightener._rest_ramps)
REST_RAMPS = True
#: ... on plans of at most this many grid points: each candidate is a TOPP pass with plateaus over the whole grid,
#: and a longer plan that keeps the ramps at the caps only runs longer, never shorter
REST_RAMP_MAX_POINTS = 2000
