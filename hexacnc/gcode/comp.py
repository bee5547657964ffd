"""Cutter radius compensation G41/G42/G41.1/G42.1/G40 in the G17 and G18 planes (LinuxCNC's algorithm).

As LinuxCNC (``convert_straight_comp1/2``, ``convert_arc_comp2``,
``move_endpoint_and_flush``): the compensated moves are held in a short queue
until the next move decides the corner; a convex corner gets an arc around
the programmed corner (G1) or a straight traverse (G0), a concave corner moves
the end point of the queued move back to the intersection.  The entry move
(first move after G41/G42) goes to the offset point of its end; after G40 the
next move goes from the compensated point to the programmed end.  Gouging is
refused (code ``comp``) with line and column, as LinuxCNC does.  Work is done in
program coordinates (mm) of the plane: (X, Y) in G17, (Z, X) in G18 (LinuxCNC's order, normal +Y);
the third axis and A/B/C move with the moves.  G19 is refused as by LinuxCNC.
In G93 each programmed move's inverse-time F becomes a feed per minute over its
programmed length (as LinuxCNC), used by the compensated moves it makes.
Not supported (``unsupported``): an arc as the entry move.
"""
from __future__ import annotations

import math

import numpy as np

from . import blocks as B
from .blocks import Block, frozen_pose
from .lexer import Line

SMALL = 0.05          #: LinuxCNC TOLERANCE_CONCAVE_CORNER (rad)
_PI = math.pi


def find_turn(x1, y1, cx, cy, turn, x2, y2) -> float:
    """Signed sweep (rad) from (x1, y1) to (x2, y2) about (cx, cy), ``turn`` CCW turns (negative: CW)."""
    if turn == 0:
        return 0.0
    a = math.atan2(y1 - cy, x1 - cx)
    b = math.atan2(y2 - cy, x2 - cx)
    if turn > 0:
        if b <= a:
            b += 2 * _PI
        return b - a + (turn - 1) * 2 * _PI
    if a <= b:
        a += 2 * _PI
    return b - a + (turn + 1) * 2 * _PI


def _inside(side: str, turn: int) -> bool:
    return (side == "L" and turn > 0) or (side == "R" and turn < 0)


class CompMixin:
    """Cutter compensation of :class:`~hexacnc.gcode.interp.Interpreter` (uses its state)."""

    # -- mode changes -------------------------------------------------------------------
    def _comp_mode(self, ln: Line, vals: dict, g: int) -> None:
        if g == 400:
            self._comp_off(ln)
            return
        if self.plane == 190:      # LinuxCNC: "allowed only in XY, XZ planes"
            raise ln.error("cutter radius compensation works in the G17 and G18 planes only", f"g{g}", "comp")
        if self.comp_side:
            raise ln.error("cutter radius compensation is already on (G40 first)", f"g{g}", "comp")
        if g in (411, 421):
            if "d" not in vals:
                raise ln.error(f"G{g / 10:g} needs a D word (tool diameter)", f"g{g}", "word")
            r = vals["d"] * self.u / 2.0
        else:
            t = self.tool
            if "d" in vals:
                d = vals["d"]
                if d < 0 or abs(d - round(d)) > 1e-4:
                    raise ln.error(f"G{g // 10} D{d:g}: D must be a tool number", "d", "tool")
                t = int(round(d))
            e = self._entry(t)
            if e is None and t != 0:
                raise ln.error(f"G{g // 10} D{t}: tool {t} is not in the tool table", "d" if "d" in vals
                               else f"g{g}", "tool")
            r = (e.diameter_mm if e is not None else 0.0) / 2.0
        side = "L" if g in (410, 411) else "R"
        if r < 0:
            r, side = -r, ("R" if side == "L" else "L")
        if r == 0.0:          # LinuxCNC: a zero radius compensates nothing
            self.comp_side, self.comp_r, self.comp_first, self.comp_q = None, 0.0, True, None
            self.comp_zero = True
            return
        self.comp_side, self.comp_r, self.comp_first = side, r, True
        self.comp_q = []
        # the plane's axes (first, second, normal): X Y Z in G17; Z X Y in G18 (LinuxCNC's comp_get_current)
        self.comp_perm = (0, 1, 2) if self.plane == 170 else (2, 0, 1)
        cur = self._cperm(self._prog_pose())
        self.comp_last6, self.comp_cur, self.comp_prog = cur, cur[:3], cur[:3]
        self.slow = True

    def _comp_off(self, ln: Line) -> None:
        if self.comp_side and self.comp_r > 0 and not self.comp_first:
            self._move_endpoint_and_flush(ln, *self.comp_cur[:2])
            self._comp_flush()
            self.comp_arc_not_allowed = True
        self.comp_side = None
        self.comp_first = True
        self.slow = self.rot_deg != 0.0 or self.comp_arc_not_allowed or self.diameter  # (next move clears)

    # -- the queue -----------------------------------------------------------------------
    def _comp_flush(self) -> None:
        q, self.comp_q = self.comp_q, []
        for it in q:
            if it[0] == "block":
                self.blocks.append(it[1])
            else:
                self._comp_out(*it)
        self.comp_q = [] if self.comp_side else None
        self.comp_endpoint = None

    def _cperm(self, p: list[float]) -> list[float]:
        """Program pose -> the compensation plane's coordinates (first, second, normal, A, B, C)."""
        a, b, c = self.comp_perm
        return [p[a], p[b], p[c]] + list(p[3:])

    def _cunperm(self, q: list[float]) -> list[float]:
        p = list(q)
        for k, i in enumerate(self.comp_perm):
            p[i] = q[k]
        return p

    def _comp_out(self, kind, line, end_prog, center, turn, _orig, _dir, fm, inv) -> None:
        end = self._to_machine(self._cunperm(end_prog))
        if end == self.pos and kind != "arc":      # (an arc back to its start is a full circle)
            return
        e = frozen_pose(end)
        es, bl, tl, tool = self.exact_stop, self.blend, self.tool_len, self.tool
        if kind == "arc":
            c = self._to_machine(self._cunperm([center[0], center[1], end_prog[2], 0.0, 0.0, 0.0]))[:3]
            w = self.comp_perm[2]
            c[w] = self.pos[w]
            normal = [0.0, 0.0, 0.0]
            normal[w] = 1.0
            b = Block(B.ARC, line, self._start_arr(), e, fm, inv, np.array(c), np.array(normal),
                      abs(turn) - 1, turn < 0, es, bl, tl, 0.0, 0.0, "off", tool)
        elif kind == "rapid":
            b = Block(B.RAPID, line, self._start_arr(), e, None, None, None, None, 0, False, es, bl, tl,
                      0.0, 0.0, "off", tool)
        else:
            b = Block(B.LINE, line, self._start_arr(), e, fm, inv, None, None, 0, False, es, bl, tl,
                      0.0, 0.0, "off", tool)
        self.blocks.append(b)
        self.pos = end
        self.pos_arr = e

    def _enqueue(self, ln: Line, kind, end_prog, center=None, turn=0, orig=0.0, direction=(0.0, 0.0)) -> None:
        fm = inv = None
        if kind != "rapid":
            if self.inverse_time:
                fm = self.comp_fm
            else:
                fm, inv = self._feed_of(ln, {}, 10 if kind == "line" else 20)
        self.comp_q.append([kind, ln.num, list(end_prog), center, turn, orig, direction, fm, inv])
        self.comp_last6 = list(end_prog)

    def _move_endpoint_and_flush(self, ln: Line, x: float, y: float) -> None:
        if not self.comp_q:
            return
        ep = self.comp_endpoint
        for it in self.comp_q:
            if it[0] == "arc":
                cx, cy = it[3]
                r1 = math.hypot(it[2][0] - cx, it[2][1] - cy)
                r2 = math.hypot(x - cx, y - cy)
                if abs(r1 - r2) > 0.01 * self.u:
                    raise ln.error("cutter compensation made an arc with mismatched radii", None, "comp")
                if it[5] != 0.0 and ep is not None:
                    l2 = find_turn(ep[0], ep[1], cx, cy, it[4], x, y)
                    if abs(l2) > abs(it[5]) + 0.001 * self.u:
                        raise ln.error("arc move in a concave corner cannot be reached by the tool without "
                                       "gouging", None, "comp")
            elif it[0] in ("line", "rapid"):
                d = it[6]
                if ep is not None and d[0] * (x - ep[0]) + d[1] * (y - ep[1]) < 0:
                    raise ln.error("straight move in a concave corner cannot be reached by the tool without "
                                   "gouging", None, "comp")
            else:
                continue
            it[2][0], it[2][1] = x, y
        self._comp_flush()
        self.comp_endpoint = (x, y)

    # -- moves ---------------------------------------------------------------------------
    def _comp_target(self, ln: Line, vals: dict) -> list[float]:
        """Programmed end (program coordinates, mm/deg): missing X/Y from the programmed point."""
        prog = list(self.comp_last6)
        prog[0], prog[1] = self.comp_prog[0], self.comp_prog[1]
        perm = self.comp_perm
        for i, letter in ln.axes:
            v = vals[letter] * self.u if i < 3 else vals[letter]
            k = perm.index(i) if i < 3 else i
            prog[k] = v if self.absolute else prog[k] + v
        return prog

    def _comp_inverse_feed(self, ln: Line, vals: dict, motion: int, length_mm: float) -> None:
        """G93 with compensation, as LinuxCNC: the inverse-time F becomes the feed per minute of the
        programmed (uncompensated) move's length, used by all the compensated moves it makes."""
        f = vals.get("f")
        if f is None or f <= 0.0:
            raise ln.error(f"G93 inverse-time G{motion // 10} move needs a positive F word on its line",
                           "f" if f is not None else f"g{motion}", "feed")
        if length_mm <= 0.0:
            raise ln.error("an inverse-time move without X/Y/Z motion under cutter compensation is not "
                           "supported", f"g{motion}", "unsupported")
        self.comp_fm = length_mm * f / 60.0

    def _comp_straight(self, ln: Line, vals: dict, motion: int) -> None:
        kind = "rapid" if motion == 0 else "line"
        p = self._comp_target(ln, vals)
        if self.inverse_time and motion != 0:
            o = self._cperm(self._prog_pose()) if self.comp_first else self.comp_prog
            self._comp_inverse_feed(ln, vals, motion, math.dist(p[:3], o[:3]))
        r, side = self.comp_r, self.comp_side
        if self.comp_first:
            cur = self._cperm(self._prog_pose())
            cx, cy = cur[0], cur[1]
            if math.hypot(p[0] - cx, p[1] - cy) <= r:
                raise ln.error("cutter compensation entry move is not longer than the tool radius",
                               ln.axes[0][1] if ln.axes else None, "comp")
            a = math.atan2(p[1] - cy, p[0] - cx) + (_PI / 2 if side == "L" else -_PI / 2)
            end = [p[0] + r * math.cos(a), p[1] + r * math.sin(a)] + p[2:]
            self.comp_endpoint = (cx, cy)
            self._enqueue(ln, kind, end, direction=(math.cos(a), math.sin(a)))
            self.comp_first = False
            self.comp_cur, self.comp_prog = end[:3], p[:3]
            return
        cx, cy = self.comp_cur[0], self.comp_cur[1]
        opx, opy = self.comp_prog[0], self.comp_prog[1]
        px, py = p[0], p[1]
        if px == opx and py == opy:
            self._enqueue(ln, kind, [cx, cy] + p[2:], direction=(0.0, 0.0))
            self.comp_cur, self.comp_prog = [cx, cy, p[2]], p[:3]
            return
        theta = math.atan2(cy - opy, cx - opx)
        alpha = math.atan2(py - opy, px - opx)
        if side == "L":
            if theta < alpha:
                theta += 2 * _PI
            beta, gamma = theta - alpha - _PI / 2, _PI / 2
        else:
            if alpha < theta:
                alpha += 2 * _PI
            beta, gamma = alpha - theta - _PI / 2, -_PI / 2
        end = [px + r * math.cos(alpha + gamma), py + r * math.sin(alpha + gamma)]
        mid = [opx + r * math.cos(alpha + gamma), opy + r * math.sin(alpha + gamma)]
        front = next((it for it in self.comp_q if it[0] != "block"), None)
        front_arc = front is not None and front[0] == "arc"
        concave = beta < -SMALL or beta > _PI + SMALL or (
            beta > _PI - SMALL and front_arc and ((side == "R" and front[4] > 0) or (side == "L" and front[4] < 0)))
        if not concave and beta > SMALL:
            self._move_endpoint_and_flush(ln, cx, cy)
            if kind == "line":
                self._enqueue(ln, "arc", mid + [self.comp_cur[2]] + p[3:], center=(opx, opy),
                              turn=-1 if side == "L" else 1)
            else:
                self._enqueue(ln, "rapid", mid + [self.comp_cur[2]] + p[3:])
            self._comp_flush()
            self.comp_endpoint = tuple(mid)
        elif concave:
            if not front_arc:
                half = (beta + _PI) / 2.0
                if half == 0.0:
                    raise ln.error("zero-degree inside corner is invalid for cutter compensation", None, "comp")
                retreat = r / math.tan(half)
                self._move_endpoint_and_flush(ln, cx + retreat * math.cos(theta + gamma),
                                              cy + retreat * math.sin(theta + gamma))
            else:
                self._move_endpoint_and_flush(ln, *self._arc_line_corner(ln, front, px, py, opx, opy))
        else:
            self._comp_flush()
            self.comp_endpoint = (cx, cy)
        self._enqueue(ln, kind, end + p[2:], direction=(px - opx, py - opy))
        self.comp_cur, self.comp_prog = end + [p[2]], p[:3]

    def _arc_line_corner(self, ln: Line, prev, px, py, opx, opy):
        (c1, c2), pturn, r, side = prev[3], prev[4], self.comp_r, self.comp_side
        oldrad = math.hypot(c2 - prev[2][1], c1 - prev[2][0])
        base = math.atan2(py - opy, px - opx)
        theta = base + _PI / 2 if pturn > 0 else base - _PI / 2
        phi = math.atan2(c2 - opy, c1 - opx)
        inside = _inside(side, pturn)
        unc = oldrad + r if inside else oldrad - r
        d = unc * math.cos(theta - phi)
        ll = (d - r) / oldrad if inside else (d + r) / oldrad
        if not -1.0 <= ll <= 1.0:
            raise ln.error("arc to straight motion makes a corner the compensated tool cannot fit in without "
                           "gouging", None, "comp")
        if inside:
            ang = (-math.acos(ll) if pturn > 0 else math.acos(ll)) + theta + _PI
        else:
            ang = (math.acos(ll) if pturn > 0 else -math.acos(ll)) + theta + _PI
        return c1 + oldrad * math.cos(ang), c2 + oldrad * math.sin(ang)

    def _comp_arc(self, ln: Line, vals: dict, motion: int) -> None:
        """convert_arc_comp2: an arc after the entry move."""
        if self.comp_first:
            raise ln.error("an arc as the cutter compensation entry move is not supported (enter with a line)",
                           f"g{motion}", "unsupported")
        lu, lv, lw = ("i", "j", "k") if self.comp_perm[0] == 0 else ("k", "i", "j")
        if lw in vals:
            raise ln.error(f"{lw.upper()} word with an arc in the G{self.plane // 10} plane", lw, "word")
        p = self._comp_target(ln, vals)
        opx, opy = self.comp_prog[0], self.comp_prog[1]
        cx, cy = self.comp_cur[0], self.comp_cur[1]
        n = 1
        if "p" in vals:
            pv = vals["p"]
            if abs(pv - round(pv)) > 1e-4 or not 1 <= round(pv) <= 10000:
                raise ln.error(f"arc P{pv:g} (number of turns) must be an integer 1..10000", "p", "arc")
            n = int(round(pv))
        cw = motion == 20
        if "r" in vals:
            if "i" in vals or "j" in vals:
                raise ln.error("arc with both R and I/J/K words", "r", "arc")
            ccx, ccy = self._r_centre(ln, vals["r"] * self.u, opx, opy, p[0], p[1], cw)
        else:
            ccx, ccy = self._ijk_centre(ln, vals, lu, lv, opx, opy, p[0], p[1])
        turn = -n if cw else n
        r, side = self.comp_r, self.comp_side
        arc_r = math.hypot(ccx - p[0], ccy - p[1])
        if self.inverse_time:     # the programmed helix's length (LinuxCNC's find_arc_length)
            sweep_len = abs(find_turn(opx, opy, ccx, ccy, turn, p[0], p[1])) * math.hypot(opx - ccx, opy - ccy)
            self._comp_inverse_feed(ln, vals, motion, math.hypot(sweep_len, p[2] - self.comp_prog[2]))
        theta = math.atan2(cy - opy, cx - opx)
        theta = theta - _PI / 2 if side == "L" else theta + _PI / 2
        delta = math.atan2(ccy - opy, ccx - opx)
        alpha = delta - _PI / 2 if not cw else delta + _PI / 2
        beta = theta - alpha if side == "L" else alpha - theta
        if beta > 1.5 * _PI:
            beta -= 2 * _PI
        elif beta < -_PI / 2:
            beta += 2 * _PI
        if (side == "L" and not cw) or (side == "R" and cw):
            gamma = math.atan2(ccy - p[1], ccx - p[0])
            if arc_r <= r:
                raise ln.error(f"tool radius {r / self.u:g} is not less than the arc radius {arc_r / self.u:g} "
                               "with compensation", None, "comp")
        else:
            gamma = math.atan2(p[1] - ccy, p[0] - ccx)
            delta += _PI
        new_end = [p[0] + r * math.cos(gamma), p[1] + r * math.sin(gamma)]
        front = next((it for it in self.comp_q if it[0] != "block"), None)
        inside = _inside(side, turn)
        sweep = find_turn(opx, opy, ccx, ccy, turn, p[0], p[1])
        if beta < -SMALL or beta > _PI + SMALL or (abs(beta - _PI) < SMALL and not inside):
            if front is None or front[0] != "arc":
                h = arc_r * math.sin(beta - _PI / 2)
                dist = arc_r - r if inside else arc_r + r
                ll = (h + r) / dist if inside else (h - r) / dist
                if not -1.0 <= ll <= 1.0:
                    raise ln.error("arc move in a concave corner cannot be reached by the tool without gouging",
                                   None, "comp")
                if inside:
                    ang = theta + math.asin(ll) if turn > 0 else theta - math.asin(ll)
                else:
                    ang = theta + _PI - math.asin(ll) if turn > 0 else theta + _PI + math.asin(ll)
                self._move_endpoint_and_flush(ln, ccx + dist * math.cos(ang), ccy + dist * math.sin(ang))
            else:
                (c1, c2), pturn = front[3], front[4]
                oldrad = math.hypot(c2 - front[2][1], c1 - front[2][0])
                newrad = arc_r - r if inside else arc_r + r
                cc = math.hypot(c2 - ccy, c1 - ccx)
                if oldrad == 0 or cc == 0:
                    raise ln.error("arc to arc motion is invalid because the arcs have the same centre", None,
                                   "comp")
                a = (oldrad ** 2 + cc ** 2 - newrad ** 2) / (2 * oldrad * cc)
                if not -1.0 <= a <= 1.0:
                    raise ln.error("arc to arc motion makes a corner the compensated tool cannot fit in without "
                                   "gouging", None, "comp")
                pull = math.acos(a)
                ccdir = math.atan2(ccy - c2, ccx - c1)
                if _inside(side, pturn):
                    d = ccdir + pull if turn > 0 else ccdir - pull
                else:
                    d = ccdir - pull if turn > 0 else ccdir + pull
                self._move_endpoint_and_flush(ln, c1 + oldrad * math.cos(d), c2 + oldrad * math.sin(d))
            self._enqueue(ln, "arc", new_end + p[2:], center=(ccx, ccy), turn=turn, orig=sweep)
        elif beta > SMALL:
            mid = [opx + r * math.cos(delta), opy + r * math.sin(delta)]
            self._comp_flush()
            self._enqueue(ln, "arc", mid + [self.comp_cur[2]] + self.comp_last6[3:], center=(opx, opy),
                          turn=-1 if side == "L" else 1)
            self._comp_flush()
            self.comp_endpoint = tuple(mid)
            self._enqueue(ln, "arc", new_end + p[2:], center=(ccx, ccy), turn=turn, orig=sweep)
        else:
            self._comp_flush()
            self.comp_endpoint = (cx, cy)
            self._enqueue(ln, "arc", new_end + p[2:], center=(ccx, ccy), turn=turn, orig=sweep)
        self.comp_cur, self.comp_prog = new_end + [p[2]], p[:3]
