"""G5 cubic and G5.1 quadratic B-splines in the G17 plane (LinuxCNC's words and rules).

``G5 X Y I J P Q``: a cubic Bezier from the current point P0 through the
control points P1 = P0 + (I, J) and P2 = P3 + (P, Q) to P3 = (X, Y); a G5
following a G5 may leave out I and J: they are then minus the previous P and Q
(the curve continues tangentially).  ``G5.1 X Y I J``: a quadratic Bezier with
the control point P0 + (I, J) (a missing I or J is zero, not both).  Only X and
Y move; A/B/C and Z words, another plane and cutter compensation are refused
as by LinuxCNC.  G5.2/G5.3 NURBS stay unsupported.

The curve is emitted as straight feed moves whose chord error is at most
:data:`CHORD_TOL_MM` (uniform parameter steps, from the bound
``|B''|max / (8 n^2)``); in G93 the F time is shared by the segments in
proportion to their lengths.
"""
from __future__ import annotations

import math

from . import blocks as B
from .blocks import Block, frozen_pose
from .lexer import Line

#: largest distance between the programmed curve and its straight segments (mm)
CHORD_TOL_MM = 0.0005
#: most segments one spline may become
MAX_SEGMENTS = 20000


def bezier_points(ctrl: list[tuple[float, float]], tol: float = CHORD_TOL_MM) -> list[tuple[float, float]]:
    """Points of a quadratic or cubic Bezier (control points ``ctrl``) after the start, chord error <= tol."""
    deg = len(ctrl) - 1
    # second differences of the control polygon bound |B''| by deg (deg - 1) max |d2|
    d2 = [math.hypot(ctrl[i][0] - 2 * ctrl[i + 1][0] + ctrl[i + 2][0],
                     ctrl[i][1] - 2 * ctrl[i + 1][1] + ctrl[i + 2][1]) for i in range(deg - 1)]
    bound = deg * (deg - 1) * max(d2)
    n = max(1, min(MAX_SEGMENTS, math.ceil(math.sqrt(bound / (8.0 * tol))) if bound > 0 else 1))
    out = []
    for k in range(1, n + 1):
        t = k / n
        s = 1.0 - t
        if deg == 2:
            w = (s * s, 2 * s * t, t * t)
        else:
            w = (s * s * s, 3 * s * s * t, 3 * s * t * t, t * t * t)
        out.append((sum(wi * c[0] for wi, c in zip(w, ctrl)), sum(wi * c[1] for wi, c in zip(w, ctrl))))
    return out


class SplineMixin:
    """G5 / G5.1 of :class:`~hexacnc.gcode.interp.Interpreter` (uses its state)."""

    def _spline(self, ln: Line, vals: dict, motion: int) -> None:
        name = "G5" if motion == 50 else "G5.1"
        if self.plane != 170:
            raise ln.error(f"{name} splines are defined in the G17 plane only", f"g{motion}", "unsupported")
        if self.comp_side:
            raise ln.error(f"{name} cannot be used with cutter radius compensation on", f"g{motion}", "comp")
        for i, letter in ln.axes:
            if i > 1:
                raise ln.error(f"{name} moves X and Y only ({letter.upper()} word)", letter, "word")
        u = self.u
        start = self._prog_pose()
        end = list(start)
        for i, letter in ln.axes:
            end[i] = vals[letter] * u if self.absolute else start[i] + vals[letter] * u
        p0, p3 = (start[0], start[1]), (end[0], end[1])
        if motion == 51:
            if not ("i" in vals or "j" in vals) or (vals.get("i", 0.0) == 0.0 and vals.get("j", 0.0) == 0.0):
                raise ln.error("G5.1 needs an I or J control point offset (not both zero)", "g51", "word")
            ctrl = [p0, (p0[0] + vals.get("i", 0.0) * u, p0[1] + vals.get("j", 0.0) * u), p3]
        else:
            if "p" not in vals or "q" not in vals:
                raise ln.error("G5 needs both P and Q (second control point from the end)", "g50", "word")
            if ("i" in vals) != ("j" in vals):
                raise ln.error("G5 needs both I and J, or neither", "i" if "i" in vals else "j", "word")
            if "i" in vals:
                di, dj = vals["i"] * u, vals["j"] * u
            elif self.g5_pq is not None:
                di, dj = -self.g5_pq[0], -self.g5_pq[1]
            else:
                raise ln.error("the first G5 of a series needs I and J", "g50", "word")
            dp, dq = vals["p"] * u, vals["q"] * u
            ctrl = [p0, (p0[0] + di, p0[1] + dj), (p3[0] + dp, p3[1] + dq), p3]
            self.g5_pq = (dp, dq)
        if p0 == p3 and all(c == p0 for c in ctrl):
            return
        self._spline_out(ln, vals, motion, bezier_points(ctrl), start)

    def _spline_out(self, ln: Line, vals: dict, motion: int, pts, start) -> None:
        fm, inv = self._feed_of(ln, vals, motion)
        prev = (start[0], start[1])
        total = sum(math.dist(a, b) for a, b in zip([prev] + pts[:-1], pts)) or 1.0
        pose = list(start)
        for x, y in pts:
            pose[0], pose[1] = x, y
            end = self._to_machine(pose)
            seg = math.dist(prev, (x, y))
            prev = (x, y)
            if end == self.pos:
                continue
            e = frozen_pose(end)
            self._emit(Block(B.LINE, ln.num, self._start_arr(), e, fm, None if inv is None else inv * seg / total,
                             None, None, 0, False, self.exact_stop, self.blend, self.tool_len, 0.0, 0.0, "off",
                             self.tool))
            self.pos = end
            self.pos_arr = e
