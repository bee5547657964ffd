"""Canned cycles G73, G81-G86, G89 with G98/G99 and L repeats (LinuxCNC semantics).

A cycle becomes ordinary rapid, feed, dwell and spindle blocks (exact stop,
as LinuxCNC runs cycles in exact-path mode).  In the G17 plane the hole is at
X Y and the drilling axis is Z; G18: hole at Z X, drilling along Y; G19: hole
at Y Z, drilling along X.  Per hole (LinuxCNC ``convert_cycle_xy``):

1. if the drilling axis is below R: rapid to R first (once, before the first hole);
2. rapid to the hole at the clearance level (the current level for the first
   hole if it is above R), then down to R;
3. the cycle's moves; the return level is R with G99, the level before the
   series of cycles (or R if higher) with G98.

R, the depth and P/Q are sticky while the same cycle repeats.  G91: X/Y are
increments repeated L times, R is relative to the start level and the depth
relative to R.  G76 (lathe threading), G87 (needs spindle orientation) and G88
(manual retract) are refused as ``unsupported``.

G73/G83 peck clearance (LinuxCNC ``convert_cycle_g73``/``g83``): after each peck
G73 rapids up to the peck's depth + clearance, G83 rapids out to R and back down
to the peck's depth + clearance.  The clearance is the line's D word if it has
one (any sign, in program units, for every hole of the line; not modal), else
LinuxCNC's default for the machine unit: 0.050 on an inch machine, 1 on a mm
machine, taken as that many *program* units (LinuxCNC sets it once from the
machine unit and adds it to program coordinates unconverted: 1 inch under G20
on a mm machine, 0.050 mm under G21 on an inch machine).
"""
from __future__ import annotations

from . import blocks as B
from .blocks import Block
from .lexer import Line

#: (hole axis a, hole axis b, drilling axis) per plane
_PLANE_AXES = {170: (0, 1, 2), 180: (2, 0, 1), 190: (1, 2, 0)}
#: G73/G83 clearance above the previous peck without a D word, in program units, by machine unit
#: (LinuxCNC rs274ngc_pre.cc: G73_PECK_CLEARANCE / G83_PECK_CLEARANCE defaults)
PECK_CLEARANCE_PROGRAM_UNITS = {"inch": 0.050, "mm": 1.0}


class CycleMixin:
    """Canned cycles of :class:`~hexacnc.gcode.interp.Interpreter` (uses its state)."""

    def _cycle(self, ln: Line, vals: dict, motion: int, prev: int) -> None:
        gname = f"G{motion // 10}"
        if self.inverse_time:
            raise ln.error(f"canned cycle {gname} cannot be used in inverse-time mode G93", f"g{motion}", "feed")
        if self.feed <= 0.0:
            raise ln.error(f"canned cycle {gname} with zero feed rate (no F word yet)", f"g{motion}", "feed")
        ia, ib, ic = _PLANE_AXES[self.plane]
        depth = "xyz"[ic]
        cyc = self.cycle
        if "r" not in vals and prev != motion:
            raise ln.error(f"{gname} needs an R word (retract level)", f"g{motion}", "word")
        if depth not in vals and prev != motion:
            raise ln.error(f"{gname} in the G{self.plane // 10} plane needs a {depth.upper()} word (depth)",
                           f"g{motion}", "word")
        r_raw = vals.get("r", cyc["r"])
        z_raw = vals.get(depth, cyc["cc"])
        reps = vals.get("l", 1.0)
        if reps != int(reps) or reps < 1:
            raise ln.error(f"L{reps:g}: canned cycle repeats must be a positive integer", "l", "cycle")
        p = self._cycle_word(ln, vals, "p", motion, prev, (820, 840, 860, 890), 0.0)
        q = self._cycle_word(ln, vals, "q", motion, prev, (730, 830), None)
        if motion in (730, 830) and q <= 0.0:
            raise ln.error(f"{gname} Q{q / self.u:g}: the peck depth must be positive", "q", "cycle")
        peck_up = self._peck_clearance_mm(vals) if motion in (730, 830) else 0.0
        if motion == 840 and self.plane != 170:
            # LinuxCNC's G84 in G18/G19 swaps the cycle's arguments and taps along the wrong axis
            # (interp_cycles.cc convert_cycle_g74_g84, XZ/YZ cases): neither reproduced nor guessed
            raise ln.error(f"G84 tapping in the G{self.plane // 10} plane is not supported (G17 only)",
                           f"g{motion}", "unsupported")
        if motion == 840 and self.spindle_dir <= 0:
            raise ln.error("G84 tapping needs the spindle turning clockwise (M3)", f"g{motion}", "cycle")
        if motion == 860 and self.spindle_dir == 0:
            raise ln.error("G86 needs the spindle turning", f"g{motion}", "cycle")
        u = self.u
        cur = self._prog_pose()
        if cyc["il"] is None:
            cyc["il"] = cur[ic]
        old = cyc["il"]
        current = cur[ic]
        inc_a = inc_b = 0.0
        aa, bb = cur[ia], cur[ib]
        if self.absolute:
            r, cc = r_raw * u, z_raw * u
            aa = vals["xyz"[ia]] * u if "xyz"[ia] in vals else aa
            bb = vals["xyz"[ib]] * u if "xyz"[ib] in vals else bb
        else:
            inc_a = vals.get("xyz"[ia], 0.0) * u
            inc_b = vals.get("xyz"[ib], 0.0) * u
            r = r_raw * u + old
            cc = r + z_raw * u
        if r < cc:
            raise ln.error(f"{gname}: R ({r / u:g}) is below the depth {depth.upper()} ({cc / u:g})",
                           "r" if "r" in vals else depth, "cycle")
        for i, letter in ln.axes:
            if i >= 3:
                raise ln.error(f"{letter.upper()} word in a canned cycle", letter, "word")
        axes = (ia, ib, ic)
        if old < r:
            self._cyc(ln, False, axes, cur[ia], cur[ib], r)
            old = current = r
        clear = r if self.retract_r else old
        for n in range(int(reps)):
            aa += inc_a
            bb += inc_b
            if n == 0 and current > r:
                self._cyc(ln, False, axes, aa, bb, current)
                self._cyc(ln, False, axes, aa, bb, r)
            else:
                self._cyc(ln, False, axes, aa, bb, clear)
                if clear > r:
                    self._cyc(ln, False, axes, aa, bb, r)
            self._cycle_body(ln, motion, axes, aa, bb, r, clear, cc, p, q, peck_up)
        cyc["r"], cyc["cc"] = r_raw, z_raw

    def _cycle_word(self, ln: Line, vals: dict, letter: str, motion: int, prev: int, users, default):
        if motion not in users:
            return 0.0
        key = letter
        if letter in vals:
            v = vals[letter]
            if v < 0:
                raise ln.error(f"{letter.upper()}{v:g} must not be negative", letter, "cycle")
            self.cycle[key] = v
        elif prev != motion:
            if default is None or motion in (820, 860, 890):
                what = "dwell time P (seconds)" if letter == "p" else "peck depth Q"
                raise ln.error(f"G{motion // 10} needs a {what}", f"g{motion}", "word")
        v = self.cycle[key]
        return v * self.u if letter == "q" else v

    def _peck_clearance_mm(self, vals: dict) -> float:
        """G73/G83 retract above each peck: the line's D word, else the machine unit's default, both in
        program units (see the module docstring)."""
        d = vals.get("d")
        if d is None:
            d = PECK_CLEARANCE_PROGRAM_UNITS["inch" if self.mu == 25.4 else "mm"]
        return d * self.u

    def _cycle_body(self, ln, motion, axes, aa, bb, r, clear, cc, p, q, peck_up) -> None:
        """The moves of one hole from R (``p`` dwell s, ``q`` peck depth mm, ``peck_up`` peck clearance mm)."""
        feed, trav = (lambda z: self._cyc(ln, True, axes, aa, bb, z)), (lambda z: self._cyc(ln, False, axes, aa, bb, z))
        if motion in (730, 830):
            d = r - q
            while d > cc:
                feed(d)
                if motion == 830:
                    trav(r)
                trav(d + peck_up)
                d -= q
            feed(cc)
            trav(clear)
        elif motion == 810:
            feed(cc)
            trav(clear)
        elif motion == 820:
            feed(cc)
            self._emit(Block(B.DWELL, ln.num, seconds=p, exact_stop=True))
            trav(clear)
        elif motion == 850:
            feed(cc)
            feed(r)
            trav(clear)
        elif motion == 890:
            feed(cc)
            self._emit(Block(B.DWELL, ln.num, seconds=p, exact_stop=True))
            feed(clear)
        elif motion == 860:
            feed(cc)
            self._emit(Block(B.DWELL, ln.num, seconds=p, exact_stop=True))
            self._emit(Block(B.SPINDLE, ln.num, spindle_rpm=0.0))
            trav(clear)
            self._emit(Block(B.SPINDLE, ln.num, spindle_rpm=self.rpm * self.spindle_dir))
        elif motion == 840:
            feed(cc)
            self._emit(Block(B.SPINDLE, ln.num, spindle_rpm=-self.rpm))
            self._emit(Block(B.DWELL, ln.num, seconds=p, exact_stop=True))
            feed(clear)
            self._emit(Block(B.SPINDLE, ln.num, spindle_rpm=self.rpm))

    def _cyc(self, ln: Line, feed: bool, axes, a: float, b: float, c: float) -> None:
        """One cycle move to program point (hole a, hole b, drilling level c), exact stop."""
        prog = self._prog_pose()
        prog[axes[0]], prog[axes[1]], prog[axes[2]] = a, b, c
        end = self._to_machine(prog)
        if end == self.pos:
            return
        saved = self.exact_stop, self.blend
        self.exact_stop, self.blend = True, None
        try:
            if feed:
                self._line_to(ln, end)
            else:
                self._rapid_to(ln, end)
        finally:
            self.exact_stop, self.blend = saved
