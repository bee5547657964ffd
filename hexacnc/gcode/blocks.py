"""Motion blocks: the interpreter's output and the planner's input.

Poses are tool-tip poses ``[x, y, z, a, b, c]`` in the machine (base) frame,
mm and degrees, with work offsets, G53 and G43 tool length already applied.
The tool length is a distance along the platform's tool axis; the planner
converts tool-tip poses to platform poses with it.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

_PACK6 = struct.Struct("6d").pack
_FROMBUFFER = np.frombuffer


def frozen_pose(pose) -> np.ndarray:
    """A read-only (6,) float array of a 6-sequence (the cheapest way numpy makes one)."""
    return _FROMBUFFER(_PACK6(*pose))

#: block kinds
RAPID = "rapid"            #: G0
LINE = "line"              #: G1
ARC = "arc"                #: G2/G3 (helical allowed)
DWELL = "dwell"            #: G4, ``seconds``
PAUSE = "pause"            #: M0
OPTIONAL_PAUSE = "optional_pause"  #: M1
END = "end"                #: M2/M30
SPINDLE = "spindle"        #: M3/M4/M5/S: ``spindle_rpm`` (signed: M4 negative, M5 zero)
COOLANT = "coolant"        #: M7/M8/M9: ``coolant`` in {"mist", "flood", "off"}
TOOL_CHANGE = "tool_change"  #: M6: ``tool``
#: G38.2-G38.5 straight probe from ``start`` toward ``end`` at ``feed_mm_s``; ``extra``: see docs/gcode.md
PROBE = "probe"
#: M62-M68 output / M66 input wait; ``extra``: see docs/gcode.md
IO = "io"

MOTION_KINDS = (RAPID, LINE, ARC)


def holds_still(blk) -> bool:
    """A block that takes time standing still: a G4 of more than 0 s, M0 or M1 (it needs a plan even in a
    program without motion)."""
    k = blk.kind
    return k == PAUSE or k == OPTIONAL_PAUSE or (k == DWELL and (blk.seconds or 0.0) > 0.0)


@dataclass
class Block:
    kind: str
    line: int                                  #: 1-based source line
    start: np.ndarray | None = None            #: (6,) tool-tip pose at block start
    end: np.ndarray | None = None              #: (6,) tool-tip pose at block end
    feed_mm_s: float | None = None             #: path feed (G94); None for rapids
    inverse_time_s: float | None = None        #: G93: the move takes this long
    center: np.ndarray | None = None           #: arcs: (3,) centre, machine frame
    normal: np.ndarray | None = None           #: arcs: (3,) unit normal, counter-clockwise positive
    turns: int = 0                             #: arcs: extra full turns (P word)
    clockwise: bool = False                    #: arcs: G2
    exact_stop: bool = False                   #: G61 active
    blend_tolerance_mm: float | None = None    #: G64 P (None: as fast as possible)
    tool_length_mm: float = 0.0                #: G43 offset along the tool axis
    seconds: float = 0.0                       #: dwell
    spindle_rpm: float = 0.0
    coolant: str = "off"
    tool: int = 0
    extra: dict = field(default_factory=dict)
    #: G94 moves with no X/Y/Z change: F is deg/min (LinuxCNC), given here in deg/s;
    #: ``feed_mm_s`` then holds the same number (the path parameter is degrees)
    feed_deg_s: float | None = None
