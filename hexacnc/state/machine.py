"""The interpreter's persistent state and the adapter that runs programs from it.

:class:`MachineState` holds what LinuxCNC keeps between programs: the numbered parameters of the
var file (work offsets G54..G59.3 #5221..#5390, G28 #5161.., G30 #5181.., G92 #5210..#5219,
the selected system #5220, the tool in the spindle #5400 and its G43 length #5403), the tool table,
and (in memory only) the modal state the last program or MDI line left (units, distance mode,
feed, motion mode, spindle, G64, tool length).

:func:`interpret` runs the interpreter (:class:`hexacnc.gcode.interp.Interpreter`) from a state and
returns the program and the state after it.  Until the interpreter takes and exposes its state
itself, the adapter sets and reads its public state attributes (``P``, ``g92``, ``cs``, ``off``,
``tools`` and the modal ones) around ``run``.

:class:`StateStore` keeps the current state of one daemon and its two files (``tool.tbl`` and
``hexacnc.var`` in :func:`state_dir`), written atomically on every change.
"""
from __future__ import annotations

import copy
import logging
import os
import threading
from dataclasses import dataclass, field, replace
from pathlib import Path

from ..errors import DataError
from .files import ToolEntry, check_tool, read_tool_table, read_var_file, write_tool_table, write_var_file

log = logging.getLogger("hexacnc.state")

#: numbered parameters kept in the var file
PERSISTENT = frozenset(list(range(5161, 5170)) + list(range(5181, 5190)) + list(range(5210, 5221))
                       + [5201 + 20 * k + i for k in range(1, 10) for i in range(9)] + [5400, 5403])
#: coordinate system names, index 1..9
SYSTEMS = ("G54", "G55", "G56", "G57", "G58", "G59", "G59.1", "G59.2", "G59.3")
#: interpreter attributes carried from one program / MDI line to the next (modal state)
MODAL_ATTRS = ("motion", "plane", "absolute", "arc_absolute", "inverse_time", "feed", "rpm", "spindle_dir",
               "mist", "flood", "selected", "exact_stop", "blend", "u", "scale")
TOOL_FILE = "tool.tbl"
VAR_FILE = "hexacnc.var"


@dataclass
class MachineState:
    params: dict[int, float] = field(default_factory=dict)
    tools: dict[int, ToolEntry] = field(default_factory=dict)
    modal: dict = field(default_factory=dict)

    def copy(self) -> "MachineState":
        return MachineState(dict(self.params), {t: replace(e) for t, e in self.tools.items()},
                            copy.deepcopy(self.modal))

    # -- views -----------------------------------------------------------------------------
    @property
    def system(self) -> int:
        return min(9, max(1, int(round(self.params.get(5220, 1.0)))))

    def offset(self, k: int) -> list[float]:
        return [self.params.get(5201 + 20 * k + i, 0.0) for i in range(6)]

    def g92(self) -> list[float]:
        if not self.params.get(5210, 0.0):
            return [0.0] * 6
        return [self.params.get(5211 + i, 0.0) for i in range(6)]

    @property
    def tool(self) -> int:
        return int(self.params.get(5400, 0.0))

    @property
    def tool_length_mm(self) -> float:
        return float(self.params.get(5403, 0.0))

    def work_origin(self) -> list[float]:
        """Machine coordinates of the active work zero: selected offset + G92 (mm, deg)."""
        o, g = self.offset(self.system), self.g92()
        return [o[i] + g[i] for i in range(6)]

    def offsets_view(self) -> dict:
        out = {name: self.offset(k) for k, name in enumerate(SYSTEMS, 1)}
        out.update({"G92": self.g92(), "G28": [self.params.get(5161 + i, 0.0) for i in range(6)],
                    "G30": [self.params.get(5181 + i, 0.0) for i in range(6)],
                    "active": SYSTEMS[self.system - 1], "tool": self.tool,
                    "tool_length_mm": self.tool_length_mm})
        return out


def default_state(cfg) -> MachineState:
    """The state of a machine with no files yet: the config's G54, G28/G30 and tool lengths."""
    from ..gcode.factory import machine_defaults
    kw = machine_defaults(cfg)
    P: dict[int, float] = {k: 0.0 for k in PERSISTENT}
    for k, vec in kw["work_offsets"].items():
        for i, v in enumerate(vec):
            P[5201 + 20 * int(k) + i] = float(v)
    for base, key in ((5161, "g28_pose"), (5181, "g30_pose")):
        for i, v in enumerate(kw[key]):
            P[base + i] = float(v)
    P[5220] = 1.0
    tools = {int(t): ToolEntry(int(t), int(t), float(z)) for t, z in (kw["tool_table"] or {}).items()}
    return MachineState(P, tools, {})


def _to_interp_state(state: MachineState):
    from ..gcode.state import MachineState as GState
    params = {k: v for k, v in state.params.items() if k not in (5400, 5403)}
    tools = {t: replace(e) for t, e in state.tools.items()}
    return GState(parameters=params, tools=tools, current_tool=state.tool, tool_length_mm=state.tool_length_mm)


def _from_interp_state(fs) -> tuple[dict, dict]:
    params = {k: float(fs.parameters.get(k, 0.0)) for k in PERSISTENT if k not in (5400, 5403)}
    params[5400] = float(fs.current_tool)
    params[5403] = float(fs.tool_length_mm)
    return params, {int(t): replace(e) for t, e in fs.tools.items()}


def interpret(text: str, name: str, cfg, start_tip_deg, state: MachineState, interpreter=None):
    """Interpret ``text`` from ``state`` starting at the tool tip pose ``start_tip_deg`` (mm, deg;
    the tool tip of the current tool).  Returns ``(Program, MachineState after it)``; ``state`` is
    not changed.  Raises GcodeError.

    The persistent state goes in as the interpreter's ``initial_state`` and comes back as
    ``Program.final_state`` (the contract with hexacnc.gcode); the modal state (MDI) is carried
    through the interpreter's modal attributes.  ``interpreter``: another Interpreter class (a
    subclass; probe synchronisation, :mod:`hexacnc.gcode.probesync`)."""
    import gc

    from ..gcode.interp import Interpreter
    Interpreter = interpreter or Interpreter
    it = Interpreter(text, name, **_interp_kwargs(cfg, start_tip_deg, state))
    _set_modal(it, state)
    was = gc.isenabled()
    gc.disable()
    try:
        prog = it.run(text)
    finally:
        if was:
            gc.enable()
    return prog, _state_after(prog.final_state, it)


def _interp_kwargs(cfg, start_tip_deg, state: MachineState) -> dict:
    from ..gcode.factory import machine_defaults
    kw = machine_defaults(cfg)
    kw["start_pose"] = [float(v) for v in start_tip_deg]
    for k in ("work_offsets", "g28_pose", "g30_pose", "tool_table"):
        kw.pop(k, None)
    if not state.tools and cfg.tools.length_mm:
        kw["tool_table"] = dict(cfg.tools.length_mm)
    kw["initial_state"] = _to_interp_state(state)
    return kw


def _set_modal(it, state: MachineState) -> None:
    for a in MODAL_ATTRS:
        if a in state.modal and hasattr(it, a):
            setattr(it, a, copy.deepcopy(state.modal[a]))


def _state_after(final_state, it) -> MachineState:
    newp, tools = _from_interp_state(final_state)
    modal = {a: copy.deepcopy(getattr(it, a)) for a in MODAL_ATTRS if hasattr(it, a)}
    return MachineState(newp, tools, modal)


def interpret_stream(text: str, name: str, cfg, start_tip_deg, state: MachineState, **kw):
    """As :func:`interpret`, streamed (:func:`hexacnc.gcode.textstream.iter_text_blocks`: blocks in
    windows, memory bounded by the window): returns the :class:`~hexacnc.gcode.stream.BlockStream`;
    once it is exhausted, :func:`state_after_stream` gives the state after the program."""
    from ..gcode.textstream import iter_text_blocks
    return iter_text_blocks(text, name, prepare=lambda it: _set_modal(it, state),
                            **_interp_kwargs(cfg, start_tip_deg, state), **kw)


def state_after_stream(stream) -> MachineState:
    """The :class:`MachineState` after an exhausted :func:`interpret_stream`."""
    return _state_after(stream.program.final_state, stream.interpreter)


def state_dir(cfg) -> Path:
    """Directory of the persistent state files: ``[daemon] state_dir``, else beside the config file;
    for the embedded default machine ``$XDG_STATE_HOME/hexacnc`` or ``~/.local/state/hexacnc``."""
    sd = cfg.operator.state_dir
    if sd:
        return Path(os.path.expanduser(os.path.expandvars(sd)))
    from ..config import default_config_path
    p = Path(cfg.path)
    try:
        embedded = p.resolve() == default_config_path().resolve()
    except OSError:
        embedded = False
    if not embedded and p.parent.is_dir() and str(cfg.path) not in ("", "<config>"):
        return p.parent
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(base) / "hexacnc"


class StateStore:
    """The current :class:`MachineState` of a daemon and its files (thread-safe)."""

    def __init__(self, cfg, directory: Path | None = None):
        self.cfg = cfg
        self.dir = Path(directory) if directory is not None else state_dir(cfg)
        self.lock = threading.Lock()
        self.state = self._load()

    @property
    def tool_path(self) -> Path:
        return self.dir / TOOL_FILE

    @property
    def var_path(self) -> Path:
        return self.dir / VAR_FILE

    def _load(self) -> MachineState:
        st = default_state(self.cfg)
        params = read_var_file(self.var_path, PERSISTENT)
        if params is not None:
            st.params.update(params)
        tools = read_tool_table(self.tool_path)
        if tools is not None:
            st.tools = tools
        log.info("machine state from %s (%s, %s)", self.dir, "var file" if params is not None else "defaults",
                 f"{len(st.tools)} tools" if tools is not None else "config tool lengths")
        return st

    def snapshot(self) -> MachineState:
        with self.lock:
            return self.state.copy()

    def commit(self, new: MachineState) -> None:
        """Make ``new`` the current state and write the files that changed (atomically)."""
        with self.lock:
            old = self.state
            if new.params != old.params:
                write_var_file(self.var_path, new.params)
            if new.tools != old.tools:
                write_tool_table(self.tool_path, new.tools)
            self.state = new.copy()

    # -- edits (hexacnc offsets / tools) -----------------------------------------------------
    def set_offset(self, system: str, values: dict[str, float]) -> MachineState:
        """Set axes of ``system`` (G54..G59.3, G92, G28, G30) to ``values`` ({axis: mm or deg})."""
        sysname = str(system).upper()
        if sysname in SYSTEMS:
            base = 5201 + 20 * (SYSTEMS.index(sysname) + 1)
        elif sysname in ("G92", "G28", "G30"):
            base = {"G92": 5211, "G28": 5161, "G30": 5181}[sysname]
        else:
            raise DataError(f"offsets: unknown system {system!r} (G54..G59.3, G92, G28, G30)")
        new = self.snapshot()
        for axis, v in values.items():
            a = str(axis).lower()
            if a not in ("x", "y", "z", "a", "b", "c"):
                raise DataError(f"offsets {sysname}: unknown axis {axis!r} (x y z a b c)")
            v = float(v)
            if not (abs(v) <= 1e5):
                raise DataError(f"offsets {sysname} {a}: {v!r} is not a number within +-1e5")
            new.params[base + "xyzabc".index(a)] = v
        if sysname == "G92":
            new.params[5210] = 1.0 if any(new.params[5211 + i] for i in range(6)) else 0.0
        self.commit(new)
        return new

    def select(self, system: str) -> MachineState:
        sysname = str(system).upper()
        if sysname not in SYSTEMS:
            raise DataError(f"offsets: unknown system {system!r} (G54..G59.3)")
        new = self.snapshot()
        new.params[5220] = float(SYSTEMS.index(sysname) + 1)
        self.commit(new)
        return new

    def set_tool(self, entry: ToolEntry) -> MachineState:
        check_tool(entry)
        new = self.snapshot()
        new.tools[entry.tool] = entry
        if new.tool == entry.tool:
            new.params[5403] = entry.z_offset_mm if new.params.get(5403) else new.params.get(5403, 0.0)
        self.commit(new)
        return new

    def delete_tool(self, tool: int) -> MachineState:
        new = self.snapshot()
        if tool not in new.tools:
            raise DataError(f"tools: T{tool} is not in the tool table")
        if new.tool == tool:
            raise DataError(f"tools: T{tool} is in the spindle; change tools first")
        del new.tools[tool]
        self.commit(new)
        return new
