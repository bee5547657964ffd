"""Persistent machine state beside the config: tool table (LinuxCNC ``tool.tbl``), numbered
parameters (LinuxCNC var file), and the adapter that runs the interpreter from and into it."""
from .files import ToolEntry, read_tool_table, read_var_file, write_tool_table, write_var_file
from .machine import MachineState, StateStore, interpret, interpret_stream, state_after_stream

__all__ = ["MachineState", "StateStore", "ToolEntry", "interpret", "interpret_stream", "state_after_stream", "read_tool_table", "read_var_file",
           "write_tool_table", "write_var_file"]
