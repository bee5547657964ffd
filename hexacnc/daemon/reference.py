"""Whether the struts' reference can still be trusted (``referenced`` in the status; ``[homing]``).

:class:`ReferenceWatch` is kept by the operator (:mod:`.operator`) and polled by the supervisor's
feeder thread every ``FEED_PERIOD_S`` and before a reset (``Daemon.ref_watch``), so no latched fault
goes by unseen.  The reference is lost (``referenced`` false, ``lost`` names why and when) on:

* ``[homing] method = "cia402"`` (incremental encoders, referenced by homing):
  - a fault: every fault ends with the drives disabled (``ST_FAULT``), and a drive that faulted
    or lost power may have lost counts;
  - a drive's NMT boot-up (reset or power cycle: its position counter restarts), in any state -
    the hot loop publishes the boot-ups it saw (``H_BOOTUPS``);
  - a homing run that fails (a drive reports a homing error, or it is stopped) - the operator
    clears the reference when a run starts;
* either method (``absolute`` too): an encoder error, an EMCY with a 0x73xx (sensor) code
  (``H_ENCODER_ERRORS``, or the fault it latched).

A plain ``disable`` keeps the reference (the drives keep counting while powered).
"""
from __future__ import annotations

import logging
import threading
import time

from . import shm as S
from .faults import F_EMCY, F_NMT, fault_message

log = logging.getLogger("hexacnc.daemon.reference")


def is_encoder_error(code: int) -> bool:
    """CiA 301/402 error codes 0x7300-0x73FF: sensor (encoder) errors."""
    return code & 0xFF00 == 0x7300


class ReferenceWatch:
    """``referenced`` and why it was lost; see the module doc. ``method``: ``absolute`` | ``cia402``."""

    def __init__(self, method: str, referenced: bool):
        self.incremental = method != "absolute"
        self.referenced = bool(referenced)
        self.lost: dict | None = None         #: {"reason", "at_unix_s"} of the last loss
        self._boot0 = 0
        self._enc0 = 0
        self._in_fault = False                #: the latched fault was looked at (until it is cleared)
        self._lock = threading.Lock()         #: the feeder thread and the socket's threads poll

    def baseline(self, h) -> None:
        """The counters as they stand (the drives' boot at start, before anything was referenced)."""
        self._boot0 = int(h[S.H_BOOTUPS])
        self._enc0 = int(h[S.H_ENCODER_ERRORS])
        self._in_fault = bool(h[S.H_FAULT])

    def mark(self, h) -> None:
        """Referenced now (homing done, or absolute encoders acknowledged)."""
        self.baseline(h)
        self.referenced = True
        self.lost = None

    def unmark(self, reason: str, quiet: bool = False) -> None:
        if self.referenced and not quiet:
            log.warning("reference lost: %s", reason)
        self.referenced = False
        self.lost = {"reason": reason, "at_unix_s": round(time.time(), 3)}

    def poll(self, h) -> bool:
        """Look at the shared header ``h``; returns ``referenced``."""
        with self._lock:
            return self._poll(h)

    def _poll(self, h) -> bool:
        boot, enc = int(h[S.H_BOOTUPS]), int(h[S.H_ENCODER_ERRORS])
        latched = bool(h[S.H_FAULT]) and h[S.H_STATE] == S.ST_FAULT
        new_fault = latched and not self._in_fault
        if not h[S.H_FAULT]:
            self._in_fault = False
        if not self.referenced:
            self._boot0, self._enc0 = boot, enc
            self._in_fault = self._in_fault or latched
            return False
        if enc != self._enc0:
            self.unmark("a drive reported an encoder error (EMCY 0x73xx)")
        elif self.incremental and boot != self._boot0:
            self.unmark("a drive was reset or power-cycled (NMT boot-up): its position counter restarted")
        elif new_fault:
            code, strut, arg = int(h[S.H_FAULT]), int(h[S.H_FAULT_STRUT]), int(h[S.H_FAULT_ARG])
            if code == F_EMCY and is_encoder_error(arg):
                self.unmark(f"encoder error: {fault_message(code, strut, arg)}")
            elif self.incremental and code == F_NMT and arg == 0:
                self.unmark(f"{fault_message(code, strut, arg)}: its position counter restarted")
            elif self.incremental:
                self.unmark(f"the fault '{fault_message(code, strut, arg)}' disabled the drives "
                            f"(incremental encoders, [homing] method = \"cia402\")")
        self._in_fault = self._in_fault or latched
        self._boot0, self._enc0 = boot, enc
        return self.referenced
