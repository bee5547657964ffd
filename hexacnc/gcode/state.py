"""Persistent interpreter state: numbered parameters and the tool table.

LinuxCNC keeps the work offsets, G28/G30 positions and G92 offsets in
numbered parameters (its ``.var`` file) and the tools in ``tool.tbl``; a
program starts from them and leaves them changed (G10, G92, G28.1 ...).
hexacnc does the same: :func:`~hexacnc.gcode.parse_program` takes
``initial_state`` (a :class:`MachineState`) and the resulting
``Program.final_state`` is the state after the program.

Units: parameters are in mm and degrees (hexacnc's machine units), whatever
G20/G21 a program uses; tool offsets and diameters are mm.

Persistent parameters (LinuxCNC numbers): #5161..#5169 G28 position,
#5181..#5189 G30 position, #5210 G92 enabled, #5211..#5219 G92 offsets,
#5220 selected coordinate system (1 = G54 .. 9 = G59.3), #5221..#5390 work
offsets G54..G59.3 (20 per system: X Y Z A B C U V W, then R rotation in
degrees at +9, e.g. #5230 for G54).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace

from ..errors import GcodeError

#: the persistent parameter numbers (LinuxCNC's .var file subset hexacnc keeps)
PERSISTENT = tuple(list(range(5161, 5170)) + list(range(5181, 5190)) + list(range(5210, 5221))
                   + [5221 + 20 * k + i for k in range(9) for i in range(10)])


@dataclass
class ToolEntry:
    """One tool (LinuxCNC ``tool.tbl`` fields; mm and degrees)."""
    tool: int                        #: T number
    pocket: int = 0                  #: P
    z_offset_mm: float = 0.0         #: Z: tool length along the tool axis (G43)
    diameter_mm: float = 0.0         #: D: cutter diameter (G41/G42 use half of it)
    comment: str = ""                #: text after ';'
    x_offset_mm: float = 0.0         #: X (kept and reported; a G43 with it non-zero is refused)
    y_offset_mm: float = 0.0         #: Y (same)
    front_angle_deg: float = 0.0     #: I (lathe; kept)
    back_angle_deg: float = 0.0      #: J (lathe; kept)
    orientation: int = 0             #: Q (lathe; kept)


@dataclass
class MachineState:
    """What a program starts from and leaves behind."""
    parameters: dict[int, float] = field(default_factory=dict)  #: numbered parameters (mm, deg)
    tools: dict[int, ToolEntry] = field(default_factory=dict)   #: tool table by T number
    current_tool: int = 0            #: tool in the spindle (M6 / M61)
    tool_length_mm: float = 0.0      #: G43 length in effect at the end (0 at a start)

    def persistent(self) -> dict[int, float]:
        """The parameters LinuxCNC writes to its .var file (work offsets, G28/G30, G92, #5220)."""
        return {k: v for k, v in self.parameters.items() if k in _PERSISTENT_SET}


_PERSISTENT_SET = frozenset(PERSISTENT)
_TBL_WORD = re.compile(r"([tpxyzabcuvwdijq])\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)", re.IGNORECASE)


def parse_tool_table(text: str, name: str = "tool.tbl", check=None) -> dict[int, ToolEntry]:
    """Read a LinuxCNC tool table (``T1 P1 Z0.5 D3 ;comment`` per line; mm).

    ``check(entry, line)``, when given, is called for each entry in file order (range checks and
    duplicate refusal of the operator's persistent table); it raises to refuse the line."""
    out: dict[int, ToolEntry] = {}
    for num, raw in enumerate(text.splitlines(), 1):
        body, _sep, comment = raw.partition(";")
        body = body.strip().rstrip("%")
        if not body:
            continue
        vals: dict[str, float] = {}
        pos = 0
        for m in _TBL_WORD.finditer(body):
            if body[pos:m.start()].strip():
                raise GcodeError(f"{name}: cannot read {body[pos:m.start()].strip()!r}", num, pos + 1, "tool")
            vals[m.group(1).lower()] = float(m.group(2))
            pos = m.end()
        if body[pos:].strip():
            raise GcodeError(f"{name}: cannot read {body[pos:].strip()!r}", num, pos + 1, "tool")
        if "t" not in vals:
            raise GcodeError(f"{name}: tool line without a T number", num, 1, "tool")
        t = vals["t"]
        if t != int(t) or t < 0 or not all(math.isfinite(v) for v in vals.values()):
            raise GcodeError(f"{name}: bad tool number T{t:g}", num, 1, "tool")
        out[int(t)] = ToolEntry(tool=int(t), pocket=int(vals.get("p", t)), z_offset_mm=vals.get("z", 0.0),
                                diameter_mm=vals.get("d", 0.0), comment=comment.strip().rstrip("%"),
                                x_offset_mm=vals.get("x", 0.0), y_offset_mm=vals.get("y", 0.0),
                                front_angle_deg=vals.get("i", 0.0), back_angle_deg=vals.get("j", 0.0),
                                orientation=int(vals.get("q", 0)))
        if check is not None:
            check(out[int(t)], num)
    return out


def format_tool_table(tools: dict[int, ToolEntry]) -> str:
    """The inverse of :func:`parse_tool_table`: one line per tool, sorted by T, ``T P Z D`` always
    (6 decimals: nm), LinuxCNC's X Y I J Q only where set, then the comment."""
    lines = []
    for t in sorted(tools):
        e = tools[t]
        s = f"T{e.tool} P{e.pocket}"
        for letter, v in (("X", e.x_offset_mm), ("Y", e.y_offset_mm)):
            if v:
                s += f" {letter}{v:.6f}"
        s += f" Z{e.z_offset_mm:.6f} D{e.diameter_mm:.6f}"
        for letter, v in (("I", e.front_angle_deg), ("J", e.back_angle_deg)):
            if v:
                s += f" {letter}{v:.6f}"
        if e.orientation:
            s += f" Q{e.orientation}"
        lines.append(s + (f" ;{e.comment}" if e.comment else ""))
    return "\n".join(lines) + ("\n" if lines else "")


def tool_entries(table) -> dict[int, ToolEntry] | None:
    """Accept ``{T: ToolEntry}`` or the older ``{T: length_mm}`` form (None stays None)."""
    if table is None:
        return None
    out: dict[int, ToolEntry] = {}
    for k, v in dict(table).items():
        try:
            t = int(k)
        except (TypeError, ValueError):
            raise GcodeError(f"tool table key {k!r} is not a tool number", None, None, "tool") from None
        if isinstance(v, ToolEntry):
            e = replace(v)
        else:
            try:
                e = ToolEntry(tool=t, pocket=t, z_offset_mm=float(v))
            except (TypeError, ValueError):
                raise GcodeError(f"tool table entry {k!r}: {v!r} is invalid", None, None, "tool") from None
        if t < 0 or not all(math.isfinite(x) for x in (e.z_offset_mm, e.diameter_mm, e.x_offset_mm,
                                                        e.y_offset_mm)):
            raise GcodeError(f"tool table entry {k!r}: {v!r} is invalid", None, None, "tool")
        out[t] = e
    return out
