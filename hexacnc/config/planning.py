"""``[planner]``, ``[tools]``, ``[gcode]`` and ``[simulation]``: the program-side sections, each typed
dataclass beside its parse function."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .section import Section, _expand_user_vars, _freeze

@dataclass(frozen=True)
class PlannerConfig:
    lookahead_segments: int = 200
    default_feed_mm_min: float = 1000.0
    rapid_feed_mm_min: float = 15000.0
    max_angular_velocity_deg_s: float = 90.0
    path_tolerance_mm: float = 0.01
    sample_bound_mm: float = 0.001
    #: lines up to this tool-tip length (mm) that meet at small turns are smoothed into one C2 curve
    #: inside the G64 P tolerance (CAM output; see hexacnc/planner/smooth.py); 0 = corner blends only
    smooth_max_segment_mm: float = 0.0
    work_offset_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: user/remap M-codes (100..9999) the interpreter accepts as no-ops (noted in the program's
    #: messages), e.g. LinuxCNC's M428/M429 kinematics switches, which a hexapod does not need
    noop_m_codes: tuple = ()
    #: windowed planning (hexacnc/planner/window.py): motion blocks and estimated seconds per window
    window_blocks: int = 2000
    window_s: float = 120.0
    #: longest nominal time (s) of one block (a move at its feed, a dwell): the plan holds a row per cycle
    max_block_s: float = 900.0
    #: motion starts once the first window is planned while the validation of the rest runs ahead
    start_before_validated: bool = False


@dataclass(frozen=True)
class ToolTableConfig:
    """``[tools] length_mm = {"1" = 62.5, ...}``: tool number -> length along the tool axis (G43 H)."""
    length_mm: dict = field(default_factory=dict)


@dataclass(frozen=True)
class GcodeConfig:
    """``[gcode]``: subroutine search path (``o<name> call`` of ``name.ngc``), program-end rule."""
    subroutine_path: tuple = ()     #: directories (relative ones: to the config file's directory)
    require_end: bool = False       #: refuse programs without M2/M30/% at the end (LinuxCNC)


def parse_planner(p: Section) -> PlannerConfig:
    """``[planner]``: look-ahead, feeds, tolerances, smoothing, work offset, no-op M-codes."""
    pd = PlannerConfig()
    return PlannerConfig(
        lookahead_segments=p.getint("lookahead_segments", pd.lookahead_segments, minval=50, maxval=10_000_000),
        default_feed_mm_min=p.getfloat("default_feed_mm_min", pd.default_feed_mm_min, above=0.0),
        rapid_feed_mm_min=p.getfloat("rapid_feed_mm_min", pd.rapid_feed_mm_min, above=0.0),
        max_angular_velocity_deg_s=p.getfloat("max_angular_velocity_deg_s", pd.max_angular_velocity_deg_s,
                                              above=0.0),
        path_tolerance_mm=p.getfloat("path_tolerance_mm", pd.path_tolerance_mm, above=0.0),
        sample_bound_mm=p.getfloat("sample_bound_mm", pd.sample_bound_mm, above=0.0),
        smooth_max_segment_mm=p.getfloat("smooth_max_segment_mm", pd.smooth_max_segment_mm, minval=0.0,
                                         maxval=1000.0),
        work_offset_mm=_freeze(p.getvec("work_offset_mm", 3, [0.0, 0.0, 0.0])),
        noop_m_codes=_noop_m_codes(p),
        window_blocks=p.getint("window_blocks", pd.window_blocks, minval=8, maxval=1_000_000),
        window_s=p.getfloat("window_s", pd.window_s, minval=1.0, maxval=3600.0),
        max_block_s=p.getfloat("max_block_s", pd.max_block_s, minval=1.0, maxval=86400.0),
        start_before_validated=p.getbool("start_before_validated", pd.start_before_validated),
    )


def parse_tools(tl: Section) -> ToolTableConfig:
    """``[tools] length_mm = {"1" = 62.5, ...}``."""
    lengths = tl._get("length_mm", {})
    if not isinstance(lengths, dict):
        raise tl.error("length_mm", f"expected a table of tool number = length, got {lengths!r}")
    tool_len: dict[int, float] = {}
    for key, v in lengths.items():
        if not str(key).isdigit() or not 1 <= int(key) <= 99999:
            raise tl.error("length_mm", f"tool number {key!r} must be an integer 1..99999")
        if not Section._is_number(v) or not math.isfinite(float(v)) or not -1000.0 <= float(v) <= 1000.0:
            raise tl.error("length_mm", f"tool {key}: length {v!r} must be a number in [-1000, 1000] mm")
        tool_len[int(key)] = float(v)
    return ToolTableConfig(length_mm=tool_len)


def _noop_m_codes(p: Section) -> tuple:
    """``[planner] noop_m_codes``: a list of distinct integers 100..9999 (user and remap M-codes only)."""
    v = p._get("noop_m_codes", [])
    if not isinstance(v, list):
        raise p.error("noop_m_codes", f"expected a list of M-code numbers, got {v!r}")
    out = []
    for m in v:
        if isinstance(m, bool) or not isinstance(m, int) or not 100 <= m <= 9999:
            raise p.error("noop_m_codes", f"{m!r} is not a user or remap M-code (an integer 100..9999); "
                                          "built-in M-codes cannot be made no-ops")
        if m in out:
            raise p.error("noop_m_codes", f"M{m} is listed twice")
        out.append(m)
    return tuple(out)


def _parse_gcode(gs: Section, path: str) -> GcodeConfig:
    """``[gcode] subroutine_path = ["subs", "/opt/ngc"]``, ``require_end = false``."""
    raw = gs._get("subroutine_path", [])
    if isinstance(raw, str):
        raw = [raw]
    if not isinstance(raw, list) or len(raw) > 32 or not all(isinstance(d, str) and 0 < len(d) <= 4096
                                                               for d in raw):
        raise gs.error("subroutine_path", f"{raw!r} must be a list of at most 32 directory names")
    base = os.path.dirname(os.path.abspath(path)) if not path.startswith("<") else os.getcwd()
    dirs = tuple(d if os.path.isabs(d) else os.path.normpath(os.path.join(base, d)) for d in raw)
    return GcodeConfig(subroutine_path=dirs, require_end=gs.getbool("require_end", False))


def _simulation_truth(ss: Section, path: str) -> str:
    """``[simulation] truth``: a true machine file (relative to this file) for the simulated plant."""
    t = ss.getstr("truth", "")
    if not t:
        return ""
    p = Path(_expand_user_vars(t))
    if not p.is_absolute() and not path.startswith("<"):
        p = Path(path).parent / p
    if not p.is_file():
        raise ss.error("truth", f"{t!r}: no such file ({p})")
    return str(p)
