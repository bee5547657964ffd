"""Nominal time of a block at its programmed feed, and the bound on it (``[planner] max_block_s``).

The plan holds a table row per cycle (0.5 ms) for the whole of a window, and a window ends only where the
motion may rest: one block of 16 h (``G1 X10 F0.01``, or ``G4 P100000``) made the planner allocate 17-24 GB.
Every block whose nominal time (a lower bound of its planned time) exceeds the bound is refused before any
table exists, naming its line; at the default 900 s a block's rows stay within ~1.8 million.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import PlanError
from ..gcode import blocks as B


def block_seconds(blk, rapid_mm_s: float, default_mm_s: float) -> float:
    """Nominal seconds of a block at its programmed feed (a lower bound of its planned time): dwell seconds,
    or length / feed (tool-tip mm, or the rotation in deg where the tip does not move) with the feed (or a
    G93 move's length / time) at most the rapid feed, as the planner caps it (:mod:`.rawmoves`).  Plain
    floats: the window splitter looks at every block (and :func:`check_blocks`, which
    :func:`~hexacnc.planner.path.build_path` runs on every block it plans or checks, once they are valid)."""
    if blk.kind == B.DWELL:
        return max(0.0, float(blk.seconds or 0.0))
    if blk.kind not in B.MOTION_KINDS:
        return 0.0
    s, e = plain_floats(blk.start), plain_floats(blk.end)
    d0, d1, d2 = e[0] - s[0], e[1] - s[1], e[2] - s[2]
    length = math.sqrt(d0 ** 2 + d1 ** 2 + d2 ** 2)
    if length == 0.0:
        d3, d4, d5 = e[3] - s[3], e[4] - s[4], e[5] - s[5]
        length = math.sqrt(d3 ** 2 + d4 ** 2 + d5 ** 2)
    if blk.kind == B.ARC and blk.center is not None:
        c = plain_floats(blk.center)
        r = math.sqrt((s[0] - c[0]) ** 2 + (s[1] - c[1]) ** 2 + (s[2] - c[2]) ** 2)
        length += 2 * math.pi * r * (int(blk.turns or 0) + (1 if length < 1e-9 else 0))
    rapid = max(float(rapid_mm_s), 1e-9)
    if blk.kind == B.RAPID:
        return length / rapid
    if blk.inverse_time_s is not None:
        return max(0.0, float(blk.inverse_time_s), length / rapid)
    return length / max(min(float(blk.feed_mm_s or default_mm_s), rapid), 1e-9)


def check_block_seconds(blk, seconds: float, max_block_s: float) -> None:
    """Raise :class:`PlanError` (limit ``"max_block_s"``) where a block's nominal time exceeds the bound."""
    if seconds > max_block_s:
        what = "dwell" if blk.kind == B.DWELL else "move"
        hint = "split it" if blk.kind == B.DWELL else "split it, or raise its feed"
        raise PlanError(f"the {what} takes at least {seconds:.6g} s; at most [planner] max_block_s = "
                        f"{max_block_s:g} s per block ({hint})", line=int(blk.line), limit="max_block_s")


def check_blocks(blocks, cfg) -> None:
    """:func:`check_block_seconds` on every block of a program at the machine's rapid and default feeds."""
    pc = cfg.planner
    rapid, feed = pc.rapid_feed_mm_min / 60.0, pc.default_feed_mm_min / 60.0
    for blk in blocks:
        check_block_seconds(blk, block_seconds(blk, rapid, feed), pc.max_block_s)


def feeds_above_rapid(blocks, cfg) -> tuple[int, int | None]:
    """(count, first line) of the feed moves (G1/G2/G3, G93 included) that ask more than the rapid feed, which
    caps them (:mod:`.rawmoves`): the plan summary says so, as a program's CAM time may assume them."""
    pc = cfg.planner
    rapid, feed = pc.rapid_feed_mm_min / 60.0, pc.default_feed_mm_min / 60.0
    n, first = 0, None
    for blk in blocks:
        if blk.kind not in B.MOTION_KINDS or blk.kind == B.RAPID:
            continue
        if blk.inverse_time_s is not None:
            over = block_seconds(blk, rapid, feed) > float(blk.inverse_time_s) * (1.0 + 1e-9)
        else:
            over = float(blk.feed_mm_s or feed) > rapid
        if over:
            n += 1
            first = int(blk.line) if first is None else first
    return n, first


def plain_floats(a) -> list:
    """A pose or point as plain floats (no numpy scalars: the window splitter looks at every block)."""
    return a.tolist() if isinstance(a, np.ndarray) else [float(v) for v in a]
