"""Probe synchronisation: interpret a program up to a probe whose result is not known yet.

LinuxCNC stops reading ahead at G38.x: the lines after a probe are interpreted only once the probe
move has ended and #5061-#5070 hold its result.  :class:`SyncInterpreter` gives the daemon the same:
it is the plain :class:`~hexacnc.gcode.interp.Interpreter` fed with the results of the probes already
executed (:class:`ProbeResult`, in execution order).  At the n-th probe of the run it

* with a known result: sets #5061-#5069 (the contact point, or the end of the move without contact,
  in the coordinate system in effect, program units), #5070 (1 contact, 0 none) and continues from
  where the machine stopped (``stop_tip``);
* without one: raises :class:`ProbeSync` after emitting the probe block, so the caller has every
  block up to and including that probe (``exc.interpreter.blocks``).

The program is interpreted again from its start after each probe (deterministic: the blocks before
the n-th probe are the same each time); the caller runs the blocks after the last known probe.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import blocks as B
from .interp import Interpreter

RESULT_PARAMETERS = tuple(range(5061, 5071))


@dataclass(frozen=True)
class ProbeResult:
    """What the machine reported for one probe: tool tip poses in the machine frame (mm, deg)."""
    contact: bool
    contact_tip: tuple          #: 6 floats: tip at the probe edge (no contact: the end of the move)
    stop_tip: tuple             #: 6 floats: where the tool tip stopped (the interpreter continues there)


class ProbeSync(Exception):
    """Raised at the first probe without a known result; ``interpreter.blocks`` ends with its block."""

    def __init__(self, interpreter: "SyncInterpreter", index: int):
        super().__init__(f"probe {index} awaits its result")
        self.interpreter = interpreter
        self.index = index


class SyncInterpreter(Interpreter):
    """An :class:`Interpreter` that knows the results of the first ``len(known)`` probes."""

    known: tuple = ()

    def _probe(self, ln, vals: dict, motion: int) -> None:
        n = getattr(self, "syncs_done", 0)
        self.syncs_done = n + 1
        super()._probe(ln, vals, motion)
        if n >= len(self.known):
            raise ProbeSync(self, n)
        r = self.known[n]
        self.pos = [float(v) for v in r.contact_tip]
        for i in range(6):
            self.P[5061 + i] = self._prog(i)
        for k in (5067, 5068, 5069):
            self.P[k] = 0.0
        self.P[5070] = 1.0 if r.contact else 0.0
        self.runtime_pending.difference_update(RESULT_PARAMETERS)
        self.pos = [float(v) for v in r.stop_tip]
        a = np.array(self.pos)
        a.flags.writeable = False
        self.pos_arr = a


    def _io(self, ln, vals: dict, m: int) -> None:
        """M66 (wait on an input) is a synchronisation point too: #5399 from ``known`` (an
        :class:`InputResult`), else :class:`ProbeSync` after its block."""
        super()._io(ln, vals, m)
        if m != 66:
            return
        n = getattr(self, "syncs_done", 0)
        self.syncs_done = n + 1
        if n >= len(self.known):
            raise ProbeSync(self, n)
        self.P[5399] = float(self.known[n].value)
        self.runtime_pending.discard(5399)


@dataclass(frozen=True)
class InputResult:
    """What an M66 read: #5399 (the input's state 0/1, or -1: the wait timed out)."""
    value: float


def is_sync_block(b) -> bool:
    """A block the interpreter stops reading ahead at: a probe, or an M66 input wait."""
    return b.kind == B.PROBE or (b.kind == B.IO and (b.extra or {}).get("op") == "wait_input")


def make_sync_interpreter(known) -> type:
    """A :class:`SyncInterpreter` subclass bound to the probe results ``known`` (a sequence)."""
    return type("BoundSyncInterpreter", (SyncInterpreter,), {"known": tuple(known)})


def segment_after(blocks: list, n_known: int) -> tuple[list, object | None]:
    """Blocks after the ``n_known``-th synchronisation block (probe or M66), split off a trailing one
    (the next)."""
    seen = 0
    start = 0
    if n_known:
        for k, b in enumerate(blocks):
            if is_sync_block(b):
                seen += 1
                if seen == n_known:
                    start = k + 1
                    break
    seg = list(blocks[start:])
    probe = seg.pop() if seg and is_sync_block(seg[-1]) else None
    return seg, probe
