"""Positions, offsets, tool length and motion blocks of the interpreter.

Machine (base-frame) tool-tip poses ``[x, y, z, a, b, c]`` in mm and degrees;
program coordinates add the active work offset and G92 offset per axis (G53:
none).  Lines and arcs become :class:`~hexacnc.gcode.blocks.Block` objects.
"""
from __future__ import annotations

import math
from dataclasses import fields

import numpy as np

from ..pose import rotation_elements
from . import blocks as B
from .blocks import Block, frozen_pose
from .lexer import Line

#: LinuxCNC CENTER_ARC_RADIUS_TOLERANCE (inch, mm) in mm
_SPIRAL_TOL_MM = {25.4: 0.002 * math.sqrt(2.0) * 25.4, 1.0: 0.02 * math.sqrt(2.0)}
#: LinuxCNC RADIUS_TOLERANCE: R arcs may fall short of the half chord by this; smaller radii are zero
_R_TOL_MM = {25.4: 0.00005 * 25.4, 1.0: 0.00005 * 25.4}
_EPS = 1e-12
_RAPID, _LINE, _ARC = B.RAPID, B.LINE, B.ARC
# motion blocks are built with positional arguments (fast): the field order is part of the contract
_POSITIONAL = ("kind", "line", "start", "end", "feed_mm_s", "inverse_time_s", "center", "normal", "turns",
               "clockwise", "exact_stop", "blend_tolerance_mm", "tool_length_mm", "seconds", "spindle_rpm",
               "coolant", "tool")
if tuple(f.name for f in fields(Block))[:len(_POSITIONAL)] != _POSITIONAL:  # pragma: no cover
    raise ImportError("hexacnc.gcode.blocks.Block fields were reordered; fix the positional Block(...) calls")


class MotionMixin:
    """Offsets, tool length and moves of :class:`~hexacnc.gcode.interp.Interpreter` (uses its state)."""

    # -- offsets and tool ---------------------------------------------------------------
    def _refresh_offsets(self) -> None:
        base = 5201 + 20 * self.cs
        P = self.P
        self.o5x = [P[base + i] for i in range(6)]
        self.off = [self.o5x[i] + self.g92[i] for i in range(6)]
        self.rot_deg = P[base + 9]
        self.slow = self.rot_deg != 0.0 or bool(self.comp_side) or self.comp_arc_not_allowed or self.diameter
        r = math.radians(self.rot_deg)
        self.rot_cs = (math.cos(r), math.sin(r))

    def _to_machine(self, prog: list[float]) -> list[float]:
        """Program coordinates (mm, deg, without offsets) -> machine coordinates."""
        off = self.off
        out = [prog[i] + off[i] for i in range(len(prog))]
        if self.rot_deg != 0.0:
            c, s = self.rot_cs
            x, y = prog[0] + self.g92[0], prog[1] + self.g92[1]
            out[0] = self.o5x[0] + c * x - s * y
            out[1] = self.o5x[1] + s * x + c * y
        return out

    def _unrotate(self, pos) -> tuple[float, float]:
        """Program X, Y (mm) of the machine point ``pos`` under the G10 L2 R rotation."""
        c, s = self.rot_cs
        dx, dy = pos[0] - self.o5x[0], pos[1] - self.o5x[1]
        return c * dx + s * dy - self.g92[0], -s * dx + c * dy - self.g92[1]

    def _prog_pose(self) -> list[float]:
        """Current tool-tip pose in program coordinates (mm, deg)."""
        pos, off = self.pos, self.off
        out = [pos[i] - off[i] for i in range(6)]
        if self.rot_deg != 0.0:
            out[0], out[1] = self._unrotate(pos)
        return out

    def _tool_vec(self, abc) -> list[float]:
        """Tool tip minus tool reference point (mm, machine frame) at orientation ``abc`` (deg)."""
        L = self.tool_len
        if L == 0.0:
            return [0.0, 0.0, 0.0]
        r = rotation_elements(*(math.radians(v) for v in abc))
        x, y, z = self.tool_axis
        return [L * (r[3 * i] * x + r[3 * i + 1] * y + r[3 * i + 2] * z) for i in range(3)]

    def _ref_point(self, pose) -> list[float]:
        """Machine pose of the tool reference point (the controlled point of G53/G28/G30)."""
        v = self._tool_vec(pose[3:6])
        return [pose[0] - v[0], pose[1] - v[1], pose[2] - v[2]] + list(pose[3:6])

    def _set_tool_length(self, new_len: float) -> None:
        d = new_len - self.tool_len
        if d != 0.0:
            old = self._tool_vec(self.pos[3:6])
            self.tool_len = new_len
            new = self._tool_vec(self.pos[3:6])
            for i in range(3):
                self.pos[i] += new[i] - old[i]
            self.pos_arr = None
        self.tool_len = new_len

    # -- motion ---------------------------------------------------------------------------
    def _g28(self, ln: Line, vals: dict, base: int) -> None:
        """G28/G30: rapid through the point of the axis words (if any) to the stored position.

        With axis words only those axes go to the stored position (LinuxCNC).
        """
        if ln.axes:
            self._rapid_to(ln, self._target(ln, vals, False))
            ref = self._ref_point(self.pos)
            for i, _letter in ln.axes:
                ref[i] = self.P[base + i]
        else:
            ref = self.P[base:base + 6]
        self._rapid_to(ln, self._tip_of(ref))

    def _rapid_to(self, ln: Line, end: list[float]) -> None:
        if end == self.pos:
            return
        e = frozen_pose(end)
        self.blocks.append(Block(_RAPID, ln.num, self._start_arr(), e, None, None, None, None, 0, False,
                                 self.exact_stop, self.blend, self.tool_len, 0.0, 0.0, "off", self.tool))
        self.pos = list(end)
        self.pos_arr = e

    def _line_to(self, ln: Line, end: list[float]) -> None:
        """Feed move (current G94 feed) to the machine pose ``end``."""
        if end == self.pos:
            return
        fm, inv = self._feed_of(ln, {}, 10)
        e = frozen_pose(end)
        self.blocks.append(Block(_LINE, ln.num, self._start_arr(), e, fm, inv, None, None, 0, False,
                                 self.exact_stop, self.blend, self.tool_len, 0.0, 0.0, "off", self.tool))
        self.pos = list(end)
        self.pos_arr = e

    def _tip_of(self, ref) -> list[float]:
        """Tool-tip machine pose whose tool reference point is ``ref``."""
        v = self._tool_vec(ref[3:6])
        return [ref[0] + v[0], ref[1] + v[1], ref[2] + v[2]] + list(ref[3:6])

    def _target(self, ln: Line, vals: dict, g53: bool) -> list[float]:
        pos = self.pos
        end = list(pos)
        u = self.u
        if g53:    # machine coordinates of the controlled point (tool reference point)
            ref = self._ref_point(pos)
            for i, letter in ln.axes:
                ref[i] = vals[letter] * u if i < 3 else vals[letter]
            return self._tip_of(ref)
        if self.rot_deg != 0.0:
            prog = self._prog_pose()
            for i, letter in ln.axes:
                v = vals[letter] * u if i < 3 else vals[letter]
                prog[i] = v if self.absolute else prog[i] + v
            return self._to_machine(prog)
        if self.absolute:
            off = self.off
            for i, letter in ln.axes:
                end[i] = (vals[letter] * u if i < 3 else vals[letter]) + off[i]
        else:
            for i, letter in ln.axes:
                end[i] = pos[i] + (vals[letter] * u if i < 3 else vals[letter])
        return end

    def _start_arr(self) -> np.ndarray:
        a = self.pos_arr
        if a is None:
            a = frozen_pose(self.pos)
            self.pos_arr = a
        return a

    def _feed_of(self, ln: Line, vals: dict, motion: int):
        """-> (feed_mm_s, inverse_time_s, feed_deg_s) for a feed move."""
        if self.inverse_time:
            f = vals.get("f")
            if f is None:
                raise ln.error(f"G93 inverse-time G{motion // 10} move needs an F word on its line",
                               f"g{motion}",
                               "feed")
            if f <= 0.0:
                raise ln.error(f"inverse-time F{f:g} must be positive", "f", "feed")
            return None, 60.0 / f
        f = self.feed
        if f <= 0.0:
            raise ln.error(f"G{motion // 10} with zero feed rate (no F word yet)",
                           f"g{motion}",
                           "feed")
        return f * self.u / 60.0, None

    def _move(self, ln: Line, vals: dict, motion: int, g53: bool) -> None:
        if self.comp_side:
            self._comp_straight(ln, vals, motion)
            return
        if self.comp_arc_not_allowed:
            self.comp_arc_not_allowed = False
            self._refresh_offsets()
        end = self._target(ln, vals, g53)
        pos = self.pos
        if end == pos:
            return
        start = self._start_arr()
        e = frozen_pose(end)
        if motion == 0:
            b = Block(_RAPID, ln.num, start, e, None, None, None, None, 0, False, self.exact_stop, self.blend,
                      self.tool_len, 0.0, 0.0, "off", self.tool)
        else:
            fm, inv = self._feed_of(ln, vals, motion)
            b = Block(_LINE, ln.num, start, e, fm, inv, None, None, 0, False, self.exact_stop, self.blend,
                      self.tool_len, 0.0, 0.0, "off", self.tool)
            if fm is not None and end[0] == pos[0] and end[1] == pos[1] and end[2] == pos[2]:
                b.feed_deg_s = b.feed_mm_s = self.feed / 60.0  # rotary-only: F is deg/min
        self.blocks.append(b)
        self.pos = end
        self.pos_arr = e

    def _arc(self, ln: Line, vals: dict, motion: int) -> None:
        if self.comp_side:
            self._comp_arc(ln, vals, motion)
            return
        if self.comp_arc_not_allowed:
            raise ln.error("the move just after G40 must be straight, not an arc", f"g{motion}", "comp")
        plane = self.plane
        # plane axes (p, q) and normal axis w; CCW = positive rotation about +w
        if plane == 170:
            p, q, w, cp, cq, bad = 0, 1, 2, "i", "j", "k"
        elif plane == 180:
            p, q, w, cp, cq, bad = 2, 0, 1, "k", "i", "j"
        else:
            p, q, w, cp, cq, bad = 1, 2, 0, "j", "k", "i"
        if bad in vals:
            raise ln.error(f"{bad.upper()} word with an arc in the G{plane // 10} plane", bad, "word")
        start = self._prog_pose()
        end = list(start)
        u = self.u
        for i, letter in ln.axes:
            v = vals[letter] * u if i < 3 else vals[letter]
            end[i] = v if self.absolute else start[i] + v
        fm, inv = self._feed_of(ln, vals, motion)
        turns = 0
        if "p" in vals:
            pv = vals["p"]
            if abs(pv - round(pv)) > 1e-4 or not 1 <= round(pv) <= 10000:
                raise ln.error(f"arc P{pv:g} (number of turns) must be an integer 1..10000", "p", "arc")
            turns = int(round(pv)) - 1
        cw = motion == 20
        sp, sq, ep, eq = start[p], start[q], end[p], end[q]
        if "r" in vals:
            if cp in vals or cq in vals:
                raise ln.error("arc with both R and I/J/K words", "r", "arc")
            c_p, c_q = self._r_centre(ln, vals["r"] * u, sp, sq, ep, eq, cw)
        else:
            c_p, c_q = self._ijk_centre(ln, vals, cp, cq, sp, sq, ep, eq)
        center = [0.0] * 6
        center[p], center[q], center[w] = c_p, c_q, start[w]
        center = self._to_machine(center)[:3]
        normal = [0.0, 0.0, 0.0]
        normal[w] = 1.0
        if self.rot_deg != 0.0 and w != 2:
            c, s_ = self.rot_cs
            normal = [c * normal[0] - s_ * normal[1], s_ * normal[0] + c * normal[1], normal[2]]
        end_m = self._to_machine(end)
        if turns == 0 and end_m == self.pos and "r" in vals:
            raise ln.error("R-format arc with start equal to end (use I/J/K for full circles)", "r", "arc")
        e = frozen_pose(end_m)
        b = Block(_ARC, ln.num, self._start_arr(), e, fm, inv, np.array(center), np.array(normal),
                  turns, cw, self.exact_stop, self.blend, self.tool_len, 0.0, 0.0, "off", self.tool)
        self.blocks.append(b)
        self.pos = end_m
        self.pos_arr = e

    def _r_centre(self, ln: Line, r: float, sp, sq, ep, eq, cw: bool):
        """Centre of an R-format arc (LinuxCNC's rule: R may fall short of the half chord by
        0.00005 in / 0.00127 mm)."""
        if ep == sp and eq == sq:
            raise ln.error("R-format arc with start equal to end (use I/J/K for full circles)", "r", "arc")
        tol = _R_TOL_MM[self.u]
        dp, dq = ep - sp, eq - sq
        d = math.hypot(dp, dq)
        half = 0.5 * d
        ar = abs(r)
        if ar < _EPS or half - ar > tol:
            raise ln.error(f"arc radius {ar / self.u:g} too small to reach the end point "
                           f"(half chord {half / self.u:g})", "r", "arc")
        if half / ar > 1.0 - 1e-12:
            half = ar
        h = ar * math.cos(math.asin(half / ar))
        # left normal of the chord; CCW short arc has its centre on the left
        side = (1.0 if not cw else -1.0) * (1.0 if r > 0 else -1.0)
        return sp + 0.5 * dp + side * h * (-dq / d), sq + 0.5 * dq + side * h * (dp / d)

    def _ijk_centre(self, ln: Line, vals: dict, cp: str, cq: str, sp, sq, ep, eq):
        """Centre of an I/J/K arc with LinuxCNC's end-radius rule: refused when the radii differ
        by more than 100 x 0.02*sqrt(2) mm (0.002*sqrt(2) in), or by more than 0.1 % and that tolerance."""
        if cp not in vals and cq not in vals:
            raise ln.error(f"arc in the G{self.plane // 10} plane needs {cp.upper()}/{cq.upper()} "
                           "words or R", f"g{self.motion}", "arc")
        u = self.u
        if self.arc_absolute:
            for letter in (cp, cq):
                if letter not in vals:
                    raise ln.error(f"{letter.upper()} word missing in absolute centre arc (G90.1)",
                                   f"g{self.motion}", "arc")
            c_p, c_q = vals[cp] * u, vals[cq] * u
        else:
            c_p, c_q = sp + vals.get(cp, 0.0) * u, sq + vals.get(cq, 0.0) * u
        r0 = math.hypot(sp - c_p, sq - c_q)
        r1 = math.hypot(ep - c_p, eq - c_q)
        col = cp if cp in vals else cq
        if r0 < _R_TOL_MM[u] or r1 < _R_TOL_MM[u]:
            raise ln.error(f"zero-radius arc (radius {r0 / u:.4f} at the start, {r1 / u:.4f} at the end)",
                           col, "arc")
        err = abs(r1 - r0)
        tol = _SPIRAL_TOL_MM[u]
        if err > 100.0 * tol or (err / max(r0, r1) > 0.001 and err > tol):
            raise ln.error(f"radius to the arc end differs from radius to the start by {err / u:.6g} "
                           f"({r0 / u:.6g} vs {r1 / u:.6g})", col, "arc")
        return c_p, c_q
