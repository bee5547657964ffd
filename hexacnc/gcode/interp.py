"""RS274NGC interpreter (LinuxCNC dialect) -> motion blocks.

The whole program is interpreted before anything moves: the result is a
:class:`Program` whose blocks carry tool-tip poses in the machine (base) frame,
mm and degrees, with work offsets, G92, G53 and the G43 tool length applied.
Anything the dialect does not support raises :class:`GcodeError` with the
line, the column and a code, never a silent skip.

Error codes: ``syntax``, ``unsupported``, ``word`` (missing, repeated or
unused word), ``modal`` (two codes of one modal group), ``parameter``,
``expression``, ``arc``, ``feed``, ``value``, ``tool``, ``flow`` (O-words,
subroutine files), ``runaway`` (execution limit), ``abort`` (``(ABORT,...)``),
``end`` (no M2/M30/% with ``require_end``), ``cycle`` (canned cycles), ``comp``
(cutter compensation gouging and conflicts).

Tool length: the controlled point is the tool tip, at ``tool_length_mm``
along the platform tool axis from the tool reference point.  G43/G49 do not
move the platform, so the programmed tool-tip position jumps by
``R(a,b,c) @ axis_platform * (new - old length)``; the next block starts there.

Modules: :mod:`.expr` (expressions), :mod:`.lexer` (lines and shapes),
:mod:`.flow` (O-words), :mod:`.motion` (offsets, tool length, lines, arcs),
:mod:`.params` (system parameters, comments), :mod:`.execute` (one general
line in LinuxCNC's order of execution), :mod:`.tooling` (G10, G43, tool
table), :mod:`.cycles` (canned cycles), :mod:`.iocmds` (probe, I/O, M70-M73),
:mod:`.subfiles` (subroutine files), :mod:`.comp` (cutter compensation), :mod:`.splines`
(G5/G5.1), :mod:`.stream`
(``iter_blocks``), :mod:`.state` (parameters and tool table), this one (state and the run loop).
"""
from __future__ import annotations

import gc
import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import GcodeError
from . import blocks as B
from .blocks import Block, frozen_pose
from .comp import CompMixin
from .cycles import CycleMixin
from .execute import ExecuteMixin
from .expr import MAX_PARAMETER, READONLY_PARAMETERS, SYSTEM_PARAMETERS, ExprError
from .flow import FlowMixin, _Frame
from .iocmds import IoMixin
from .lexer import Line, Presplit, parse_line
from .motion import _LINE, _RAPID, MotionMixin
from .params import ParamMixin
from .state import MachineState, ToolEntry, tool_entries
from .splines import SplineMixin
from .subfiles import SubfileMixin
from .tooling import ToolingMixin


@dataclass
class Program:
    """An interpreted program: the planner's input."""
    name: str
    blocks: list[Block]
    line_count: int                           #: source lines
    lines_executed: int = 0                   #: lines interpreted (loops counted each time)
    messages: list[tuple[int, str]] = field(default_factory=list)  #: (line, text) of MSG/DEBUG (and notes)
    end_line: int | None = None               #: line of M2/M30/% ending the program
    end_reason: str = "eof"                   #: "M2", "M30", "percent" or "eof"
    final_pose: np.ndarray | None = None      #: (6,) tool tip at the end, machine frame
    units: str = "mm"                         #: units mode at the end
    #: (kind, line, text) of every MSG/DEBUG/PRINT comment, kind in {"msg", "debug", "print"}
    notes: list[tuple[str, int, str]] = field(default_factory=list)
    final_state: MachineState | None = None   #: parameters and tool table after the program

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


def _six(v, what: str) -> list[float]:
    out = [float(x) for x in v]
    if len(out) == 3:
        out += [0.0, 0.0, 0.0]
    if len(out) != 6 or not all(math.isfinite(x) for x in out):
        raise GcodeError(f"{what} must be 3 or 6 finite numbers, got {v!r}", None, None, "value")
    return out


class Interpreter(FlowMixin, MotionMixin, ParamMixin, ExecuteMixin, ToolingMixin, CycleMixin, IoMixin,
                  SubfileMixin, CompMixin, SplineMixin):
    """Interpret one program text; :meth:`run` returns the :class:`Program`."""

    system_numbers = SYSTEM_PARAMETERS
    readonly_numbers = READONLY_PARAMETERS

    def __init__(self, text, name: str = "<program>", *, start_pose=None, work_offsets=None,
                 tool_table=None, units_default: str = "mm", tool_axis_platform=(0.0, 0.0, 1.0),
                 block_delete: bool = True, max_lines: int = 20_000_000,
                 max_blocks: int = 20_000_000, max_call_depth: int = 64, g28_pose=None, g30_pose=None,
                 noop_m_codes=(), initial_state: MachineState | None = None, subroutine_path=(),
                 require_end: bool = False, lines=None, fanuc_subs: bool = True,
                 machine_units: str = "mm"):
        if lines is None:
            if not isinstance(text, str):
                raise GcodeError(f"program text must be str, got {type(text).__name__}", None, None, "syntax")
            lines = text.split("\n")
            if lines and lines[-1] == "":
                lines.pop()
        self.name = name
        self.lines = lines
        self.main_n = len(lines)
        self.parsed = [None] * len(lines) if isinstance(lines, list) else {}
        if units_default not in ("mm", "inch"):
            raise GcodeError(f"units_default must be 'mm' or 'inch', got {units_default!r}",
                             None, None, "value")
        self.u = 25.4 if units_default == "inch" else 1.0
        if machine_units not in ("mm", "inch"):
            raise GcodeError(f"machine_units must be 'mm' or 'inch', got {machine_units!r}", None, None, "value")
        self.mu = 25.4 if machine_units == "inch" else 1.0   # unit of stored lengths as a program sees them
        self.scale = [self.u] * 3 + [1.0] * 3
        self.pos = [0.0] * 6 if start_pose is None else _six(start_pose, "start_pose")
        if start_pose is not None and len(list(start_pose)) != 6:
            raise GcodeError(f"start_pose must be 6 finite numbers, got {start_pose!r}", None, None, "value")
        self.pos_arr = None
        ax = [float(v) for v in tool_axis_platform]
        n = math.sqrt(sum(v * v for v in ax))
        if len(ax) != 3 or not n > 0:
            raise GcodeError(f"tool_axis_platform must be a non-zero 3-vector, got {tool_axis_platform!r}",
                             None, None, "value")
        self.tool_axis = [v / n for v in ax]
        self.block_delete = bool(block_delete)
        self._init_noop(noop_m_codes)
        self.max_lines = int(max_lines)
        self.max_blocks = int(max_blocks)
        self.max_depth = int(max_call_depth)
        self.require_end = bool(require_end)
        self.fanuc_subs = bool(fanuc_subs)
        self.sub_path = [str(p) for p in subroutine_path]
        self.segments: list[tuple[int, str]] = []   #: (first line index, file) of loaded subroutine files
        self.P = [0.0] * (MAX_PARAMETER + 1)
        self.comp_side = None          # cutter compensation: "L", "R" or None
        self.comp_q = None
        self.comp_first = True
        self.comp_arc_not_allowed = False
        self.diameter = False          # G7 lathe diameter mode: X words are diameters
        self.G: dict[str, float] = {}
        self.L: dict[str, float] = {}
        self._init_state(initial_state, tool_table, work_offsets, g28_pose, g30_pose)
        self._init_modes()

    def _init_noop(self, noop_m_codes) -> None:
        from .codes import M_GROUP
        noop = [int(m) for m in noop_m_codes]
        bad = [m for m in noop if not 100 <= m <= 9999 or m in M_GROUP]
        if bad:
            raise GcodeError(f"noop_m_codes {bad}: only user and remap M-codes (100..9999) can be no-ops",
                             None, None, "value")
        self.noop_m: frozenset = frozenset(noop)

    def _init_state(self, state, tool_table, work_offsets, g28_pose, g30_pose) -> None:
        P = self.P
        self.tools: dict[int, ToolEntry] | None = None
        self.tool = 0
        self.tool_len = 0.0
        if state is not None:
            for k, v in state.parameters.items():
                k = int(k)
                if not 1 <= k <= MAX_PARAMETER or not math.isfinite(float(v)):
                    raise GcodeError(f"initial parameter #{k} = {v!r} is invalid", None, None, "parameter")
                P[k] = float(v)
            self.tools = {t: ToolEntry(**vars(e)) for t, e in tool_entries(state.tools).items()}
            self.tool = int(state.current_tool)
        if tool_table is not None:
            self.tools = tool_entries(tool_table)
        self.tools_given = self.tools is not None     # without a table any T is accepted
        if self.tools is None:
            self.tools = {}
        if work_offsets is not None:
            items = work_offsets.items() if hasattr(work_offsets, "items") else enumerate(work_offsets, 1)
            for key, vec in items:
                k = _coord_index(key)
                P[5201 + 20 * k:5207 + 20 * k] = _six(vec, f"work offset {key!r}")
        for base, stored in ((5161, g28_pose), (5181, g30_pose)):
            if stored is not None:
                v = [float(x) for x in stored]
                if len(v) != 6 or not all(math.isfinite(x) for x in v):
                    raise GcodeError(f"G28/G30 position must be 6 finite numbers, got {stored!r}", None, None,
                                     "value")
                P[base:base + 6] = v
        cs = int(P[5220]) if 1 <= P[5220] <= 9 and P[5220] == int(P[5220]) else 1
        self.cs = cs
        P[5220] = float(cs)
        self.g92 = [P[5211 + i] for i in range(6)] if P[5210] else [0.0] * 6
        self._refresh_offsets()

    def _init_modes(self) -> None:
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
        self.selected = self.tool
        self.exact_stop = False
        self.blend = None
        self.retract_r = False     # G98 (old Z) by default
        self.g5_pq = None          # P, Q of the last G5 of a series (mm): the next may omit I, J
        self.cycle = {"il": None, "r": 0.0, "cc": 0.0, "p": 0.0, "q": 0.0}
        self.blocks: list[Block] = []
        self.messages: list[tuple[int, str]] = []
        self.notes: list[tuple[str, int, str]] = []
        self.frames: list[_Frame] = []
        self.seek = False
        self.line_now = 0
        self.ret_value = 0.0
        self.ret_flag = 0.0
        self.runtime_pending: set[int] = set()
        self.saved_modal: dict[int, dict] = {}
        self._top_repeat: dict[int, int] = {}
        self._sysfn = self._sys

    # -- parsing and structure ------------------------------------------------
    def _line(self, idx: int) -> Line:
        ln = self.parsed[idx] if isinstance(self.parsed, list) else self.parsed.get(idx)
        if ln is None:
            ln = parse_line(self.lines[idx], self._num(idx))
            self.parsed[idx] = ln
        return ln

    def _num(self, idx: int) -> int:
        """1-based line number of index ``idx`` in its own file."""
        if idx < self.main_n:
            return idx + 1
        start = max(s for s, _f in self.segments if s <= idx)
        return idx - start + 1

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

    # -- running ----------------------------------------------------------------
    def run(self, text=None) -> Program:
        self.percent_start = None
        self.stop_at = self._find_end()
        if text is None:
            text = "\n".join(self.lines)
        presplit = Presplit(text, self.lines)
        self._prescan(text, presplit)
        blocks = self.blocks
        end_reason, end_line, executed = self._loop(presplit.line, None)
        return Program(name=self.name, blocks=blocks, line_count=self.main_n, lines_executed=executed,
                       messages=self.messages, end_line=end_line, end_reason=end_reason,
                       final_pose=np.array(self.pos), units="mm" if self.u == 1.0 else "inch",
                       notes=self.notes, final_state=self.final_state())

    def _loop(self, pre, flush):
        """The run loop; ``flush(blocks)`` (streaming) is called when blocks pile up."""
        end_reason, end_line = "eof", None
        n = self.main_n if self.stop_at is None else self.stop_at
        if self.stop_at is not None:
            end_reason, end_line = "percent", self.stop_at + 1
        pc = 0 if self.percent_start is None else self.percent_start + 1
        executed = 0
        max_lines = self.max_lines
        parsed = self.parsed
        blocks = self.blocks
        main_n = self.main_n
        lines = self.lines
        try:
            while pc < n or main_n <= pc < len(lines):     # (second: inside a subroutine file)
                ln = parsed[pc]
                if ln is None:
                    ln = pre(pc) if pc < main_n else self._line(pc)
                    parsed[pc] = ln
                executed += 1
                if executed > max_lines:
                    raise GcodeError(f"more than {max_lines} lines executed (endless loop?)", ln.num, 1,
                                     "runaway")
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
                if ln.plain and self.motion in (0, 10) and not self.slow:
                    if ln.comments:
                        self._comments(ln)
                    self._plain(ln)
                elif ln.gmot is not None and not self.slow:
                    if ln.comments:
                        self._comments(ln)
                    self.motion = ln.gmot
                    self._plain(ln)
                elif ln.arcok and ln.axes and self.motion in (20, 30):
                    if ln.comments:
                        self._comments(ln)
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
                if len(blocks) > 4096:
                    if flush is not None:
                        flush(blocks)
                        blocks.clear()
                    elif len(blocks) > self.max_blocks:
                        raise GcodeError(f"more than {self.max_blocks} blocks (endless loop?)", ln.num, 1,
                                         "runaway")
                pc += 1
            else:
                if self.frames:
                    fr = self.frames[-1]
                    raise GcodeError(f"program ended inside subroutine o{fr.label} called at line {fr.line}",
                                     n, 1, "flow")
                if self.comp_q:
                    self._comp_flush()
                if self.require_end and end_reason == "eof":
                    raise GcodeError("file ended with no percent sign (%) or program end (M2/M30)",
                                     max(n, 1), 1, "end")
        except GcodeError as exc:
            raise self._in_file(exc, pc) from None
        if flush is not None:
            flush(blocks)
            blocks.clear()
        return end_reason, end_line, executed

    def final_state(self) -> MachineState:
        """Parameters and tool table now (after :meth:`run`: the program's final state)."""
        params = {k: self.P[k] for k in range(1, MAX_PARAMETER + 1)
                  if self.P[k] != 0.0 and k not in READONLY_PARAMETERS}
        from .state import PERSISTENT
        for k in PERSISTENT:
            params[k] = self.P[k]
        tools = {t: ToolEntry(**vars(e)) for t, e in (self.tools or {}).items()}
        return MachineState(parameters=params, tools=tools, current_tool=self.tool,
                            tool_length_mm=self.tool_len)

    # -- the fast path: constant-free of G/M, modal G0/G1 ---------------------------
    def _plain(self, ln: Line) -> None:
        """Modal G0/G1 line with only axis and F words (the bulk of CAM output)."""
        vals = ln.words
        fn = ln.fn
        if fn is not None:
            try:
                res = fn(self.P, self.L, self.G, self._sysfn, ln.k)
            except (KeyError, ArithmeticError, ValueError, ExprError, IndexError, TypeError, GcodeError) as exc:
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
        e = frozen_pose(end)
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

    def _emit(self, b: Block) -> None:
        if self.comp_q:      # behind the compensated moves still waiting for their corner
            self.comp_q.append(["block", b])
        else:
            self.blocks.append(b)


def parse_program(text: str, name: str = "<program>", *, start_pose=None, work_offsets=None,
                  tool_table=None, units_default: str = "mm", tool_axis_platform=(0.0, 0.0, 1.0),
                  block_delete: bool = True, max_lines: int = 20_000_000, g28_pose=None,
                  g30_pose=None, noop_m_codes=(), initial_state: MachineState | None = None,
                  subroutine_path=(), require_end: bool = False, fanuc_subs: bool = True,
                  machine_units: str = "mm") -> Program:
    """Interpret a whole RS274NGC program.

    ``start_pose``: (6,) tool-tip pose in the machine frame at the start (mm, deg;
    default zeros).  ``initial_state``: a :class:`~hexacnc.gcode.state.MachineState`
    (numbered parameters incl. work offsets, G28/G30, G92 and #5220; tool table;
    current tool); ``Program.final_state`` is the state afterwards.
    ``work_offsets``: {"G54".."G59.3" or 1..9: 3 or 6 numbers} (mm, deg; override
    the state's).  ``tool_table``: {T: ToolEntry} or {T: length mm} (overrides the
    state's); with a table, T words must name a listed tool; without one, any T is
    accepted but G43 needs a length.  ``tool_axis_platform``: unit tool axis in
    the platform frame (G43 shifts the controlled point along it).
    ``block_delete``: skip lines starting with '/'.  ``g28_pose``/``g30_pose``:
    the stored G28/G30 positions (#5161.., #5181..; machine poses of the tool
    reference point, mm and deg).  ``noop_m_codes``: user/remap M-codes (100..9999)
    accepted as no-ops, each occurrence noted in ``Program.messages``.
    ``subroutine_path``: directories searched for ``<name>.ngc`` on ``o<name> call``.
    ``require_end``: refuse a program that runs off its end without M2/M30/% (LinuxCNC).
    ``fanuc_subs``: Fanuc-style subprograms (M98 P L, M99, bare O-numbers); False refuses
    them as LinuxCNC's ``DISABLE_FANUC_STYLE_SUB``.  ``machine_units``: the unit in which a
    program reads and sets stored lengths (#5161.., #5181.., #5211.., work offsets #5221..: LinuxCNC's
    INI units; "mm" for a hexacnc machine, "inch" as LinuxCNC's standalone rs274); the
    ``initial_state`` and ``final_state`` keep them in mm.
    Raises GcodeError.
    """
    it = Interpreter(text, name, start_pose=start_pose, work_offsets=work_offsets,
                     tool_table=tool_table, units_default=units_default,
                     tool_axis_platform=tool_axis_platform, block_delete=block_delete,
                     max_lines=max_lines, g28_pose=g28_pose, g30_pose=g30_pose, noop_m_codes=noop_m_codes,
                     initial_state=initial_state, subroutine_path=subroutine_path, require_end=require_end,
                     fanuc_subs=fanuc_subs, machine_units=machine_units)
    # the interpreter builds no reference cycles: keep the cyclic collector out of the loop
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        return it.run(text)
    finally:
        if was_enabled:
            gc.enable()
