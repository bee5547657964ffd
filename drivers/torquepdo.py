"""Drive torque actual value (CiA 402 0x6077) in a decimated synchronous TPDO3, while moving too.

``[bus] torque_pdo_every = n`` (1..240; 0 = off, the default): each drive sends TPDO3 (COB-ID 0x380 +
node id, one mapping ``[0x6077 INTEGER16]``, 2 bytes) on every n-th SYNC (CiA 301 transmission type n),
staggered like the position feedback: SYNC start value = the drive's TPDO1 start value, so with a
SYNC counter (``feedback_divider`` > 1) the drives of one bus start on consecutive SYNCs and never send
their TPDO3 in the same cycle (n >= drives per bus).

Bus budget (:func:`budget`, a part of ``hexacnc bus load``). The cyclic frames (SYNC 0x080, TPDO1
0x18x, RPDO1 0x20x) all win arbitration against 0x38x, so a TPDO3 delays them only as a *blocking*
frame: one lower-priority frame already on the wire when the SYNC comes (CAN is not pre-emptive;
response-time analysis: blocking = the longest lower-priority frame, counted once).  That term is the
budget's asynchronous reserve (2 bytes); the 2-byte TPDO3 is no longer, so the worst case of the cyclic
frames is unchanged.  What the TPDO3 costs is its own wire time, sent in the idle time after the cyclic
frames: :func:`budget` reports it per bus and checks that the low-priority traffic (TPDO3 + the
asynchronous frames) needs less than the idle time of the worst cycle.  It also raises the bus demand
of the cycles that carry it (``hexacnc bus demand``: the ``staggered_with_torque_pdo`` variant): on the
default layout (0.5 ms, two buses, ~2 % of the cycles with an asynchronous frame) p99 rises by a few
us with any rate, which is why it is off by default.

The master maps it (:meth:`drivers.master.Master.configure`), the codec decodes it
(``CyclicIO.torque_pdo_permille`` / ``torque_pdo_time_s`` / ``torque_pdo_count``), the simulated
drives send it (their 0x6077 read hook, :mod:`drivers.simtorque`).
"""
from __future__ import annotations

from .errors import BusError

OBJ_TORQUE_ACTUAL = 0x6077
TPDO_NUMBER = 3                       #: TPDO3: 0x1802 / 0x1A02
COB_BASE = 0x380
MAPPING = ((OBJ_TORQUE_ACTUAL, 0, 16),)
BYTES = 2


def every(bus_cfg) -> int:
    """SYNCs between two TPDO3 of one drive (0: no torque PDO)."""
    n = int(getattr(bus_cfg, "torque_pdo_every", 0) or 0)
    if n and not 1 <= n <= 240:
        raise BusError(f"[bus] torque_pdo_every = {n} must be 0 (off) or 1..240 (CiA 301 transmission type)")
    return n


def cob_id(node_id: int) -> int:
    return COB_BASE + int(node_id)


def tpdo_entry(bus_cfg, plan, nd) -> tuple | None:
    """The master's TPDO3 entry ``(cob, transmission type, mapping, inhibit, event timer, SYNC start)`` of
    node plan ``nd`` (:class:`drivers.layout.NodePlan`), None when off."""
    n = every(bus_cfg)
    if not n:
        return None
    return (cob_id(nd.node_id), n, MAPPING, None, None,
            nd.tpdo1_sync_start if plan.sync_counter_overflow else None)


def budget(bus_cfg, plan, period_us: float, per_bus: list[dict], async_frames_per_s: float,
           frame_time_us, reserve_bytes: int) -> dict | None:
    """The torque PDO's part of the bus budget (None when off): bytes, rate, wire time per cycle and the
    low-priority utilisation check (see the module doc).  ``frame_time_us(n)`` -> (min, max) us of an
    n-byte classic frame; ``per_bus`` rows of :func:`drivers.busload.bus_time` (``max_us`` includes the
    asynchronous reserve)."""
    n = every(bus_cfg)
    if not n:
        return None
    t_max = frame_time_us(BYTES)[1]
    reserve_max = frame_time_us(reserve_bytes)[1]
    rows = []
    for p in per_bus:
        k = len(p["node_ids"])
        idle_us = period_us - (p["max_us"] - reserve_max)          # after the cyclic frames of the worst cycle
        async_per_cycle = async_frames_per_s / max(1, len(per_bus)) * period_us * 1e-6
        low_us = (k / n + async_per_cycle) * reserve_max           # mean low-priority wire time per cycle
        rows.append({"bus": p["bus"], "frames_per_cycle": round(k / n, 4), "torque_us_per_cycle": round(k / n * t_max, 2),
                     "low_priority_us_per_cycle": round(low_us, 2), "idle_us_per_cycle": round(idle_us, 2),
                     "drains": low_us < idle_us})
    fits = BYTES <= reserve_bytes and all(r["drains"] for r in rows)
    return {"object": "0x6077 torque actual value", "tpdo": TPDO_NUMBER, "cob_id": f"0x{COB_BASE:03X} + node id",
            "bytes": BYTES, "every_syncs": n, "sample_period_s": round(n * period_us * 1e-6, 6), "max_us": t_max,
            "blocking": (f"priority below every cyclic frame: delays them only as the one blocking frame, "
                         f"already counted by the {reserve_bytes}-byte asynchronous reserve"
                         if BYTES <= reserve_bytes else "longer than the asynchronous reserve"),
            "per_bus": rows, "fits": fits}
