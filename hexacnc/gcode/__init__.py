"""RS274NGC interpreter (LinuxCNC dialect, hexapod subset): text -> motion blocks.

``parse_program(text, name, ...) -> Program`` and ``program_from_config(text,
name, cfg)``; see :mod:`hexacnc.gcode.interp` and ``docs/gcode.md``.
"""
from __future__ import annotations

from ..errors import GcodeError
from .blocks import Block
from .interp import Program, parse_program
from .factory import program_from_config
from .state import MachineState, ToolEntry, parse_tool_table
from .stream import iter_blocks

__all__ = ["Block", "GcodeError", "MachineState", "Program", "ToolEntry", "iter_blocks", "parse_program",
           "parse_tool_table", "program_from_config"]
