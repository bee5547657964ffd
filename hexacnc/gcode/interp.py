"""RS274NGC interpreter (LinuxCNC dialect, hexapod subset) -> motion blocks.

The whole program is interpreted before anything moves: the result is a
:class:`Program` whose blocks carry tool-tip poses in the machine (base) frame,
mm and degrees, with work offsets, G92, G53 and the G43 tool length applied.
Anything the dialect does not support raises :class:`GcodeError` with the
line, the column and a code, never a silent skip.

Error codes: ``syntax``, ``unsupported``, ``word`` (missing, repeated or
unused word), ``modal`` (two codes of one modal group), ``parameter``,
``expression``, ``arc``, ``feed``, ``value``, ``tool``, ``flow`` (O-words),
``runaway`` (execution limit).

Tool length: the controlled point is the tool tip, at ``tool_length_mm``
along the platform tool axis from the tool reference point.  G43/G49 do not
move the platform, so the programmed tool-tip position jumps by
``R(a,b,c) @ axis_platform * (new - old length)``; the next block starts there.

Modules: :mod:`.expr` (expressions), :mod:`.lexer` (lines and shapes),
:mod:`.flow` (O-words), :mod:`.motion` (offsets, tool length, lines, arcs),
this one (modal state, the order of execution within a line, the run loop).
"""
from __future__ import annotations

import gc
import math
import re
from dataclasses import dataclass, field

import numpy as np

from ..errors import GcodeError
from . import blocks as B
from .blocks import Block
from .expr import MAX_PARAMETER, PREDEFINED as _PRED, ExprError, compile_template
from .flow import FlowMixin, _Frame
from .lexer import Line, Presplit, parse_line
from .motion import _LINE, _RAPID, MotionMixin

#: modal groups of the supported G codes (code x10)
_G_GROUP = {0: 1, 10: 1, 20: 1, 30: 1, 800: 1,
            170: 2, 180: 2, 190: 2,
            900: 3, 910: 3, 901: 4, 911: 4, 930: 5, 940: 5, 200: 6, 210: 6, 400: 7,
            430: 8, 490: 8, 540: 12, 550: 12, 560: 12, 570: 12, 580: 12, 590: 12, 591: 12,
            592: 12, 593: 12, 610: 13, 611: 13, 640: 13,
            40: 0, 100: 0, 530: 0, 920: 0, 921: 0, 922: 0, 923: 0, 280: 0, 281: 0, 300: 0, 301: 0}
_G_UNSUPPORTED = {
    50: "G5 splines", 51: "G5.1 quadratic splines", 52: "G5.2 NURBS", 70: "G7 lathe diameter mode",
    80: "G8 lathe radius mode", 330: "G33 spindle-synchronised motion",
    331: "G33.1 rigid tapping", 382: "G38.2 probing", 383: "G38.3 probing", 384: "G38.4 probing",
    385: "G38.5 probing", 410: "G41 cutter radius compensation",
    411: "G41.1 cutter radius compensation", 420: "G42 cutter radius compensation",
    421: "G42.1 cutter radius compensation", 431: "G43.1 dynamic tool length",
    432: "G43.2 additional tool length", 730: "G73 canned cycle", 760: "G76 threading cycle",
    810: "G81 canned cycle", 820: "G82 canned cycle", 830: "G83 canned cycle",
    840: "G84 canned cycle", 850: "G85 canned cycle", 860: "G86 canned cycle",
    870: "G87 canned cycle", 880: "G88 canned cycle", 890: "G89 canned cycle",
    950: "G95 feed per revolution", 960: "G96 constant surface speed", 970: "G97 spindle RPM mode",
    980: "G98 canned-cycle return level", 990: "G99 canned-cycle return level",
    171: "G17.1 plane", 181: "G18.1 plane", 191: "G19.1 plane", 200 + 1: "G20.1",
}
_M_GROUP = {0: 4, 1: 4, 2: 4, 30: 4, 6: 6, 3: 7, 4: 7, 5: 7, 7: 8, 8: 8, 9: 8}
_M_UNSUPPORTED = {
    19: "M19 spindle orientation", 48: "M48 override enable", 49: "M49 override disable",
    50: "M50 feed override control", 51: "M51 spindle override control",
    52: "M52 adaptive feed", 53: "M53 feed stop", 60: "M60 pallet change",
    61: "M61 set current tool", 62: "M62 digital output", 63: "M63 digital output",
    64: "M64 digital output", 65: "M65 digital output", 66: "M66 wait on input",
    67: "M67 analog output", 68: "M68 analog output", 70: "M70 save modal state",
    71: "M71", 72: "M72 restore modal state", 73: "M73",
}
_MSG = re.compile(r"\s*(msg|debug|print)\s*,", re.IGNORECASE)
_SUBST = re.compile(r"#(\d+)|#<([^>]+)>")


@dataclass
class Program:
    """An interpreted program: the planner's input."""
    name: str
    blocks: list[Block]
    line_count: int                           #: source lines
    lines_executed: int = 0                   #: lines interpreted (loops counted each time)
    messages: list[tuple[int, str]] = field(default_factory=list)  #: (line, text) of (MSG,...)
    end_line: int | None = None               #: line of M2/M30/% ending the program
    end_reason: str = "eof"                   #: "M2", "M30", "percent" or "eof"
    final_pose: np.ndarray | None = None      #: (6,) tool tip at the end, machine frame
    units: str = "mm"                         #: units mode at the end

    @property
    def motion_blocks(self) -> list[Block]:
        return [b for b in self.blocks if b.kind in B.MOTION_KINDS]


def _coord_index(key) -> int:
    if isinstance(key, int) and 1 <= key <= 9:
        return key
    names = {"g54": 1, "g55": 2, "g56": 3, "g57": 4, "g58": 5, "g59": 6,
             "g59.1": 7, "g59.2": 8, "g59.3": 9}
    k = str(key).lower().strip()
    if k in names:
        return names[k]
    raise GcodeError(f"unknown coordinate system {key!r} in work_offsets (use G54..G59.3 or 1..9)",
                     None, None, "value")


class Interpreter(FlowMixin, MotionMixin):
    """Interpret one program text; :meth:`run` returns the :class:`Program`."""

    def __init__(self, text: str, name: str = "<program>", *, start_pose=None, work_offsets=None,
                 tool_table=None, units_default: str = "mm", tool_axis_platform=(0.0, 0.0, 1.0),
                 block_delete: bool = True, max_lines: int = 20_000_000,
                 max_blocks: int = 20_000_000, max_call_depth: int = 64, g28_pose=None, g30_pose=None,
                 noop_m_codes=()):
        if not isinstance(text, str):
            raise GcodeError(f"program text must be str, got {type(text).__name__}", None, None, "syntax")
        self.name = name
        lines = text.split("\n")
        if lines and lines[-1] == "":
            lines.pop()
        self.lines = lines
        self.parsed: list[Line | None] = [None] * len(lines)
        if units_default not in ("mm", "inch"):
            raise GcodeError(f"units_default must be 'mm' or 'inch', got {units_default!r}",
                             None, None, "value")
        self.u = 25.4 if units_default == "inch" else 1.0
        self.scale = [self.u] * 3 + [1.0] * 3
        pose = [0.0] * 6 if start_pose is None else [float(v) for v in start_pose]
        if len(pose) != 6 or not all(math.isfinite(v) for v in pose):
            raise GcodeError(f"start_pose must be 6 finite numbers, got {start_pose!r}", None, None, "value")
        self.pos = pose
        self.pos_arr = None
        ax = [float(v) for v in tool_axis_platform]
        n = math.sqrt(sum(v * v for v in ax))
        if len(ax) != 3 or not n > 0:
            raise GcodeError(f"tool_axis_platform must be a non-zero 3-vector, got {tool_axis_platform!r}",
                             None, None, "value")
        self.tool_axis = [v / n for v in ax]
        self.tools: dict[int, float] | None = None
        if tool_table is not None:
            self.tools = {}
            for k, v in dict(tool_table).items():
                t, length = int(k), float(v)
                if t < 0 or not math.isfinite(length):
                    raise GcodeError(f"tool table entry {k!r}: {v!r} is invalid", None, None, "tool")
                self.tools[t] = length
        self.block_delete = bool(block_delete)
        noop = [int(m) for m in noop_m_codes]
        bad = [m for m in noop if not 100 <= m <= 9999 or m in _M_GROUP]
        if bad:
            raise GcodeError(f"noop_m_codes {bad}: only user and remap M-codes (100..9999) can be no-ops",
                             None, None, "value")
        self.noop_m: frozenset = frozenset(noop)    #: user/remap M-codes accepted as no-ops
        self.max_lines = int(max_lines)
        self.max_blocks = int(max_blocks)
        self.max_depth = int(max_call_depth)
        # parameters
        self.P = [0.0] * (MAX_PARAMETER + 1)
        self.G: dict[str, float] = {}
        self.L: dict[str, float] = {}
        offsets = [[0.0] * 6 for _ in range(10)]
        if work_offsets is not None:
            items = work_offsets.items() if hasattr(work_offsets, "items") else enumerate(work_offsets, 1)
            for key, vec in items:
                k = _coord_index(key)
                v = [float(x) for x in vec]
                if len(v) == 3:
                    v += [0.0, 0.0, 0.0]
                if len(v) != 6 or not all(math.isfinite(x) for x in v):
                    raise GcodeError(f"work offset {key!r} must be 3 or 6 finite numbers", None, None, "value")
                offsets[k] = v
        for k in range(1, 10):
            base = 5201 + 20 * k
            for i in range(6):
                self.P[base + i] = offsets[k][i]
        for base, stored in ((5161, g28_pose), (5181, g30_pose)):
            if stored is not None:
                v = [float(x) for x in stored]
                if len(v) != 6 or not all(math.isfinite(x) for x in v):
                    raise GcodeError(f"G28/G30 position must be 6 finite numbers, got {stored!r}", None, None,
                                     "value")
                self.P[base:base + 6] = v
        self.cs = 1
        self.P[5220] = 1.0
        self.g92 = [0.0] * 6
        self.off = list(offsets[1])
        # modal state
        self.motion = 800          # G80: no motion mode until a G0..G3 is given
        self.plane = 170
        self.absolute = True
        self.arc_absolute = False
        self.inverse_time = False
        self.feed = 0.0            # program units (or deg) per minute
        self.rpm = 0.0
        self.spindle_dir = 0       # +1 M3, -1 M4, 0 M5
        self.mist = False
        self.flood = False
        self.tool = 0
        self.selected = 0
        self.tool_len = 0.0
        self.exact_stop = False
        self.blend = None
        self.blocks: list[Block] = []
        self.messages: list[tuple[int, str]] = []
        self.frames: list[_Frame] = []
        self.seek = False
        self.line_now = 0
        self._top_repeat: dict[int, int] = {}
        self._sysfn = self._sys

    # -- parsing and structure ------------------------------------------------
    def _line(self, idx: int) -> Line:
        ln = self.parsed[idx]
        if ln is None:
            ln = parse_line(self.lines[idx], idx + 1)
            self.parsed[idx] = ln
        return ln

    def _find_end(self) -> int | None:
        """Index of a closing '%' line (programs wrapped in %...%), else None."""
        first = None
        for i, raw in enumerate(self.lines):
            t = raw.strip()
            if not t:
                continue
            if first is None:
                first = i
                if t == "%":
                    self.percent_start = i
                    continue
            if t == "%":
                return i
        if self.percent_start is not None:
            raise GcodeError("program starts with '%' but has no closing '%' line",
                             len(self.lines) or 1, 1, "syntax")
        return None

    # -- evaluation ---------------------------------------------------------------
    def _eval(self, ln: Line) -> dict:
        """Word values of ``ln`` (constant and computed) as a dict."""
        vals = ln.words
        if ln.fn is not None:
            try:
                res = ln.fn(self.P, self.L, self.G, self._sys, ln.k)
            except (KeyError, ArithmeticError, ValueError, ExprError, IndexError, TypeError) as exc:
                raise self._expr_error(ln, exc) from None
            vals = dict(vals)
            for key, v in zip(ln.dyn, res):
                if not -1e300 < v < 1e300:
                    raise ln.error(f"value {v!r} is not a finite number", key, "expression")
                vals[key] = v
        return vals

    def _expr_error(self, ln: Line, exc: Exception) -> GcodeError:
        if isinstance(exc, KeyError):
            name = exc.args[0] if exc.args else "?"
            col = 1
            m = re.search(r"#\s*<\s*" + r"\s*".join(map(re.escape, str(name))) + r"\s*>",
                          ln.raw, re.IGNORECASE)
            if m:
                col = m.start() + 1
            return GcodeError(f"parameter #<{name}> is not defined", ln.num, col, "parameter")
        msg = str(exc) or type(exc).__name__
        if isinstance(exc, ZeroDivisionError):
            msg = "division by zero"
        elif isinstance(exc, OverflowError):
            msg = "numeric overflow"
        # locate the word: evaluate one value at a time
        col = 1
        if ln.oword is not None:
            col = ln.column("o")
        elif ln.dyn:
            key = ln.dyn[0]
            for i, src in enumerate(ln.srcs):
                try:
                    compile_template("(" + src + ",)")(self.P, self.L, self.G, self._sys, ln.k)
                except Exception:  # noqa: BLE001 - the first value that fails is the one to name
                    key = ln.dyn[i]
                    break
            col = ln.column(key)
        return GcodeError(f"expression error: {msg}", ln.num, col, "expression")

    def _sys(self, key):
        """Read-only system parameters (numbered and predefined named)."""
        pos, off, u = self.pos, self.off, self.u
        if isinstance(key, int):
            if key == 5400:
                return float(self.tool)
            if key == 5403:
                return self.tool_len / u
            i = key - 5420
            return (pos[i] - off[i]) / (u if i < 3 else 1.0)
        if key in ("_x", "_y", "_z", "_a", "_b", "_c"):
            i = "xyzabc".index(key[1])
            return (pos[i] - off[i]) / (u if i < 3 else 1.0)
        if key.startswith("_abs_"):
            i = "xyzabc".index(key[5])
            return pos[i] / (u if i < 3 else 1.0)
        return float({
            "_line": self.line_now, "_motion_mode": self.motion, "_plane": self.plane,
            "_metric": self.u == 1.0, "_imperial": self.u != 1.0, "_absolute": self.absolute,
            "_incremental": not self.absolute, "_inverse_time": self.inverse_time,
            "_units_per_minute": not self.inverse_time, "_feed": self.feed, "_rpm": self.rpm,
            "_current_tool": self.tool, "_selected_tool": self.selected,
            "_coord_system": [0, 540, 550, 560, 570, 580, 590, 591, 592, 593][self.cs],
            "_tool_offset": self.tool_len / u, "_spindle_on": self.spindle_dir != 0,
            "_spindle_cw": self.spindle_dir > 0, "_flood": self.flood, "_mist": self.mist,
            "_call_level": len(self.frames), "_remap_level": 0,
            "_ijk_absolute_mode": self.arc_absolute,
        }[key])

    # -- running ----------------------------------------------------------------
    def run(self, text: str) -> Program:
        self.percent_start = None
        self.stop_at = self._find_end()
        presplit = Presplit(text, self.lines)
        self._prescan(text, presplit)
        end_reason, end_line = "eof", None
        n = len(self.lines) if self.stop_at is None else self.stop_at
        if self.stop_at is not None:
            end_reason, end_line = "percent", self.stop_at + 1
        pc = 0 if self.percent_start is None else self.percent_start + 1
        executed = 0
        max_lines = self.max_lines
        parsed = self.parsed
        pre = presplit.line
        blocks = self.blocks
        while pc < n:
            ln = parsed[pc]
            if ln is None:
                ln = pre(pc)
                parsed[pc] = ln
            executed += 1
            if executed > max_lines:
                raise GcodeError(f"more than {max_lines} lines executed (endless loop?)", pc + 1, 1, "runaway")
            if ln.empty:
                if ln.comments:
                    self._comments(ln)
                pc += 1
                continue
            if ln.delete and self.block_delete:
                pc += 1
                continue
            if ln.oword is not None:
                pc = self._oword(ln, pc)
                continue
            if self.seek:
                raise ln.error("internal: seeking an O-word branch", None, "flow")
            if ln.plain and self.motion in (0, 10):
                self._plain(ln)
            elif ln.gmot is not None:
                self.motion = ln.gmot
                self._plain(ln)
            elif ln.arcok and ln.axes and self.motion in (20, 30):
                vals = self._eval(ln)      # modal arc: only axis, F, I J K R P words
                self.line_now = ln.num
                if "f" in vals:
                    self._set_feed(ln, vals["f"])
                self._arc(ln, vals, self.motion)
            else:
                r = self._execute(ln)
                if r is not None:
                    end_reason, end_line = r, ln.num
                    break
            if len(blocks) > self.max_blocks:
                raise GcodeError(f"more than {self.max_blocks} blocks (endless loop?)", ln.num, 1, "runaway")
            pc += 1
        else:
            if self.frames:
                fr = self.frames[-1]
                raise GcodeError(f"program ended inside subroutine o{fr.label} called at line {fr.line}",
                                 n, 1, "flow")
        return Program(name=self.name, blocks=blocks, line_count=len(self.lines), lines_executed=executed,
                       messages=self.messages, end_line=end_line, end_reason=end_reason,
                       final_pose=np.array(self.pos), units="mm" if self.u == 1.0 else "inch")

    def _comments(self, ln: Line) -> None:
        for c in ln.comments:
            m = _MSG.match(c)
            if m:
                text = c[m.end():].strip()
                if m.group(1).lower() != "msg":
                    text = _SUBST.sub(self._subst, text)
                self.messages.append((ln.num, text))

    def _subst(self, m) -> str:
        try:
            if m.group(1):
                v = self.P[int(m.group(1))]
            else:
                name = m.group(2).lower().replace(" ", "")
                v = self._sys(name) if name in _PRED else (self.G if name[0] == "_" else self.L)[name]
            return f"{v:.6f}"
        except (KeyError, IndexError, ValueError):
            return "######"

    # -- the fast path: constant-free of G/M, modal G0/G1 ---------------------------
    def _plain(self, ln: Line) -> None:
        """Modal G0/G1 line with only axis and F words (the bulk of CAM output)."""
        vals = ln.words
        fn = ln.fn
        if fn is not None:
            try:
                res = fn(self.P, self.L, self.G, self._sysfn, ln.k)
            except (KeyError, ArithmeticError, ValueError, ExprError, IndexError, TypeError) as exc:
                raise self._expr_error(ln, exc) from None
            for key, v in zip(ln.dyn, res):
                if not -1e300 < v < 1e300:
                    raise ln.error(f"value {v!r} is not a finite number", key, "expression")
                vals[key] = v
        self.line_now = ln.num
        f = vals.get("f")
        if f is not None:
            if f < 0.0:
                raise ln.error(f"negative feed F{f:g}", "f", "feed")
            self.feed = f
        axes = ln.axes
        if not axes:
            return
        pos = self.pos
        end = pos[:]
        sc = self.scale
        if self.absolute:
            off = self.off
            for i, letter in axes:
                end[i] = vals[letter] * sc[i] + off[i]
        else:
            for i, letter in axes:
                end[i] = pos[i] + vals[letter] * sc[i]
        if end == pos:
            return
        start = self.pos_arr
        if start is None:
            start = self._start_arr()
        e = np.array(end)
        e.flags.writeable = False
        if self.motion == 0:
            b = Block(_RAPID, ln.num, start, e, None, None, None, None, 0, False, self.exact_stop, self.blend,
                      self.tool_len, 0.0, 0.0, "off", self.tool)
        else:
            if self.inverse_time:
                fm, inv = self._feed_of(ln, vals, 10)
            else:
                fm, inv = self.feed * self.u / 60.0, None
                if fm <= 0.0:
                    self._feed_of(ln, vals, 10)  # raises the zero-feed error
            b = Block(_LINE, ln.num, start, e, fm, inv, None, None, 0, False, self.exact_stop, self.blend,
                      self.tool_len, 0.0, 0.0, "off", self.tool)
            if inv is None and end[0] == pos[0] and end[1] == pos[1] and end[2] == pos[2]:
                b.feed_deg_s = b.feed_mm_s = self.feed / 60.0  # rotary-only: F is deg/min
        self.blocks.append(b)
        self.pos = end
        self.pos_arr = e

    def _set_feed(self, ln: Line, f: float) -> None:
        if f < 0.0:
            raise ln.error(f"negative feed F{f:g}", "f", "feed")
        self.feed = f

    # -- the general line -------------------------------------------------------------
    def _execute(self, ln: Line):
        vals = self._eval(ln)
        self.line_now = ln.num
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
        # -- validate codes and modal groups
        groups: dict[int, int] = {}
        for g in gs:
            grp = _G_GROUP.get(g)
            if grp is None:
                what = _G_UNSUPPORTED.get(g, f"G{g / 10:g}")
                raise ln.error(f"{what} is not supported", f"g{g}", "unsupported")
            if grp in groups:
                raise ln.error(f"G{g / 10:g} and G{groups[grp] / 10:g} are in the same modal group "
                               f"(group {grp})", f"g{g}", "modal")
            groups[grp] = g
        mgroups: dict[int, int] = {}
        for m in ms:
            grp = _M_GROUP.get(m)
            if grp is None and m in self.noop_m:
                self.messages.append((ln.num, f"M{m} ignored: a no-op here ([planner] noop_m_codes)"))
                continue
            if grp is None:
                what = _M_UNSUPPORTED.get(m, f"M{m}")
                if 100 <= m <= 199:
                    what = f"M{m} user-defined M-code"
                elif m >= 200:
                    what = f"M{m} (user M-code or remap, undefined here)"
                raise ln.error(f"{what} is not supported", f"m{m}", "unsupported")
            if grp in mgroups and mgroups[grp] != m and not (grp == 8 and {m, mgroups[grp]} == {7, 8}):
                raise ln.error(f"M{m} and M{mgroups[grp]} are in the same modal group", f"m{m}", "modal")
            mgroups[grp] = m
        if len(ms) > 4:
            raise ln.error("more than four M words on one line", f"m{ms[4]}", "modal")
        gset = set(gs)
        # -- word usage
        g0 = groups.get(0)
        motion_g = groups.get(1)
        axis_user = g0 if g0 in (100, 920, 280, 300) else None
        if g0 in (281, 301) and ln.axes:
            raise ln.error(f"G{g0 / 10:g} takes no axis words", ln.axes[0][1], "word")
        if axis_user is not None and motion_g is not None and motion_g != 800:
            raise ln.error(f"G{g0 / 10:g} and G{motion_g // 10} both use the axis words", f"g{motion_g}",
                           "modal")
        motion = motion_g if motion_g is not None else self.motion
        if ln.axes and axis_user is None and motion == 800:
            raise ln.error("axis words without a motion mode (G0/G1/G2/G3)" if motion_g is None
                           else "axis words with G80", ln.axes[0][1], "word")
        do_move = axis_user is None and motion != 800 and (bool(ln.axes) or motion_g in (20, 30))
        arc = do_move and motion in (20, 30)
        for letter, users in (("i", arc), ("j", arc), ("k", arc), ("r", arc or g0 == 100),
                              ("p", arc or g0 in (40, 100) or 640 in gset),
                              ("q", 640 in gset), ("h", 430 in gset), ("l", g0 == 100)):
            if letter in vals and not users:
                raise ln.error(f"{letter.upper()} word with no G code that uses it", letter, "word")
        # -- assignments (all values were read before any is set)
        if ln.assigns:
            for kind, target, key in ln.assigns:
                v = vals[key]
                if kind == "n":
                    self.P[target] = v
                elif kind == "i":
                    self.P[int(vals[ln.dyn[target]])] = v
                elif kind == "l":
                    self.L[target] = v
                else:
                    self.G[target] = v
        if ln.comments:
            self._comments(ln)
        # -- units first, so that F, G64 P and axis words of this line are read in the new units
        if 200 in gset or 210 in gset:
            new_u = 25.4 if 200 in gset else 1.0
            if new_u != self.u:
                self.feed = self.feed * self.u / new_u   # keep the physical feed of an earlier F
                self.u = new_u
                self.scale = [new_u] * 3 + [1.0] * 3
        u = self.u
        # -- feed mode and F
        if 930 in gset or 940 in gset:
            inv = 930 in gset
            if inv != self.inverse_time:
                self.feed = 0.0   # an F of the other mode means something else: a new F is required
            self.inverse_time = inv
        if "f" in vals:
            self._set_feed(ln, vals["f"])
        # -- S, T, M6, spindle, coolant
        spindle_changed = False
        if "s" in vals:
            s = vals["s"]
            if s < 0.0:
                raise ln.error(f"negative spindle speed S{s:g}", "s", "value")
            if s != self.rpm:
                spindle_changed = self.spindle_dir != 0
            self.rpm = s
        if "t" in vals:
            t = vals["t"]
            if t < 0 or t != int(t):
                raise ln.error(f"tool number T{t:g} must be a non-negative integer", "t", "tool")
            t = int(t)
            if self.tools is not None and t != 0 and t not in self.tools:
                raise ln.error(f"tool T{t} is not in the tool table", "t", "tool")
            self.selected = t
        if 6 in mgroups.values():
            self.tool = self.selected
            self._emit(Block(B.TOOL_CHANGE, ln.num, tool=self.tool, tool_length_mm=self.tool_len))
        sp = mgroups.get(7)
        if sp is not None:
            self.spindle_dir = {3: 1, 4: -1, 5: 0}[sp]
            spindle_changed = True
        if spindle_changed:
            self._emit(Block(B.SPINDLE, ln.num, spindle_rpm=self.rpm * self.spindle_dir))
        if 8 in mgroups:
            for m in ms:
                if m in (7, 8, 9):
                    if m == 9:
                        self.mist = self.flood = False
                    elif m == 7:
                        self.mist = True
                    else:
                        self.flood = True
                    self._emit(Block(B.COOLANT, ln.num, coolant={7: "mist", 8: "flood", 9: "off"}[m]))
        # -- dwell
        if g0 == 40:
            if "p" not in vals:
                raise ln.error("G4 dwell needs a P word (seconds)", "g40", "word")
            p = vals["p"]
            if p < 0:
                raise ln.error(f"negative dwell time P{p:g}", "p", "value")
            self._emit(Block(B.DWELL, ln.num, seconds=p, exact_stop=True))
        # -- plane, units
        for g in (170, 180, 190):
            if g in gset:
                self.plane = g
        # -- tool length
        if 430 in gset:
            if "h" in vals:
                h = vals["h"]
                if h < 0 or h != int(h):
                    raise ln.error(f"H{h:g} must be a non-negative integer", "h", "tool")
                h = int(h)
            else:
                h = self.tool
            if h == 0:
                new_len = 0.0
            elif self.tools is None or h not in self.tools:
                raise ln.error(f"G43 H{h}: tool {h} has no length in the tool table", "h" if "h" in vals else "g430",
                               "tool")
            else:
                new_len = self.tools[h]
            self._set_tool_length(new_len)
        elif 490 in gset:
            self._set_tool_length(0.0)
        # -- coordinate system
        cs = groups.get(12)
        if cs is not None:
            self.cs = {540: 1, 550: 2, 560: 3, 570: 4, 580: 5, 590: 6, 591: 7, 592: 8, 593: 9}[cs]
            self.P[5220] = float(self.cs)
            self._refresh_offsets()
        # -- path control
        pc_ = groups.get(13)
        if pc_ is not None:
            if pc_ == 640:
                self.exact_stop = False
                if "p" in vals:
                    p = vals["p"]
                    if p < 0:
                        raise ln.error(f"negative blending tolerance P{p:g}", "p", "value")
                    self.blend = p * u if p > 0 else None
                else:
                    self.blend = None
                if "q" in vals and vals["q"] < 0:
                    raise ln.error("negative G64 Q tolerance", "q", "value")
            else:
                self.exact_stop = True
                self.blend = None
        # -- distance modes
        if 900 in gset:
            self.absolute = True
        elif 910 in gset:
            self.absolute = False
        if 901 in gset:
            self.arc_absolute = True
        elif 911 in gset:
            self.arc_absolute = False
        # -- G10 / G92
        if g0 == 100:
            self._g10(ln, vals)
        elif g0 in (920, 921, 922, 923):
            self._g92(ln, vals, g0)
        elif g0 in (280, 300):
            self._g28(ln, vals, 5161 if g0 == 280 else 5181)
        elif g0 in (281, 301):
            base = 5161 if g0 == 281 else 5181
            for i in range(6):
                self.P[base + i] = self.pos[i]
        # -- motion
        if motion_g is not None:
            self.motion = motion_g
        if do_move:
            g53 = g0 == 530
            if g53:
                if motion not in (0, 10):
                    raise ln.error("G53 needs G0 or G1 motion", "g530", "modal")
                if not self.absolute:
                    raise ln.error("G53 cannot be used in incremental mode G91", "g530", "modal")
            if motion in (20, 30):
                if not ln.axes:
                    raise ln.error("arc with all axis words missing", f"g{motion}", "word")
                self._arc(ln, vals, motion)
            else:
                self._move(ln, vals, motion, g53)
        elif g0 == 530:
            raise ln.error("G53 without a G0/G1 move on the line", "g530", "word")
        # -- stops
        stop = mgroups.get(4)
        if stop is not None:
            if stop == 0:
                self._emit(Block(B.PAUSE, ln.num, exact_stop=True))
            elif stop == 1:
                self._emit(Block(B.OPTIONAL_PAUSE, ln.num, exact_stop=True))
            else:
                self._emit(Block(B.END, ln.num, exact_stop=True))
                return "M2" if stop == 2 else "M30"
        return None

    def _emit(self, b: Block) -> None:
        self.blocks.append(b)

def parse_program(text: str, name: str = "<program>", *, start_pose=None, work_offsets=None,
                  tool_table=None, units_default: str = "mm", tool_axis_platform=(0.0, 0.0, 1.0),
                  block_delete: bool = True, max_lines: int = 20_000_000, g28_pose=None,
                  g30_pose=None, noop_m_codes=()) -> Program:
    """Interpret a whole RS274NGC program.

    ``start_pose``: (6,) tool-tip pose in the machine frame at the start (mm, deg;
    default zeros).  ``work_offsets``: {"G54".."G59.3" or 1..9: 3 or 6 numbers}
    (mm, deg; unset systems are zero).  ``tool_table``: {tool number: length mm};
    with a table, T words must name a listed tool; without one, any T is
    accepted but G43 needs a length.  ``tool_axis_platform``: unit tool axis in
    the platform frame (G43 shifts the controlled point along it).
    ``block_delete``: skip lines starting with '/'.  ``g28_pose``/``g30_pose``:
    the stored G28/G30 positions (#5161.., #5181..; machine tool-tip poses, mm
    and deg; default zeros as in LinuxCNC).  ``noop_m_codes``: user/remap M-codes (100..9999) accepted
    as no-ops, each occurrence noted in ``Program.messages``.  Raises GcodeError.
    """
    it = Interpreter(text, name, start_pose=start_pose, work_offsets=work_offsets,
                     tool_table=tool_table, units_default=units_default,
                     tool_axis_platform=tool_axis_platform, block_delete=block_delete,
                     max_lines=max_lines, g28_pose=g28_pose, g30_pose=g30_pose, noop_m_codes=noop_m_codes)
    # the interpreter builds no reference cycles: keep the cyclic collector out of the loop
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        return it.run(text)
    finally:
        if was_enabled:
            gc.enable()
