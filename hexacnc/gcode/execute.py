"""One general line, in LinuxCNC's order of execution.

Comments, G93/G94, F, S, T, M62-M68, M6/M61, M3-M5, M70-M73, M7-M9, G4,
G17-G19, G20/G21, G40, G43/G49, G54.., G61/G64, G90/G91, G98/G99,
G10/G28/G30/G92, motion (incl. G53, canned cycles, probes), M0/M1/M2/M30.
"""
from __future__ import annotations

from . import blocks as B
from .blocks import Block
from .codes import CYCLES, G_GROUP, G_UNSUPPORTED, M_GROUP, M_UNSUPPORTED, PROBES
from .expr import LENGTH_PARAMETERS
from .lexer import Line

_AXIS_USERS = (100, 520, 920, 280, 300)


class ExecuteMixin:
    """:meth:`_execute` of :class:`~hexacnc.gcode.interp.Interpreter` (uses its state)."""

    def _codes(self, ln: Line, vals: dict):
        """G and M codes of the line (constant and computed), validated -> (gs, ms, groups, mgroups)."""
        gs, ms = ln.gs, ln.ms
        if ln.dyn and any(len(d) > 1 and d[0] in "gm" for d in ln.dyn):
            gs, ms = list(gs), list(ms)
            for d in ln.dyn:
                if d[0] in "gm" and d[1] == "@":
                    v = vals[d]
                    code = round(v * 10.0) if 0.0 <= v < 1e6 else -1
                    if abs(v * 10.0 - code) > 0.001 or code < 0 or (d[0] == "m" and code % 10):
                        raise ln.error(f"{d[0].upper()}{v:g} is not a valid code", d, "unsupported")
                    (gs if d[0] == "g" else ms).append(int(code) if d[0] == "g" else int(code) // 10)
                    if ln.cols is not None:
                        ln.cols.setdefault(f"{d[0]}{int(code) if d[0] == 'g' else int(code) // 10}", ln.cols[d])
        groups: dict[int, int] = {}
        for g in gs:
            grp = G_GROUP.get(g)
            if grp is None:
                what = G_UNSUPPORTED.get(g, f"G{g / 10:g}")
                raise ln.error(f"{what} is not supported", f"g{g}", "unsupported")
            if grp in groups:
                if grp == 1 and 800 in (g, groups[1]):    # LinuxCNC: G80 with another motion code yields
                    groups[1] = g if groups[1] == 800 else groups[1]
                    continue
                raise ln.error(f"G{g / 10:g} and G{groups[grp] / 10:g} are in the same modal group "
                               f"(group {grp})", f"g{g}", "modal")
            groups[grp] = g
        mgroups: dict[int, int] = {}
        io: list[int] = []
        for m in ms:
            grp = M_GROUP.get(m)
            if grp is None and m in self.noop_m:
                self.messages.append((ln.num, f"M{m} ignored: a no-op here ([planner] noop_m_codes)"))
                continue
            if grp is None:
                what = M_UNSUPPORTED.get(m, f"M{m}")
                if 100 <= m <= 199:
                    what = f"M{m} user-defined M-code"
                elif m >= 200:
                    what = f"M{m} (user M-code or remap, undefined here)"
                raise ln.error(f"{what} is not supported", f"m{m}", "unsupported")
            if grp == 5:
                io.append(m)
            if grp in mgroups and mgroups[grp] != m and not (grp == 8 and {m, mgroups[grp]} == {7, 8}):
                raise ln.error(f"M{m} and M{mgroups[grp]} are in the same modal group", f"m{m}", "modal")
            mgroups[grp] = m
        if len(ms) > 5:
            raise ln.error("more than five M words on one line", f"m{ms[5]}", "modal")
        return gs, groups, mgroups

    def _check_words(self, ln: Line, vals: dict, groups: dict, gset: set, mgroups: dict):
        g0 = groups.get(0)
        motion_g = groups.get(1)
        axis_user = g0 if g0 in _AXIS_USERS else None
        if g0 in (281, 301) and ln.axes:
            raise ln.error(f"G{g0 / 10:g} takes no axis words", ln.axes[0][1], "word")
        if axis_user is not None and motion_g is not None and motion_g != 800:
            raise ln.error(f"G{g0 / 10:g} and G{motion_g / 10:g} both use the axis words", f"g{motion_g}",
                           "modal")
        motion = motion_g if motion_g is not None else self.motion
        if (431 in gset or 432 in gset) and axis_user is None and motion_g is None:
            axis_user = 431         # G43.1/G43.2: the axis words are the offset, not a move (LinuxCNC)
        if ln.axes and axis_user is None and motion == 800:
            raise ln.error("axis words without a motion mode (G0/G1/G2/G3)" if motion_g is None
                           else "axis words with G80", ln.axes[0][1], "word")
        arcw = motion in (20, 30) and axis_user is None and (bool(ln.axes) or motion_g in (20, 30))
        cyc = motion in CYCLES and axis_user is None
        spl = motion in (50, 51) and axis_user is None
        # LinuxCNC's motion_to_be: the line's motion code, else the modal one when the line has axis words
        to_be = motion_g if motion_g is not None else (self.motion if ln.axes and axis_user is None else None)
        io = 5 in mgroups
        m66 = mgroups.get(5) == 66
        g10 = g0 == 100
        for letter, users in (("i", arcw or g10 or spl), ("j", arcw or g10 or spl), ("k", arcw),
                              ("r", arcw or g10 or cyc or 640 in gset),
                              ("p", arcw or g0 in (40, 100) or 640 in gset or cyc or io or motion == 50),
                              ("q", motion == 50 or 640 in gset or cyc or (io and mgroups.get(5) in (66, 67, 68))
                               or 61 in mgroups.values() or g10 and vals.get("l") in (1.0, 10.0, 11.0)),
                              ("h", 430 in gset), ("l", g0 == 100 or cyc or m66),
                              ("e", io and mgroups.get(5) in (66, 67, 68)),
                              ("d", bool(gset & {410, 411, 420, 421}) or to_be in (730, 830))):
            if letter in vals and not users:
                raise ln.error(f"{letter.upper()} word with no G or M code that uses it", letter, "word")
        return g0, motion_g, motion, axis_user

    def _execute(self, ln: Line):
        vals = self._eval(ln)
        self.line_now = ln.num
        gs, groups, mgroups = self._codes(ln, vals)
        gset = set(gs)
        g0, motion_g, motion, axis_user = self._check_words(ln, vals, groups, gset, mgroups)
        # -- assignments (all values were read before any is set)
        if ln.assigns:
            for kind, target, key in ln.assigns:
                v = vals[key]
                if kind == "n":
                    self.P[target] = v * self.mu if target in LENGTH_PARAMETERS else v
                    if target in self.runtime_pending:     # set by the program: known again
                        self.runtime_pending.discard(target)
                elif kind == "i":
                    t = int(vals[ln.dyn[target]])
                    if t in self.readonly_numbers:
                        raise ln.error(f"parameter #{t} is read-only", key, "parameter")
                    self.P[t] = v * self.mu if t in LENGTH_PARAMETERS else v
                elif kind == "l":
                    self.L[target] = v
                else:
                    self.G[target] = v
        if ln.comments:
            self._comments(ln)
        self._modes_early(ln, vals, gset, mgroups)
        diameter = self.diameter
        self._modes_late(ln, vals, groups, gset)
        if 70 in gset or 80 in gset:
            self.diameter = 70 in gset
            self._refresh_offsets()
            if self.diameter != diameter and "x" in vals:    # LinuxCNC: G7/G8 act on their line's X
                vals = dict(vals)
                vals["x"] *= 0.5 if self.diameter else 2.0
        # -- G10 / G28 / G30 / G92 family
        if g0 == 100:
            self._g10(ln, vals)
        elif g0 in (520, 920, 921, 922, 923):
            self._g92(ln, vals, g0)
        elif g0 in (280, 300):
            self._g28(ln, vals, 5161 if g0 == 280 else 5181)
        elif g0 in (281, 301):
            base = 5161 if g0 == 281 else 5181
            ref = self._ref_point(self.pos)
            for i in range(6):
                self.P[base + i] = ref[i]
        # -- motion
        self._motion(ln, vals, g0, motion_g, motion, axis_user)
        return self._stops(ln, mgroups)

    def _modes_early(self, ln: Line, vals: dict, gset: set, mgroups: dict) -> None:
        """Steps 3-14: feed mode, F, S, T, I/O, M6/M61, spindle, M70-M73, coolant, dwell."""
        if 930 in gset or 940 in gset:
            inv = 930 in gset
            if inv != self.inverse_time:
                self.feed = 0.0   # an F of the other mode means something else: a new F is required
            self.inverse_time = inv
        if 200 in gset or 210 in gset:     # lengths of this line (F, G64 P ...) are read in the new units
            new_u = 25.4 if 200 in gset else 1.0
            if new_u != self.u:
                self.feed = self.feed * self.u / new_u   # keep the physical feed of an earlier F
                self.u = new_u
                self.scale = [new_u] * 3 + [1.0] * 3
        if "f" in vals:
            self._set_feed(ln, vals["f"])
        spindle_changed = False
        if "s" in vals:
            s = vals["s"]
            if s < 0.0:
                raise ln.error(f"negative spindle speed S{s:g}", "s", "value")
            if s != self.rpm:
                spindle_changed = self.spindle_dir != 0
            self.rpm = s
        if "t" in vals:
            self._select_tool(ln, vals["t"])
        if 5 in mgroups:
            self._io(ln, vals, mgroups[5])
        tc = mgroups.get(6)
        if tc == 6:
            self.tool = self.selected
            self._emit(Block(B.TOOL_CHANGE, ln.num, tool=self.tool, tool_length_mm=self.tool_len))
        elif tc == 61:
            self._m61(ln, vals)
        sp = mgroups.get(7)
        if sp is not None:
            self.spindle_dir = {3: 1, 4: -1, 5: 0}[sp]
            spindle_changed = True
        if spindle_changed:
            self._emit(Block(B.SPINDLE, ln.num, spindle_rpm=self.rpm * self.spindle_dir))
        if 10 in mgroups:
            self._modal_state(ln, mgroups[10])
        if 8 in mgroups:
            for m in ln.ms:
                if m in (7, 8, 9):
                    if m == 9:
                        self.mist = self.flood = False
                    elif m == 7:
                        self.mist = True
                    else:
                        self.flood = True
                    self._emit(Block(B.COOLANT, ln.num, coolant={7: "mist", 8: "flood", 9: "off"}[m]))
        if 40 in gset:
            if "p" not in vals:
                raise ln.error("G4 dwell needs a P word (seconds)", "g40", "word")
            p = vals["p"]
            if p < 0:
                raise ln.error(f"negative dwell time P{p:g}", "p", "value")
            self._emit(Block(B.DWELL, ln.num, seconds=p, exact_stop=True))

    def _modes_late(self, ln: Line, vals: dict, groups: dict, gset: set) -> None:
        """Steps 15-22: plane, G43/G49, coordinate system, path control, distance, retract mode."""
        for g in (170, 180, 190):
            if g in gset:
                if self.comp_side and g != self.plane:
                    raise ln.error("cannot change planes with cutter radius compensation on", f"g{g}", "comp")
                self.plane = g
        for g in (400, 410, 411, 420, 421):
            if g in gset:
                self._comp_mode(ln, vals, g)
        if 430 in gset:
            self._g43(ln, vals)
        elif 431 in gset or 432 in gset:
            self._g43_dynamic(ln, vals, 431 in gset)
        elif 490 in gset:
            self._set_tool_length(0.0)
        cs = groups.get(12)
        if cs is not None:
            self.cs = {540: 1, 550: 2, 560: 3, 570: 4, 580: 5, 590: 6, 591: 7, 592: 8, 593: 9}[cs]
            self.P[5220] = float(self.cs)
            self._refresh_offsets()
        pc_ = groups.get(13)
        if pc_ is not None:
            if pc_ == 640:
                self.exact_stop = False
                if "p" in vals:
                    p = vals["p"]
                    if p < 0:
                        raise ln.error(f"negative blending tolerance P{p:g}", "p", "value")
                    self.blend = p * self.u if p > 0 else None
                else:
                    self.blend = None
                if "q" in vals and vals["q"] < 0:
                    raise ln.error("negative G64 Q tolerance", "q", "value")
            else:
                self.exact_stop = True
                self.blend = None
        if 900 in gset:
            self.absolute = True
        elif 910 in gset:
            self.absolute = False
        if 901 in gset:
            self.arc_absolute = True
        elif 911 in gset:
            self.arc_absolute = False
        if 980 in gset:
            self.retract_r = False
        elif 990 in gset:
            self.retract_r = True

    def _motion(self, ln: Line, vals: dict, g0, motion_g, motion: int, axis_user) -> None:
        prev = self.motion
        if motion_g is not None:
            self.motion = motion_g
        if self.comp_side and (g0 in (280, 300, 530) or (motion in CYCLES or motion in PROBES)
                               and (ln.axes or motion_g is not None)):
            what = {280: "G28", 300: "G30", 530: "G53"}.get(g0, f"G{motion / 10:g}")
            raise ln.error(f"{what} cannot be used with cutter radius compensation on (G40 first)",
                           f"g{g0 if g0 in (280, 300, 530) else motion}", "comp")
        if axis_user is not None:
            return
        if motion in CYCLES:
            if g0 == 530:
                raise ln.error("G53 cannot be used with a canned cycle", "g530", "modal")
            if ln.axes:
                self._cycle(ln, vals, motion, prev)
            elif motion_g is not None:
                raise ln.error(f"canned cycle G{motion / 10:g} without axis words", f"g{motion}", "word")
            return
        do_move = motion != 800 and (bool(ln.axes) or motion_g in (20, 30))
        if do_move or motion_g is not None:
            self.cycle["il"] = None      # a non-cycle motion ends a series of canned cycles
            if motion != 50:
                self.g5_pq = None        # ... and any other than G5 a series of G5 splines
        if not do_move:
            if g0 == 530:
                raise ln.error("G53 without a G0/G1 move on the line", "g530", "word")
            if motion in PROBES and motion_g is not None:
                raise ln.error(f"G{motion / 10:g} probe without an axis word", f"g{motion}", "word")
            return
        g53 = g0 == 530
        if g53:
            if motion not in (0, 10):
                raise ln.error("G53 needs G0 or G1 motion", "g530", "modal")
            if not self.absolute:
                raise ln.error("G53 cannot be used in incremental mode G91", "g530", "modal")
        if motion in (20, 30):
            self._arc(ln, vals, motion)
        elif motion in (50, 51):
            self._spline(ln, vals, motion)
        elif motion in PROBES:
            self._probe(ln, vals, motion)
        else:
            self._move(ln, vals, motion, g53)

    def _stops(self, ln: Line, mgroups: dict):
        stop = mgroups.get(4)
        if stop is None:
            return None
        if stop in (2, 30) and self.comp_side:
            self._comp_off(ln)
        if stop == 0:
            self._emit(Block(B.PAUSE, ln.num, exact_stop=True))
        elif stop == 1:
            self._emit(Block(B.OPTIONAL_PAUSE, ln.num, exact_stop=True))
        else:
            self._emit(Block(B.END, ln.num, exact_stop=True))
            return "M2" if stop == 2 else "M30"
        return None
