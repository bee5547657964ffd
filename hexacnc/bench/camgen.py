"""Synthetic CAM-like programs of any length (``hexacnc bench stream``, tests): raster passes of short G1
segments over a wavy surface (G64 P tolerance), a retract, a rapid to the next pass and a plunge between
passes, as 3-axis CAM output looks.  Coordinates fit the default machine (G54 origin 30 mm below the home
tool tip); one line per move, written line by line (a 1e6-line file without holding it)."""
from __future__ import annotations

import math
from pathlib import Path

#: the raster's feeds (mm/min): along the passes, and plunging
FEED_MM_MIN, PLUNGE_MM_MIN = 2400, 600


def _header(feed_mm_min: int) -> list[str]:
    """The program's first lines."""
    return ["(synthetic CAM raster, hexacnc bench)", "G21 G90 G17 G94", "G64 P0.01", f"F{feed_mm_min:d}",
            "S12000 M3", "G0 Z5"]


def cam_lines(n_lines: int, step_mm: float = 0.6, width_mm: float = 60.0, pitch_mm: float = 1.0,
              amp_mm: float = 2.0, bad_line: int | None = None, feed_scale: float = 1.0):
    """Yields ``n_lines`` program lines (ending with M5 and M2).  ``bad_line``: that line (1-based, a move
    line past the header) goes to X 5000, far outside any workspace (a program bad far past its start);
    ``feed_scale``: the feeds times this (1000: feeds no strut follows, as 3D_Chips.ngc's F4.5e6)."""
    feed, plunge = round(FEED_MM_MIN * feed_scale), round(PLUNGE_MM_MIN * feed_scale)
    head = _header(feed)
    body = max(1, n_lines - len(head) - 2)
    for ln in head:
        yield ln
    n = 0
    k = 0
    per = int(width_mm / step_mm)
    y0 = -width_mm / 2
    while n < body:
        y = y0 + (k % int(width_mm / pitch_mm)) * pitch_mm
        xs = [-width_mm / 2 + i * step_mm for i in range(per + 1)]
        if k % 2:
            xs.reverse()
        pre = [f"G0 X{xs[0]:.3f} Y{y:.3f}", f"G1 Z{_z(xs[0], y, amp_mm):.4f} F{plunge:d}", f"F{feed:d}"]
        for ln in pre + [f"G1 X{x:.3f} Z{_z(x, y, amp_mm):.4f}" for x in xs[1:]] + ["G0 Z5"]:
            if n >= body:
                break
            n += 1
            if bad_line is not None and n + len(head) == bad_line:
                ln = "G1 X5000"
            yield ln
        k += 1
    yield "M5"
    yield "M2"


def _z(x: float, y: float, amp: float) -> float:
    return -amp * (1.0 + 0.5 * math.sin(x / 7.0) * math.cos(y / 9.0))


def cam_program(n_lines: int, **kw) -> str:
    return "\n".join(cam_lines(n_lines, **kw)) + "\n"


def write_cam_program(path: Path, n_lines: int, **kw) -> Path:
    with open(path, "w", encoding="utf-8") as f:
        for ln in cam_lines(n_lines, **kw):
            f.write(ln + "\n")
    return path
