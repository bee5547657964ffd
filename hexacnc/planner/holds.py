"""Stops and holds on the planning grid (part of step 3 of :mod:`hexacnc.planner.plan`): the grid points where
the motion rests (corner stops, events, the ends) and the standstill after each (dwells, M0/M1, the filter's
minimum)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..gcode import blocks as B
from . import path as P
from .grid import Grid


@dataclass
class Hold:
    grid: int                  #: hold after grid point
    seconds: float             #: extra standstill beyond the filter's minimum
    line: int
    pause: bool = False        #: M0 (or M1 with optional stop) waits for resume
    optional: bool = False
    kinds: list = field(default_factory=list)


@dataclass
class Rests:
    """Where and how long the motion rests: ``holds`` {grid point: Hold} (events), ``stop_idx`` the stop
    grid points (with the ends), ``stop_all`` with their duplicated junction points, ``holds_s`` (Ng,)
    standstill seconds after each grid point, ``rest_grid`` the points with a hold."""
    holds: dict
    stop_idx: np.ndarray
    stop_all: np.ndarray
    holds_s: np.ndarray
    rest_grid: list


def rests(path: P.Path, events, g: Grid, hold_min: float, dt: float) -> Rests:
    holds: dict[int, Hold] = {}
    stop_grid = set()
    Ng = g.n
    for m in path.stops_after:
        stop_grid.add(int(g.last[m]))
    for m, blk in events:
        k = int(g.last[m]) if m >= 0 else 0
        hd = holds.setdefault(k, Hold(k, 0.0, int(blk.line)))
        hd.kinds.append(blk)
        if blk.kind == B.DWELL:
            hd.seconds += max(0.0, float(blk.seconds or 0.0))
            hd.line = int(blk.line)
        elif blk.kind == B.PAUSE:
            hd.pause = True
            hd.line = int(blk.line)
        elif blk.kind == B.OPTIONAL_PAUSE:
            hd.optional = True
            hd.line = int(blk.line)
        if blk.kind in P.STOP_EVENTS:
            stop_grid.add(k)
    stop_idx = np.array(sorted(stop_grid | {0, Ng - 1}), dtype=np.int64)
    # at a stop both duplicated junction points are at rest
    dup = stop_idx[stop_idx + 1 < Ng]
    dup = dup[g.h[dup] == 0] + 1
    stop_all = np.concatenate([stop_idx, dup])
    holds_s = np.zeros(Ng)
    for k in stop_idx:
        # the program's start and end need no hold: the smoothing starts from rest and its tail
        # (T of the final position) brings the motion to rest
        if 0 < k < Ng - 1:
            holds_s[k] = hold_min
    for k, hd in holds.items():
        extra = hd.seconds
        if hd.pause or hd.optional:
            extra += 2 * hold_min
        holds_s[k] = hold_min + extra + (2 * dt if extra > 0 else 0.0)
    holds_s[0] = max(holds_s[0], 0.0)
    rest_grid = [int(k) for k in np.nonzero(holds_s > 0)[0]]
    return Rests(holds, stop_idx, stop_all, holds_s, rest_grid)


def hold_rows(th_s: float, hold_s: float, dt: float, nf: int) -> tuple[int, int]:
    """First and last row (not clamped to the table) at which the filtered table stands still in a raw hold of
    ``hold_s`` seconds from raw time ``th_s``: the rows whose filter window of ``nf`` rows lies inside the hold."""
    return int(math.ceil(th_s / dt - 1e-9)) + nf, int(math.floor((th_s + hold_s) / dt + 1e-9)) - 1
