"""Tables of a plan (the last step of :mod:`hexacnc.planner.plan`): source line and flags per row, holds
marked as dwells, events and program pauses placed, per-line times."""
from __future__ import annotations

import math

import numpy as np

from ..gcode import blocks as B
from ..setpoint import FLAG_DWELL, FLAG_END, FLAG_EVENT, FLAG_MOTION, FLAG_PROGRAM_PAUSE, FLAG_RAPID
from . import path as P
from .grid import Grid
from .holds import Rests, hold_rows


def event_value(blk):
    """The value an event row reports: spindle rpm, coolant state, tool number, dwell seconds."""
    return {B.SPINDLE: float(getattr(blk, "spindle_rpm", 0.0)), B.COOLANT: getattr(blk, "coolant", "off"),
            B.TOOL_CHANGE: int(getattr(blk, "tool", 0)), B.DWELL: float(getattr(blk, "seconds", 0.0))
            }.get(blk.kind)


def row_tables(path: P.Path, events, g: Grid, rs: Rests, s_f: np.ndarray, TH: np.ndarray, dt: float, nf: int):
    """Returns (line_tab, flag_tab, events [(time_s, line, kind, value)], pause_idx, line_times)."""
    Nt = s_f.shape[0]
    pt = path.piece_at(s_f)
    line_tab = path.line[pt].astype(np.int32)
    flag_tab = np.where(path.rapid[pt], FLAG_MOTION | FLAG_RAPID, FLAG_MOTION).astype(np.int32)
    ev_out = []
    pause_idx = []
    for k, hd in sorted(rs.holds.items()):
        # the smoothed table stands still once the filter window lies inside the raw hold
        c0, c1 = hold_rows(TH[k], rs.holds_s[k], dt, nf)
        c0 = max(0, min(Nt - 1, c0))
        c1 = min(Nt - 1, max(c0, c1))
        line_tab[c0:c1 + 1] = hd.line
        flag_tab[c0:c1 + 1] = FLAG_DWELL
        for blk in hd.kinds:
            ev_out.append((c0 * dt, int(blk.line), blk.kind, event_value(blk)))
            flag_tab[c0] |= FLAG_EVENT
        if hd.pause or hd.optional:
            p = (c0 + c1) // 2
            pause_idx.append((p, hd.optional, hd.line))
            flag_tab[p] |= FLAG_PROGRAM_PAUSE
    # events that do not stop (coolant) are attached at their position
    for m, blk in events:
        if blk.kind not in P.STOP_EVENTS:
            k = int(g.last[m]) if m >= 0 else 0
            j = max(0, min(Nt - 1, int(math.floor(TH[k] / dt)) + nf // 2))
            ev_out.append((j * dt, int(blk.line), blk.kind, getattr(blk, "coolant", None)))
            flag_tab[j] |= FLAG_EVENT
    flag_tab[-1] |= FLAG_END
    return line_tab, flag_tab, ev_out, pause_idx, line_times(line_tab, dt)


def line_times(line_tab: np.ndarray, dt: float) -> dict:
    """{line: (first row's time, last row's time + dt)} of a line table."""
    out: dict[int, tuple[float, float]] = {}
    Nt = line_tab.shape[0]
    if Nt:
        ul, first_i = np.unique(line_tab, return_index=True)
        _, last_rev = np.unique(line_tab[::-1], return_index=True)
        last_i = Nt - 1 - last_rev
        for ln, a0, a1 in zip(ul.tolist(), first_i.tolist(), last_i.tolist()):
            out[int(ln)] = (a0 * dt, (a1 + 1) * dt)
    return out
