"""Digital I/O of the simulated drives: 0x60FD (digital inputs) and 0x60FE (digital outputs).

0x60FE:1 holds the physical outputs, 0x60FE:2 the bit mask of outputs the drive drives: the
outputs that are on are ``0x60FE:1 & 0x60FE:2``.  0x60FD is set from outside (the simulated
drives' ``inject dinput NODE VALUE`` line, :mod:`hexacnc.daemon.simhost`).  Each drive keeps a
bounded log of its output changes with the SYNC count (one per master cycle), the drive's clock
and its position target at that moment, so a test can tell *when* along a motion an output changed.
"""
from __future__ import annotations

import time
from collections import deque

from .simhooks import EXTENSIONS

LOG_LEN = 1024
DEFAULT_MASK = 0xFFFF0000


class DigitalIO:
    """One drive's digital inputs and outputs (see the module text)."""

    def __init__(self, drive):
        self.drive = drive
        self.inputs = 0
        self.outputs = 0          #: 0x60FE:1
        self.mask = DEFAULT_MASK  #: 0x60FE:2
        self.syncs = 0
        self.log: deque = deque(maxlen=LOG_LEN)

    @property
    def physical(self) -> int:
        """The outputs that are on."""
        return self.outputs & self.mask

    def on_read_inputs(self, sub: int):
        return self.inputs

    def on_read_outputs(self, sub: int):
        return {1: self.outputs, 2: self.mask}.get(sub)

    def on_write_outputs(self, sub: int, value: int) -> None:
        before = self.physical
        if sub == 1:
            self.outputs = int(value) & 0xFFFFFFFF
        elif sub == 2:
            self.mask = int(value) & 0xFFFFFFFF
        if self.physical != before:
            self.log.append({"syncs": self.syncs, "t_s": time.monotonic(), "outputs": self.physical,
                             "target_inc": int(self.drive.target_inc), "pos_inc": int(self.drive.pos_inc)})

    def on_sync(self, drive, now_s: float) -> None:
        self.syncs += 1

    def snapshot(self) -> dict:
        return {"inputs": self.inputs, "outputs": self.physical, "syncs": self.syncs, "log": list(self.log)}


def attach(drive) -> None:
    dio = DigitalIO(drive)
    drive.dio = dio
    drive.hooks.on_read(0x60FD, dio.on_read_inputs)
    drive.hooks.on_read(0x60FE, dio.on_read_outputs)
    drive.hooks.on_write(0x60FE, dio.on_write_outputs)
    drive.hooks.on_sync(dio.on_sync)


EXTENSIONS.append(attach)
