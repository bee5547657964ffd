"""Probing (G38.2-G38.5), I/O (M62-M68) and modal state (M70-M73).

Programs are interpreted before anything moves, so what the machine only
learns while running (a probe's trip point, an input's value) is not known
here: a probe is a block of kind ``probe`` and the interpreter continues as if
it ended at its target; an input wait is a block of kind ``io``.  Reading the
results (#5061-#5070 after a probe, #5399 after M66) is refused as
``unsupported``, since the program would branch on them.
"""
from __future__ import annotations

import numpy as np

from . import blocks as B
from .blocks import Block
from .lexer import Line

_PROBE = {382: ("G38.2", True, True), 383: ("G38.3", True, False),
          384: ("G38.4", False, True), 385: ("G38.5", False, False)}
_SAVED = ("u", "plane", "absolute", "arc_absolute", "inverse_time", "cs", "retract_r", "exact_stop",
          "blend", "feed", "rpm", "spindle_dir", "mist", "flood", "tool_len")


class IoMixin:
    """Probe, I/O and modal-state commands of :class:`~hexacnc.gcode.interp.Interpreter`."""

    def _probe(self, ln: Line, vals: dict, motion: int) -> None:
        code, toward, must = _PROBE[motion]
        if self.inverse_time:
            raise ln.error(f"{code} probing cannot be used in inverse-time mode G93", f"g{motion}", "feed")
        if self.feed <= 0.0:
            raise ln.error(f"{code} probe with zero feed rate (no F word yet)", f"g{motion}", "feed")
        end = self._target(ln, vals, False)
        if end[3:] != self.pos[3:]:
            raise ln.error(f"{code}: rotary axes cannot move during probing", ln.axes[-1][1], "word")
        if end == self.pos:
            if 5061 in self.runtime_pending:     # the start is where an earlier probe tripped: run time only
                raise ln.error(f"{code} from the end of an earlier probe: where that probe stops is only "
                               "known while the machine runs (hexacnc interprets before any motion)",
                               f"g{motion}", "unsupported")
            if motion in (383, 385):     # LinuxCNC: G38.3/G38.5 may start at their target (no move)
                self.runtime_pending.update(range(5061, 5071))
                return
            raise ln.error(f"{code}: the probe target is the current point (zero-length probe move)",
                           f"g{motion}", "word")
        b = Block(B.PROBE, ln.num, self._start_arr(), None, self.feed * self.u / 60.0,
                  exact_stop=True, tool_length_mm=self.tool_len, tool=self.tool)
        b.end = self._freeze(end)
        b.extra = {"code": code, "toward": toward, "error_if_no_contact": must,
                   "result_parameters": list(range(5061, 5071))}
        self._emit(b)
        self.pos = end
        self.pos_arr = b.end
        self.runtime_pending.update(range(5061, 5071))

    def _freeze(self, pose):
        a = np.array(pose, dtype=float)
        a.flags.writeable = False
        return a

    def _io(self, ln: Line, vals: dict, m: int) -> None:
        key = f"m{m}"
        if m in (62, 63, 64, 65):
            if "p" not in vals:
                raise ln.error(f"M{m} needs a P word (digital output number)", key, "word")
            idx = self._io_index(ln, vals, "p")
            extra = {"op": "digital_out", "index": idx, "value": 1.0 if m in (62, 64) else 0.0,
                     "synchronized": m in (62, 63)}
        elif m in (67, 68):
            if "e" not in vals or "q" not in vals:
                raise ln.error(f"M{m} needs an E word (analog output number) and a Q word (value)", key, "word")
            extra = {"op": "analog_out", "index": self._io_index(ln, vals, "e"), "value": float(vals["q"]),
                     "synchronized": m == 67}
        else:
            if ("p" in vals) == ("e" in vals):
                raise ln.error("M66 needs exactly one of P (digital input) or E (analog input)", key, "word")
            mode = vals.get("l", 0.0)
            if mode not in (0.0, 1.0, 2.0, 3.0, 4.0):
                raise ln.error(f"M66 L{mode:g}: wait mode must be 0..4", "l", "value")
            if "e" in vals and mode != 0.0:
                raise ln.error("M66 with an analog input (E) only reads it immediately (L0)", "l", "value")
            timeout = vals.get("q", 0.0)
            if mode != 0.0 and "q" not in vals:
                raise ln.error(f"M66 L{mode:g} needs a Q word (timeout in seconds)", key, "word")
            if timeout < 0:
                raise ln.error(f"M66 Q{timeout:g}: negative timeout", "q", "value")
            extra = {"op": "wait_input", "input": "digital" if "p" in vals else "analog",
                     "index": self._io_index(ln, vals, "p" if "p" in vals else "e"),
                     "mode": ("immediate", "rise", "fall", "high", "low")[int(mode)],
                     "timeout_s": float(timeout), "result_parameter": 5399, "synchronized": False}
            self.runtime_pending.add(5399)
        b = Block(B.IO, ln.num, exact_stop=extra["op"] == "wait_input")
        b.extra = extra
        self._emit(b)

    def _io_index(self, ln: Line, vals: dict, letter: str) -> int:
        v = vals[letter]
        if v < 0 or v != int(v) or v > 1023:
            raise ln.error(f"{letter.upper()}{v:g}: I/O number must be an integer 0..1023", letter, "value")
        return int(v)

    # -- M70-M73 ----------------------------------------------------------------------
    def _modal_state(self, ln: Line, m: int) -> None:
        level = len(self.frames)
        if m == 70:
            self.saved_modal[level] = self._snapshot()
        elif m == 71:
            self.saved_modal.pop(level, None)
        elif m == 72:
            st = self.saved_modal.get(level)
            if st is None:
                raise ln.error("M72: no modal state saved with M70 at this call level", "m72", "flow")
            self._restore(ln, st)
        else:
            if not self.frames:
                raise ln.error("M73 (save and auto-restore) is only meaningful inside a subroutine", "m73",
                               "flow")
            self.frames[-1].autorestore = self._snapshot()

    def _snapshot(self) -> dict:
        return {k: getattr(self, k) for k in _SAVED}

    def _restore(self, ln: Line, st: dict) -> None:
        if st["u"] != self.u:
            self.u = st["u"]
            self.scale = [self.u] * 3 + [1.0] * 3
        for k in ("plane", "absolute", "arc_absolute", "inverse_time", "retract_r", "exact_stop", "blend",
                  "feed", "rpm"):
            setattr(self, k, st[k])
        if st["cs"] != self.cs:
            self.cs = st["cs"]
            self.P[5220] = float(self.cs)
            self._refresh_offsets()
        if st["tool_len"] != self.tool_len:
            self._set_tool_length(st["tool_len"])
        if st["spindle_dir"] != self.spindle_dir:
            self.spindle_dir = st["spindle_dir"]
            self._emit(Block(B.SPINDLE, ln.num, spindle_rpm=self.rpm * self.spindle_dir))
        if (st["mist"], st["flood"]) != (self.mist, self.flood):
            if not st["mist"] and not st["flood"]:
                self._emit(Block(B.COOLANT, ln.num, coolant="off"))
            else:
                if self.mist or self.flood:
                    self._emit(Block(B.COOLANT, ln.num, coolant="off"))
                for on, name in ((st["mist"], "mist"), (st["flood"], "flood")):
                    if on:
                        self._emit(Block(B.COOLANT, ln.num, coolant=name))
            self.mist, self.flood = st["mist"], st["flood"]
