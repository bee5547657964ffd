"""The setpoint contract between whatever produces motion and the hot loop.

Producers (the planner's :class:`~hexacnc.planner.sampler.PlanSampler` behind a program, the
daemon's point-to-point moves, MDI and jog) and the consumer (the hot loop reading the shared
ring) agree on this module only.

A **row** is one cycle period: ``float64[ROW]`` =
``[x, y, z, a, b, c, line, flags]`` — the **platform** pose in the base frame (mm and
**radians**; the tool offset already applied), the 1-based source line it belongs to (0: none)
and an integer bit set of ``FLAG_*`` stored as a float.

A stream of rows ends with one row whose flags carry :data:`FLAG_END`; that row is at rest, and an
empty ring after it is normal (not a dead source).
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

#: floats per row
ROW = 8
#: column of x (x, y, z, a, b, c follow in order)
COL_X = 0
#: columns of the platform pose (mm, rad)
COL_POSE = slice(0, 6)
#: columns of the position (mm) and of the orientation (rad)
COL_XYZ = slice(0, 3)
COL_ABC = slice(3, 6)
#: column of the source line
COL_LINE = 6
#: column of the flag bits
COL_FLAGS = 7

FLAG_MOTION = 1            #: the row moves along a programmed path
FLAG_RAPID = 2             #: ... on a rapid (G0)
FLAG_DWELL = 4             #: a dwell (G4) holds the pose
FLAG_PROGRAM_PAUSE = 8     #: a program pause (M0, M1 with optional stop) starts here
FLAG_PAUSED = 16           #: standing still in a feed hold
FLAG_STOPPING = 32         #: decelerating for a stop
FLAG_END = 64              #: last row of a stream, at rest
FLAG_EVENT = 128           #: a program event (spindle, coolant, tool change, message) happens here
#: program digital-output changes (M62-M65) happen here, packed above bit 16 of the flags
#: (hexacnc.daemon.dioloop: up to 3 changes of 10 bits each; the float stays an exact integer)
FLAG_IO = 256


def flags_of(row: np.ndarray) -> int:
    """The flag bits of one row."""
    return int(row[COL_FLAGS])


def is_end(row: np.ndarray) -> bool:
    """True for the row that ends a stream."""
    return bool(int(row[COL_FLAGS]) & FLAG_END)


def end_row(pose_rad, line: int = 0) -> np.ndarray:
    """A single at-rest row (1, ROW) at ``pose_rad`` (platform, mm/rad) that ends a stream."""
    out = np.zeros((1, ROW))
    out[0, COL_POSE] = pose_rad
    out[0, COL_LINE] = line
    out[0, COL_FLAGS] = FLAG_END
    return out


def mark_end(rows: np.ndarray) -> np.ndarray:
    """Set :data:`FLAG_END` on the last row of ``rows`` (N, ROW), in place; returns ``rows``."""
    if len(rows):
        rows[-1, COL_FLAGS] = float(int(rows[-1, COL_FLAGS]) | FLAG_END)
    return rows


class SetpointSource(Protocol):
    """What the daemon's feeder asks of a producer of rows (supervisor side, numpy allowed).

    ``next_rows`` fills ``count`` rows (or fewer at the end, the last with :data:`FLAG_END`).
    ``pause``/``resume``/``stop``/``set_feed_override`` act on rows not yet produced, along the path
    and jerk-limited. ``snapshot``/``restore`` let the feeder re-produce rows from an earlier
    state (a command takes effect ahead of the hot loop without waiting for the queue).
    ``progress`` returns ``(line, percent, seconds left)``.
    """

    def next_rows(self, count: int) -> np.ndarray: ...
    def pause(self) -> None: ...
    def resume(self) -> None: ...
    def stop(self) -> None: ...
    def set_feed_override(self, f: float) -> None: ...
    def snapshot(self) -> tuple: ...
    def restore(self, snap: tuple) -> None: ...
    def progress(self) -> tuple[int, float, float]: ...
