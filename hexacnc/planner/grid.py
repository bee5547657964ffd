"""Planning grid (step 2 of :mod:`hexacnc.planner.plan`): positions in s whose spacing bounds the strut-length
error between samples, the strut derivatives on it by central differences, and the path-limit checks there
(strut lengths, joint angles, singularity, Cartesian soft limits).  :func:`check_path` is the whole
validation of a path: the streaming validation runs it without the time parameterisation.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import PlanError
from . import path as P
from .consts import (FD_MIN_STEP, FD_MIN_STEP_BLEND, FD_PIECE_STEPS, GRADE_MM, PIECE_MIN_INTERVALS,
                     REST_PIECE_INTERVALS)
from .limits import _check_limits
from .softlimits import check_box
from .verify import FD_STEP


@dataclass
class Grid:
    """Grid points ``sg`` (Ng,) of a path: piece ``pidx`` of each, ``h`` (Ng-1,) spacing (0 at duplicated
    junction points), ``last`` (M,) the last grid point of every piece, and the check margins."""
    sg: np.ndarray
    pidx: np.ndarray
    h: np.ndarray
    last: np.ndarray
    lmarg: np.ndarray
    amarg: np.ndarray

    @property
    def n(self) -> int:
        return int(self.sg.shape[0])


@dataclass
class Derivs:
    """Strut derivatives along s at the grid (Ng,6) and what the speed limits need."""
    Lp: np.ndarray
    Lpp: np.ndarray
    Lppp: np.ndarray
    Xg: np.ndarray          #: platform poses (Ng,6) mm/rad
    dtip: np.ndarray        #: d tool-tip / ds (Ng,6)
    tip_g: np.ndarray | None  #: tool tips at the grid (Ng,6), dropped after the checks


#: most check samples one plan (a window) may take: ~60,000 on a window of dense CAM (3D_Chips.ngc); a single
#: move of 692,689 deg about A over 1.3 mm asked for tens of millions and 17.5 GB before any check could refuse it
MAX_GRID_POINTS = 1_000_000


def _check_size(path: P.Path, nint: np.ndarray) -> None:
    """Raise :class:`PlanError` (limit ``"check_samples"``) at the piece where the path's check samples
    (``nint`` intervals per piece) pass :data:`MAX_GRID_POINTS`, before any of them is allocated."""
    total = np.cumsum(np.asarray(nint, dtype=np.float64) + 1.0)
    if total.size == 0 or total[-1] <= MAX_GRID_POINTS:
        return
    k = int(np.searchsorted(total, MAX_GRID_POINTS, side="right"))      # < size: total[-1] is over the bound
    raise PlanError(f"the path up to here needs {total[k]:.4g} limit-check samples, at most {MAX_GRID_POINTS} in "
                    f"one plan (the daemon plans a long program window by window): a rotation or curvature this "
                    f"large for the move's length, or too many such moves", line=int(path.line[k]),
                    limit="check_samples")


def build_grid(path: P.Path, hx, cfg, events) -> Grid:
    """Uniform samples at the bounded spacing plus a geometric refinement near both ends of each piece."""
    h_p, nint, lmarg, amarg = P.sample_spacing(path, hx.plat, float(np.min(hx.min_length)),
                                               cfg.planner.sample_bound_mm)
    _check_size(path, nint)
    # a piece that rests at both ends (a short move from rest to rest) needs moving grid points inside, and
    # enough of them that its speed peak gets a plateau near the best level (the caps place plateaus
    # between grid points): REST_PIECE_INTERVALS at least (a finer spacing only tightens the bounds above)
    rest_end = np.zeros(path.n, dtype=bool)
    rest_end[[m for m in path.stops_after]] = True
    rest_end[[m for m, blk in events if m >= 0 and blk.kind in P.STOP_EVENTS]] = True
    rest_start = np.concatenate([[True], rest_end[:-1]])
    two = rest_start & rest_end & (nint < REST_PIECE_INTERVALS)
    if two.any():
        nint = np.where(two, REST_PIECE_INTERVALS, nint)
        h_p = np.where(two, path.slen / REST_PIECE_INTERVALS, h_p)
    # every other short programmed piece (not a corner blend): at least PIECE_MIN_INTERVALS, a fraction of its
    # length (its grid scales with it; at PIECE_MIN_INTERVALS * GRADE_MM[0] those points are the GRADE_MM
    # offsets a longer piece gets)
    few = ((nint < PIECE_MIN_INTERVALS) & (path.slen > 0) & (path.slen < PIECE_MIN_INTERVALS * GRADE_MM[0])
           & (path.kind != P.BLEND))
    if few.any():
        nint = np.where(few, PIECE_MIN_INTERVALS, nint)
        h_p = np.where(few, path.slen / PIECE_MIN_INTERVALS, h_p)
    pidx, u_loc, counts = P.grid_offsets(path, h_p, nint, GRADE_MM)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    sg = path.s0[pidx] + u_loc
    last = first + counts - 1
    sg[last] = path.s0 + path.slen
    h = np.diff(sg)
    h[last[:-1]] = 0.0        # duplicated junction points
    h = np.maximum(h, 0.0)
    return Grid(sg, pidx, h, last, lmarg, amarg)


def derivatives(path: P.Path, hx, g: Grid) -> Derivs:
    """Strut derivatives by central differences (same piece formula on both sides).

    The step is FD_STEP, or an eighth of a shorter piece (the stencil of a piece far shorter than FD_STEP
    reads its polynomial far outside the piece: a 1 um blend's third derivative came out orders too large);
    a zero-length piece keeps FD_STEP (its polynomial is only read at its point); the rounding of a third
    difference grows as 1 / step^3, FD_MIN_STEP keeps it far below any jerk bound that matters; a corner
    blend's step goes down to FD_MIN_STEP_BLEND (its L''' grows as 1 / length^2: a fixed step overestimated
    a sub-micrometre blend's by a factor that shrank as the blend grew).
    """
    sg, pidx = g.sg, g.pidx
    sl = path.slen[pidx]
    lo = np.where(path.kind[pidx] == P.BLEND, FD_MIN_STEP_BLEND, FD_MIN_STEP)
    d = np.where(sl > 0, np.minimum(FD_STEP, np.maximum(sl / FD_PIECE_STEPS, lo)), FD_STEP)
    offs = (-2, -1, 0, 1, 2)
    Ls = []
    tips = []
    tool_pt = path.tool_point[pidx]
    Xg = None
    for o, tip in zip(offs, path.tips(pidx, [sg + o * d for o in offs])):
        X, L = P.platform_struts(tip, tool_pt, hx.plat, hx.base)
        Ls.append(L)
        if o == 0:
            Xg = X
        if o in (-1, 1):
            tips.append(tip)
    Lm2, Lm1, L0, Lp1, Lp2 = Ls
    del Ls
    dc = d[:, None]
    Lp = (Lp1 - Lm1) / (2 * dc)
    Lpp = (Lp1 - 2 * L0 + Lm1) / (dc * dc)
    Lppp = (Lp2 - 2 * Lp1 + 2 * Lm1 - Lm2) / (2 * dc ** 3)
    dtip = (tips[1] - tips[0]) / (2 * dc)
    tip_g = 0.5 * (tips[0] + tips[1])         # tool tip at the grid (the mean of the +-d samples: O(d^2) off)
    return Derivs(Lp, Lpp, Lppp, Xg, dtip, tip_g)


def check_grid(path: P.Path, hx, cfg, g: Grid, Xg: np.ndarray, tip_g: np.ndarray) -> tuple[float, float]:
    """The machine's limits at the grid, then the Cartesian soft limits (the machine's own limits name the
    physical cause first).  Returns (min joint margin deg, min length margin mm); raises PlanError."""
    jmarg, lmmarg = _check_limits(path, hx, cfg, g.sg, g.pidx, Xg, g.lmarg, g.amarg)
    check_box(cfg, Xg, tip_g, path.line[g.pidx])
    return jmarg, lmmarg


def check_path(path: P.Path, hx, cfg, events) -> tuple[int, float, float]:
    """Validation of a path without its time parameterisation: the grid, the platform poses and tool tips
    on it (no derivatives) and :func:`check_grid`.  Returns (grid points, joint margin, length margin)."""
    g = build_grid(path, hx, cfg, events)
    tip = path.tip(g.pidx, g.sg)
    X = P.tip_to_platform(tip, path.tool_point[g.pidx])
    jm, lm = check_grid(path, hx, cfg, g, X, tip)
    return g.n, jm, lm
