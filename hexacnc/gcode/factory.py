"""Build a program for a configured machine (``program_from_config``)."""
from __future__ import annotations

import math

import numpy as np

from ..pose import matrix_from_euler
from .interp import Program, parse_program


def machine_defaults(cfg) -> dict:
    """Interpreter keyword arguments implied by a :class:`MachineConfig`.

    * G54 origin: ``[planner] work_offset_mm`` (machine frame) with the home
      pose orientation as the A/B/C origin; G55..G59.3 start at zero (as in LinuxCNC).
    * start pose: the tool reference point (``[tool] tip_platform_mm``, tool
      length 0) at the home pose, with the home orientation.
    * tool axis: ``[tool] axis_platform``; tool lengths: ``[tools] length_mm`` if present.
    * G28 and G30 positions: the start pose (the tool reference point at home).
    * no-op M-codes: ``[planner] noop_m_codes``.
    * subroutine files: ``[gcode] subroutine_path``; ``[gcode] require_end``.
    * block delete (skip ``/`` lines): ``[planner] block_delete`` (the operator's switch, default on).
    """
    home = np.asarray(cfg.home_pose, dtype=float)
    R = matrix_from_euler(*(math.radians(float(v)) for v in home[3:6]))
    tip = home[:3] + R @ np.asarray(cfg.tool.tip_platform_mm, dtype=float)
    start = [float(v) for v in tip] + [float(v) for v in home[3:6]]
    wo = [float(v) for v in cfg.planner.work_offset_mm] + [float(v) for v in home[3:6]]
    tools = getattr(cfg, "tools", None)
    table = None
    if tools is not None and getattr(tools, "length_mm", None):
        table = dict(tools.length_mm)   # an empty [tools] table means "no table": any T is accepted
    gc_cfg = getattr(cfg, "gcode", None)
    return {"start_pose": start, "work_offsets": {1: wo}, "tool_table": table,
            "tool_axis_platform": [float(v) for v in cfg.tool.axis_platform],
            "g28_pose": list(start), "g30_pose": list(start),
            "noop_m_codes": tuple(getattr(cfg.planner, "noop_m_codes", ())),
            "subroutine_path": tuple(getattr(gc_cfg, "subroutine_path", ())),
            "require_end": bool(getattr(gc_cfg, "require_end", False)),
            "block_delete": bool(getattr(getattr(cfg, "operator", None), "block_delete", True))}


def program_from_config(text: str, name: str, cfg, **overrides) -> Program:
    """Interpret ``text`` for the machine ``cfg`` (keywords override the defaults)."""
    kw = machine_defaults(cfg)
    kw.update(overrides)
    return parse_program(text, name, **kw)
