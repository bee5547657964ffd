"""Tools, tool lengths and coordinate-system data: T, M61, G43/G49, G10 L1/L2/L10/L11/L20, G92.

The tool table holds :class:`~hexacnc.gcode.state.ToolEntry` (mm).  The tool
length (``z_offset_mm``) acts along the platform tool axis; with the canonical
axis (0, 0, -1) it is LinuxCNC's Z tool offset exactly.
"""
from __future__ import annotations

import math

from .lexer import Line
from .state import ToolEntry


class ToolingMixin:
    """Tool and offset commands of :class:`~hexacnc.gcode.interp.Interpreter` (uses its state)."""

    def _entry(self, t: int) -> ToolEntry | None:
        return None if self.tools is None else self.tools.get(t)

    def _select_tool(self, ln: Line, t: float) -> None:
        if t < 0 or t != int(t):
            raise ln.error(f"tool number T{t:g} must be a non-negative integer", "t", "tool")
        t = int(t)
        if self.tools_given and t != 0 and t not in self.tools:
            raise ln.error(f"tool T{t} is not in the tool table", "t", "tool")
        self.selected = t

    def _m61(self, ln: Line, vals: dict) -> None:
        q = vals.get("q")
        if q is None:
            raise ln.error("M61 needs a Q word (tool number)", "m61", "word")
        if q < 0 or abs(q - round(q)) > 1e-4:
            raise ln.error(f"M61 Q{q:g}: tool number must be a non-negative integer", "q", "tool")
        t = int(round(q))
        if self.tools_given and t != 0 and t not in self.tools:
            raise ln.error(f"M61 Q{t}: tool {t} is not in the tool table", "q", "tool")
        self.tool = self.selected = t

    def _tool_param(self, key: int) -> float:
        """#5401..#5413: the loaded tool's table entry (program units)."""
        e = self._entry(self.tool)
        if e is None:
            return 0.0
        u = self.u
        return {5401: e.x_offset_mm / u, 5402: e.y_offset_mm / u, 5403: e.z_offset_mm / u,
                5410: e.diameter_mm / u, 5411: e.front_angle_deg, 5412: e.back_angle_deg,
                5413: float(e.orientation)}.get(key, 0.0)

    def _g43(self, ln: Line, vals: dict) -> None:
        h = self.tool
        if "h" in vals:
            hv = vals["h"]
            if hv < 0 or hv != int(hv):
                raise ln.error(f"H{hv:g} must be a non-negative integer", "h", "tool")
            h = int(hv) or self.tool          # LinuxCNC: H0 is the tool in the spindle
        e = self._entry(h)
        if h == 0 and e is None:
            self._set_tool_length(0.0)
            return
        if e is None:
            raise ln.error(f"G43 H{h}: tool {h} has no length in the tool table",
                           "h" if "h" in vals else "g430", "tool")
        if e.x_offset_mm or e.y_offset_mm:
            raise ln.error(f"G43 with tool {h}'s X/Y offset ({e.x_offset_mm:g}, {e.y_offset_mm:g} mm) is not "
                           "supported: a hexapod tool offset acts along the tool axis only",
                           "h" if "h" in vals else "g430", "unsupported")
        self._set_tool_length(e.z_offset_mm)

    def _g43_dynamic(self, ln: Line, vals: dict, direct: bool) -> None:
        """G43.1 Z (tool length given on the line) / G43.2 Z (added to the current one)."""
        code = "G43.1" if direct else "G43.2"
        if any(i != 2 for i, _l in ln.axes):
            bad = next(letter for i, letter in ln.axes if i != 2)
            raise ln.error(f"{code} with a {bad.upper()} offset is not supported: a hexapod tool offset acts "
                           "along the tool axis only", bad, "unsupported")
        if "h" in vals:
            raise ln.error(f"{code} with H is not supported", "h", "unsupported")
        z = vals["z"] * self.u if "z" in vals else 0.0
        self._set_tool_length(z if direct else self.tool_len + z)

    # -- G10 --------------------------------------------------------------------------
    def _g10(self, ln: Line, vals: dict) -> None:
        if "l" not in vals:
            raise ln.error("G10 needs an L word (L1, L2, L10, L11 or L20)", "g100", "word")
        lv = vals["l"]
        if lv not in (1.0, 2.0, 10.0, 11.0, 20.0):
            raise ln.error(f"G10 L{lv:g} is not supported (L1, L2, L10, L11, L20)", "l", "unsupported")
        if "p" not in vals:
            raise ln.error(f"G10 L{lv:g} needs a P word", "g100", "word")
        if lv in (2.0, 20.0):
            self._g10_coord(ln, vals, int(lv))
        else:
            self._g10_tool(ln, vals, int(lv))

    def _g10_coord(self, ln: Line, vals: dict, lv: int) -> None:
        p = vals["p"]
        if p != int(p) or not 0 <= p <= 9:
            raise ln.error(f"G10 P{p:g}: coordinate system must be 0..9", "p", "value")
        k = int(p) or self.cs
        base = 5201 + 20 * k
        u = self.u
        P = self.P
        if not ln.axes and "r" not in vals:
            raise ln.error(f"G10 L{lv} needs an axis word or R", "g100", "word")
        rot = vals.get("r", P[base + 9])
        if lv == 2:
            for i, letter in ln.axes:
                P[base + i] = vals[letter] * (u if i < 3 else 1.0)
            P[base + 9] = rot
        else:   # L20: the current point gets the given coordinates in that system
            m, g = self.pos, self.g92
            c0, s0 = math.cos(math.radians(P[base + 9])), math.sin(math.radians(P[base + 9]))
            dx, dy = m[0] - P[base], m[1] - P[base + 1]
            px, py = c0 * dx + s0 * dy - g[0], -s0 * dx + c0 * dy - g[1]
            given = dict((i, vals[letter] * (u if i < 3 else 1.0)) for i, letter in ln.axes)
            px, py = given.get(0, px), given.get(1, py)
            c1, s1 = math.cos(math.radians(rot)), math.sin(math.radians(rot))
            P[base + 9] = rot
            if 0 in given or 1 in given or "r" in vals:
                x, y = px + g[0], py + g[1]
                P[base] = m[0] - (c1 * x - s1 * y)
                P[base + 1] = m[1] - (s1 * x + c1 * y)
            for i, v in given.items():
                if i >= 2:
                    P[base + i] = m[i] - g[i] - v
        if k == self.cs:
            self._refresh_offsets()

    def _g10_tool(self, ln: Line, vals: dict, lv: int) -> None:
        p = vals["p"]
        if p != int(p) or p < 0:
            raise ln.error(f"G10 L{lv} P{p:g}: tool number must be a non-negative integer", "p", "tool")
        t = int(p)
        if self.tools_given and t not in self.tools and t != 0:
            raise ln.error(f"G10 L{lv} P{t}: tool {t} is not in the tool table", "p", "tool")
        if not (ln.axes or any(x in vals for x in "rijq")):
            raise ln.error(f"G10 L{lv} needs an axis word or R/I/J/Q", "g100", "word")
        if any(i >= 3 for i, _l in ln.axes):
            raise ln.error(f"G10 L{lv}: A/B/C tool offsets are not supported", ln.axes[-1][1], "unsupported")
        e = self.tools.setdefault(t, ToolEntry(tool=t, pocket=t))
        u = self.u
        given = {i: vals[letter] * u for i, letter in ln.axes}
        if lv == 1:
            cur = given
        else:
            cur = self._g10_l10(ln, given, lv)
        if 0 in cur:
            e.x_offset_mm = cur[0]
        if 1 in cur:
            e.y_offset_mm = cur[1]
        if 2 in cur:
            e.z_offset_mm = cur[2]
        if "r" in vals:
            e.diameter_mm = 2.0 * vals["r"] * u
        if "i" in vals:
            e.front_angle_deg = vals["i"]
        if "j" in vals:
            e.back_angle_deg = vals["j"]
        if "q" in vals:
            q = vals["q"]
            if q != int(q) or not 0 <= q <= 9:
                raise ln.error(f"G10 Q{q:g}: tool orientation must be an integer 0..9", "q", "tool")
            e.orientation = int(q)

    def _g10_l10(self, ln: Line, given: dict, lv: int) -> dict:
        """L10/L11: offsets that make the current point have the given coordinates (L11: in G59.3)."""
        k = 9 if lv == 11 else self.cs
        base = 5201 + 20 * k
        P = self.P
        ref = self._ref_point(self.pos)
        g = [0.0] * 6 if lv == 11 else self.g92
        th = math.radians(P[base + 9])
        c, s = math.cos(th), math.sin(th)
        dx, dy = ref[0] - P[base], ref[1] - P[base + 1]
        prog = [c * dx + s * dy - g[0], -s * dx + c * dy - g[1], ref[2] - P[base + 2] - g[2]]
        axis = self._tool_vec_unit(self.pos[3:6])
        out = {}
        for i, v in given.items():
            if i == 2:
                if abs(axis[2]) < 1e-9:
                    raise ln.error(f"G10 L{lv} Z: the tool axis is horizontal here, a length cannot set Z",
                                   "z", "tool")
                out[2] = (v - prog[2]) / axis[2]
            else:
                out[i] = prog[i] - v
        return out

    def _tool_vec_unit(self, abc) -> list[float]:
        saved = self.tool_len
        self.tool_len = 1.0
        try:
            return self._tool_vec(abc)
        finally:
            self.tool_len = saved

    # -- G92 ----------------------------------------------------------------------------
    def _g92(self, ln: Line, vals: dict, g: int) -> None:
        if g == 520:          # G52: the G92 offsets are the given values (LinuxCNC shares them)
            if not ln.axes:
                raise ln.error("G52 needs at least one axis word", "g520", "word")
            for i, letter in ln.axes:
                self.g92[i] = vals[letter] * (self.u if i < 3 else 1.0)
        elif g == 920:
            if not ln.axes:
                raise ln.error("G92 needs at least one axis word", "g920", "word")
            u = self.u
            saved = list(self.g92)
            self.g92 = [0.0] * 6
            self._refresh_offsets()
            prog = self._prog_pose()          # current point in the system without G92
            self.g92 = saved
            for i, letter in ln.axes:
                self.g92[i] = prog[i] - vals[letter] * (u if i < 3 else 1.0)
        elif g in (921, 922):
            self.g92 = [0.0] * 6
        else:  # G92.3: restore from parameters
            self.g92 = [self.P[5211 + i] for i in range(6)]
        if g != 922:
            for i in range(6):
                self.P[5211 + i] = self.g92[i]
        self.P[5210] = 1.0 if g in (520, 920, 923) else 0.0   # LinuxCNC: applied flag
        self._refresh_offsets()
