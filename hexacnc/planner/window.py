"""Windowed planning: programs of any length planned window by window, with memory bounded by the window.

:func:`plan_windows` takes the interpreter's blocks as an iterator (``hexacnc.gcode.iter_blocks``
streams them) and yields :class:`Window` s, each a :class:`~hexacnc.planner.plan.Plan` from rest to rest.
A window closes at a point where the motion rests anyway (:func:`rest_after`: an event that stops -
dwell, M0/M1, spindle, tool change -, exact stop G61, a tool-length change, a reversal, a corner with
blend tolerance 0), the last such point once ``[planner] window_blocks`` motion blocks or an estimated
``window_s`` seconds of motion are buffered.  Only where the buffer has no such point (a CAM stretch
longer than the window without one) the window ends at its sharpest corner past MIN_SHARE of the buffer, where the
motion then stops (``Window.forced_stop``; counted in the summaries).  A program that fits one window is
planned exactly as :func:`~hexacnc.planner.plan.plan_program` plans it.

Memory: the buffered blocks (at most one window) plus the window being planned.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..gcode import blocks as B
from ..pose import matrix_from_euler
from . import path as P
from .blocktime import block_seconds as _seconds, plain_floats as _floats
from .plan import Plan, plan_program
from .timefit import line_sums

#: motion blocks of the first window when motion starts before the validation ends (then 2x, 4x, ...)
FIRST_WINDOW_BLOCKS = 100
#: a window closes at a rest point once it holds at least this share of ``window_blocks`` motion blocks
MIN_SHARE = 0.25
#: cosine of the turn between moves below which the planner stops there (a reversal, as in path.py)
REVERSAL_COS = -0.996


@dataclass
class Window:
    index: int
    plan: Plan
    last: bool                 #: no window follows
    first_line: int
    last_line: int
    blocks: int
    forced_stop: bool = False  #: ends at a stop the program does not have (no rest point in the window)
    nominal_s: float = 0.0     #: its blocks' nominal seconds at their programmed feeds (blocktime)
    time_sums: tuple = ()      #: per-line sums of nominal s, blocks and planned s (timefit.line_sums)


def tool_tip_pose_deg(cfg, platform_rad) -> list[float]:
    """Tool reference point (tool length 0) of a platform pose (mm, rad) -> [x,y,z mm, a,b,c deg]."""
    X = np.asarray(platform_rad, dtype=float)
    R = matrix_from_euler(*X[3:6])
    tip = X[:3] + R @ np.asarray(cfg.tool.tip_platform_mm, dtype=float)
    return [float(v) for v in tip] + [math.degrees(float(v)) for v in X[3:6]]


def _direction(blk, at_end: bool):
    """Unit xyz direction (3 floats) of a move at its start or end (arcs: tangent from centre and normal), or
    None.  Plain floats: the splitter looks at every block."""
    s, e = blk.start, blk.end
    if blk.kind == B.ARC and blk.center is not None and blk.normal is not None:
        p, c = _floats(e if at_end else s), _floats(blk.center)
        px, py, pz = p[0] - c[0], p[1] - c[1], p[2] - c[2]
        nx, ny, nz = _floats(blk.normal)[:3]
        sg = -1.0 if blk.clockwise else 1.0
        dx, dy, dz = sg * (ny * pz - nz * py), sg * (nz * px - nx * pz), sg * (nx * py - ny * px)
    else:
        (sx, sy, sz), (ex, ey, ez) = _floats(s)[:3], _floats(e)[:3]
        dx, dy, dz = ex - sx, ey - sy, ez - sz
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    return (dx / n, dy / n, dz / n) if n > 1e-9 else None


def turn_cos(a, b) -> float:
    """Cosine of the turn from move ``a``'s end to move ``b``'s start (1 where either has no direction)."""
    da, db = _direction(a, True), _direction(b, False)
    return 1.0 if da is None or db is None else da[0] * db[0] + da[1] * db[1] + da[2] * db[2]


def rest_after(blk, nxt) -> bool:
    """Whether the planner brings the motion to rest between ``blk`` and the next motion block ``nxt``
    (None: not known yet)."""
    if blk.kind in P.STOP_EVENTS:
        return True
    if blk.kind not in B.MOTION_KINDS or nxt is None:
        return False
    if blk.exact_stop or float(blk.tool_length_mm or 0.0) != float(nxt.tool_length_mm or 0.0):
        return True
    c = turn_cos(blk, nxt)
    if c < REVERSAL_COS:
        return True
    tol = [b.blend_tolerance_mm for b in (blk, nxt)]
    return any(t is not None and t <= 0 for t in tol) and c < 1.0 - 1e-12


class _Splitter:
    """Cuts a block stream into windows (lists of blocks) at rest points."""

    def __init__(self, cfg, window_blocks: int, window_s: float, first_blocks: int = 0):
        """``first_blocks`` > 0: the first window closes after that many motion blocks, each next one after
        twice as many, up to ``window_blocks`` (a quick first window: motion starts sooner)."""
        pc = cfg.planner
        self.wb = int(window_blocks)
        self.grow = int(first_blocks) if 0 < int(first_blocks) < self.wb else self.wb
        self.ws = float(window_s)
        self.rapid = pc.rapid_feed_mm_min / 60.0
        self.feed = pc.default_feed_mm_min / 60.0

    def windows(self, blocks):
        """Yields (blocks, forced_stop, last, nominal seconds of each block); a window is yielded once a
        block after it arrived (or the stream ended), so that ``last`` is known."""
        buf: list = []
        sec: list = []              # nominal seconds of each block in buf
        rests: list = []            # indices i in buf after which the motion rests
        nmot = 0
        secs = 0.0
        prev_mot = None             # index of the last motion block in buf
        pending = None
        for blk in blocks:
            if pending is not None:
                yield pending[0], pending[1], False, pending[2]
                pending = None
            if blk.kind in B.MOTION_KINDS:
                if prev_mot is not None and rest_after(buf[prev_mot], blk):
                    rests.append(prev_mot)
                prev_mot = len(buf)
                nmot += 1
            elif rest_after(blk, None):
                rests.append(len(buf))
            buf.append(blk)
            sec.append(_seconds(blk, self.rapid, self.feed))
            secs += sec[-1]
            if blk.kind == B.END:
                break
            if nmot >= self.grow or secs >= self.ws:
                self.grow = min(self.wb, 2 * self.grow)
                cut, forced = self._cut(buf, rests)
                pending = (buf[:cut + 1], forced, sec[:cut + 1])
                buf, sec = buf[cut + 1:], sec[cut + 1:]
                rests = [i - cut - 1 for i in rests if i > cut]
                nmot = sum(1 for b in buf if b.kind in B.MOTION_KINDS)
                secs = sum(sec)
                mot = [i for i, b in enumerate(buf) if b.kind in B.MOTION_KINDS]
                prev_mot = mot[-1] if mot else None
        if pending is not None:
            yield pending[0], pending[1], not buf, pending[2]
        if buf or pending is None:
            yield buf, False, True, sec

    def _cut(self, buf: list, rests: list) -> tuple[int, bool]:
        """Index of the last block of the window, and whether the window forces a stop there."""
        mot = [i for i, b in enumerate(buf) if b.kind in B.MOTION_KINDS]
        lo = mot[min(len(mot) - 1, int(MIN_SHARE * len(mot)))] if mot else 0
        ok = [i for i in rests if i >= lo and i < len(buf) - 1]
        if ok:
            return ok[-1], False
        # no rest point: the sharpest corner between motion blocks in the buffer's second half
        half = [i for i in mot if i >= lo]
        best, best_c = half[0] if half else len(buf) - 2, 2.0
        for a, b in zip(half[:-1], half[1:]):
            c = turn_cos(buf[a], buf[b])
            if c < best_c:
                best, best_c = a, c
        return max(0, min(best, len(buf) - 2)), True


def plan_windows(blocks, cfg, hexapod=None, period_s: float | None = None, start_pose=None,
                 window_blocks: int | None = None, window_s: float | None = None, first_blocks: int = 0):
    """Plan the blocks (any iterable) window by window; yields :class:`Window` s (see the module docstring).
    ``first_blocks``: a short first window, the next ones twice as long up to ``window_blocks``.

    Each window's plan starts at rest where the previous one ended; errors (GcodeError from the
    iterator, PlanError from a window) are raised when the window that holds them is reached, after
    every window before it was yielded.
    """
    from ..kinematics import Hexapod
    hx = hexapod if hexapod is not None else Hexapod(cfg)
    pc = cfg.planner
    wb = int(window_blocks if window_blocks is not None else pc.window_blocks)
    ws = float(window_s if window_s is not None else pc.window_s)
    start = start_pose
    for i, (blks, forced, last, secs) in enumerate(_Splitter(cfg, wb, ws, first_blocks).windows(blocks)):
        plan = plan_program(blks, cfg, hexapod=hx, period_s=period_s, start_pose=start)
        lines = [int(b.line) for b in blks] or [0]
        sums = line_sums(lines, secs, plan.line_tab, plan.dt) if blks else ()
        yield Window(i, plan, last, min(lines), max(lines), len(blks), forced, float(sum(secs)), sums)
        start = tool_tip_pose_deg(cfg, plan.end_pose_platform)


def validate_windows(blocks, cfg, hexapod=None, start_rad=None):
    """Check the blocks window by window without planning their timing (:func:`~hexacnc.planner.grid.check_path`:
    strut lengths, joint angles, singularity, soft limits, continuity); yields after every window
    (blocks so far, nominal seconds so far, last line, platform pose at the end (mm, rad)) and raises
    the first error (GcodeError from the iterator, PlanError) with its line."""
    from ..kinematics import Hexapod
    from .grid import check_path
    hx = hexapod if hexapod is not None else Hexapod(cfg)
    sp = _Splitter(cfg, cfg.planner.window_blocks, cfg.planner.window_s)
    nb, est = 0, 0.0
    end = None if start_rad is None else np.asarray(start_rad, dtype=float)
    for blks, _forced, _last, secs in sp.windows(blocks):
        path, events = P.build_path(blks, cfg)
        if path.n:
            check_path(path, hx, cfg, events)
            end = path.platform(np.array([path.n - 1]), np.array([path.total]))[0]
        nb += len(blks)
        est += sum(secs)
        yield nb, est, int(max((b.line for b in blks), default=0)), end
