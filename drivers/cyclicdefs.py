"""The drive bus's cyclic contract: ``send``/``poll`` result bits, units and the master heartbeat period.

Shared by :mod:`drivers.cyclic` (the hot-path codec, which re-exports these names) and its users.
Drive positions are increments: ``inc = round((strut_length_mm - strut_offset_mm) * increments_per_mm)``.
"""
from __future__ import annotations

import math

# -- send() result bits ------------------------------------------------------------------------
SEND_OK = 0
SEND_LIMIT = 1          #: a target was outside the drive limits: no new target sent (drives hold)
SEND_BUS_ERROR = 2      #: a bus refused a frame (python-can error); the others were still tried

# -- poll() event bits -------------------------------------------------------------------------
EV_FEEDBACK = 1 << 0    #: position actual updated (TPDO1)
EV_STATUS = 1 << 1      #: a statusword changed (TPDO2)
EV_HEARTBEAT = 1 << 2   #: a drive heartbeat arrived
EV_EMCY = 1 << 3        #: an EMCY was queued in ``emcy`` (error reset EMCYs too)
EV_BOOTUP = 1 << 4      #: a drive sent boot-up: it was reset (power loss, watchdog)
EV_NMT = 1 << 5         #: a drive's heartbeat reports a state other than OPERATIONAL
EV_BAD_FRAME = 1 << 6   #: a frame of a known COB-ID had a wrong length
EV_OVERFLOW = 1 << 7    #: the drain stopped at ``max_frames`` with frames left
EV_BUS_ERROR = 1 << 8   #: a bus raised on receive

EVENT_NAMES = {EV_FEEDBACK: "feedback", EV_STATUS: "status", EV_HEARTBEAT: "heartbeat", EV_EMCY: "emcy",
               EV_BOOTUP: "bootup", EV_NMT: "nmt", EV_BAD_FRAME: "bad frame", EV_OVERFLOW: "overflow",
               EV_BUS_ERROR: "bus error"}

NMT_OPERATIONAL = 5

def length_to_increments(length_mm: float, offset_mm: float, increments_per_mm: float) -> int:
    """Drive reading in increments of a strut length (mm)."""
    return round((length_mm - offset_mm) * increments_per_mm)


def increments_to_length(inc: int, offset_mm: float, increments_per_mm: float) -> float:
    """Strut length (mm) of a drive reading in increments."""
    return inc / increments_per_mm + offset_mm


def limits_inc(cfg) -> tuple[list[int], list[int]]:
    """(min, max) drive positions in increments from ``[struts] min/max_length_mm`` (MachineConfig).

    Rounded inwards, so an increment inside the limits is a length inside the limits.
    """
    k = cfg.bus.increments_per_mm
    lo = [math.ceil((float(cfg.min_length_mm[i]) - float(cfg.strut_offset_mm[i])) * k - 1e-9) for i in range(6)]
    hi = [math.floor((float(cfg.max_length_mm[i]) - float(cfg.strut_offset_mm[i])) * k + 1e-9) for i in range(6)]
    return lo, hi


def master_heartbeat_s(bus_cfg) -> float:
    """Period of the master heartbeat (0x700 + 0x7F) while cycling: ``[bus] heartbeat_ms``.

    The drives' heartbeat consumer time 0x1016 is ``[bus] heartbeat_timeout_ms`` (the master writes it),
    so this period keeps a live master live for them. A silent master is found within
    ``[bus] comm_loss_timeout_s`` by the RPDO deadline (0x1400:05) and the SYNC time-out (0x1006), not by
    the heartbeat: a faster master heartbeat (it was a quarter of comm_loss_timeout_s, one frame per
    ten cycles at 20 ms) bought nothing and cost bus demand (``hexacnc bus demand``)."""
    return bus_cfg.heartbeat_ms * 1e-3


def event_text(ev: int) -> str:
    return ", ".join(name for bit, name in EVENT_NAMES.items() if ev & bit) or "none"
