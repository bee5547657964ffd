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
from .blocks import Block
from .lexer import Line

_LINEAR_TOL_MM = {25.4: 0.002 * 25.4, 1.0: 0.02}   #: arc end-radius tolerance (LinuxCNC-like)
_R_TOL_MM = {25.4: 0.00005 * 25.4, 1.0: 0.0005}    #: R-arc chord tolerance
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
        self.off = [P[base + i] + self.g92[i] for i in range(6)]

    def _set_tool_length(self, new_len: float) -> None:
        d = new_len - self.tool_len
        if d != 0.0:
            r = rotation_elements(*(math.radians(v) for v in self.pos[3:6]))
            x, y, z = self.tool_axis
            for i in range(3):
                self.pos[i] += d * (r[3 * i] * x + r[3 * i + 1] * y + r[3 * i + 2] * z)
            self.pos_arr = None
        self.tool_len = new_len

    def _g10(self, ln: Line, vals: dict) -> None:
        if "l" not in vals:
            raise ln.error("G10 needs an L word (L2 or L20)", "g100", "word")
        lv = vals["l"]
        if lv not in (2.0, 20.0):
            raise ln.error(f"G10 L{lv:g} is not supported (only L2 and L20)", "l", "unsupported")
        if "p" not in vals:
            raise ln.error("G10 L2/L20 needs a P word (coordinate system 0..9)", "g100", "word")
        p = vals["p"]
        if p != int(p) or not 0 <= p <= 9:
            raise ln.error(f"G10 P{p:g}: coordinate system must be 0..9", "p", "value")
        if "r" in vals:
            raise ln.error("G10 R (coordinate system rotation) is not supported", "r", "unsupported")
        k = int(p) or self.cs
        base = 5201 + 20 * k
        u = self.u
        for i, letter in ln.axes:
            v = vals[letter] * (u if i < 3 else 1.0)
            if lv == 2.0:
                self.P[base + i] = v
            else:  # L20: the current point gets coordinate v in that system
                self.P[base + i] = self.pos[i] - self.g92[i] - v
        if k == self.cs:
            self._refresh_offsets()

    def _g92(self, ln: Line, vals: dict, g: int) -> None:
        if g == 920:
            if not ln.axes:
                raise ln.error("G92 needs at least one axis word", "g920", "word")
            base = 5201 + 20 * self.cs
            u = self.u
            for i, letter in ln.axes:
                v = vals[letter] * (u if i < 3 else 1.0)
                self.g92[i] = self.pos[i] - self.P[base + i] - v
        elif g in (921, 922):
            self.g92 = [0.0] * 6
        else:  # G92.3: restore from parameters
            self.g92 = [self.P[5211 + i] for i in range(6)]
        if g != 922:
            for i in range(6):
                self.P[5211 + i] = self.g92[i]
            self.P[5210] = 1.0 if any(self.g92) else 0.0
        self._refresh_offsets()

    # -- motion ---------------------------------------------------------------------------
    def _g28(self, ln: Line, vals: dict, base: int) -> None:
        """G28/G30: rapid through the point of the axis words (if any) to the stored position.

        With axis words only those axes go to the stored position (LinuxCNC).
        """
        if ln.axes:
            self._rapid_to(ln, self._target(ln, vals, False))
            end = list(self.pos)
            for i, _letter in ln.axes:
                end[i] = self.P[base + i]
        else:
            end = self.P[base:base + 6]
        self._rapid_to(ln, end)

    def _rapid_to(self, ln: Line, end: list[float]) -> None:
        if end == self.pos:
            return
        e = np.array(end)
        e.flags.writeable = False
        self.blocks.append(Block(_RAPID, ln.num, self._start_arr(), e, None, None, None, None, 0, False,
                                 self.exact_stop, self.blend, self.tool_len, 0.0, 0.0, "off", self.tool))
        self.pos = list(end)
        self.pos_arr = e

    def _target(self, ln: Line, vals: dict, g53: bool) -> list[float]:
        pos = self.pos
        end = list(pos)
        u = self.u
        if g53:
            for i, letter in ln.axes:
                end[i] = vals[letter] * u if i < 3 else vals[letter]
        elif self.absolute:
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
            a = np.array(self.pos)
            a.flags.writeable = False
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
        end = self._target(ln, vals, g53)
        pos = self.pos
        if end == pos:
            return
        start = self._start_arr()
        e = np.array(end)
        e.flags.writeable = False
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
        end = self._target(ln, vals, False)
        start = self.pos
        u = self.u
        fm, inv = self._feed_of(ln, vals, motion)
        turns = 0
        if "p" in vals:
            pv = vals["p"]
            if pv != int(pv) or not 1 <= pv <= 10000:
                raise ln.error(f"arc P{pv:g} (number of turns) must be an integer 1..10000", "p", "arc")
            turns = int(pv) - 1
        cw = motion == 20
        sp, sq, ep, eq = start[p], start[q], end[p], end[q]
        if "r" in vals:
            if cp in vals or cq in vals:
                raise ln.error("arc with both R and I/J/K words", "r", "arc")
            r = vals["r"] * u
            dp, dq = ep - sp, eq - sq
            d = math.hypot(dp, dq)
            if d < 1e-9:
                raise ln.error("R-format arc with start equal to end (use I/J/K for full circles)", "r", "arc")
            half = 0.5 * d
            ar = abs(r)
            if ar < _EPS:
                raise ln.error("arc radius R0", "r", "arc")
            if half > ar:
                if half - ar > _R_TOL_MM[u]:
                    raise ln.error(f"arc radius {ar / u:g} too small to reach the end point "
                                   f"(half chord {half / u:g})", "r", "arc")
                h = 0.0
            else:
                h = math.sqrt(ar * ar - half * half)
            # left normal of the chord; CCW short arc has its centre on the left
            nlp, nlq = -dq / d, dp / d
            side = (1.0 if not cw else -1.0) * (1.0 if r > 0 else -1.0)
            c_p = sp + 0.5 * dp + side * h * nlp
            c_q = sq + 0.5 * dq + side * h * nlq
        else:
            if cp not in vals and cq not in vals:
                raise ln.error(f"arc in the G{plane // 10} plane needs {cp.upper()}/{cq.upper()} "
                               "words or R", f"g{motion}", "arc")
            if self.arc_absolute:
                c_p = vals.get(cp, 0.0) * u + self.off[p]
                c_q = vals.get(cq, 0.0) * u + self.off[q]
            else:
                c_p = sp + vals.get(cp, 0.0) * u
                c_q = sq + vals.get(cq, 0.0) * u
            r0 = math.hypot(sp - c_p, sq - c_q)
            r1 = math.hypot(ep - c_p, eq - c_q)
            if r0 < 1e-9:
                raise ln.error("arc with zero radius (centre at the start point)",
                               cp if cp in vals else cq, "arc")
            err = abs(r1 - r0)
            if err > _LINEAR_TOL_MM[u] and err > 0.001 * r0:
                raise ln.error(f"radius to the arc end differs from radius to the start by {err / u:.6g} "
                               f"({r0 / u:.6g} vs {r1 / u:.6g})", cp if cp in vals else cq, "arc")
        center = [0.0, 0.0, 0.0]
        center[p], center[q], center[w] = c_p, c_q, start[w]
        normal = [0.0, 0.0, 0.0]
        normal[w] = 1.0
        e = np.array(end)
        e.flags.writeable = False
        b = Block(_ARC, ln.num, self._start_arr(), e, fm, inv, np.array(center), np.array(normal),
                  turns, cw, self.exact_stop, self.blend, self.tool_len, 0.0, 0.0, "off", self.tool)
        self.blocks.append(b)
        self.pos = end
        self.pos_arr = e
