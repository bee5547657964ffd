"""Benchmark: bus demand per cycle (wire time of the frames released in each bus cycle) over
simulated seconds (default 10) of the configured layout, with the drives' timers as the master configures them
(TPDO2 event timers / inhibit times and heartbeat producer times staggered per strut) against the
former uniform timers (every drive 50 ms / 1 ms / ``heartbeat_ms``, started by one NMT command)::

    hexacnc bus demand [--config F] [--seconds 10]      # JSON: median / p99 per variant

Frame times are exact for each frame's bits: base format, 1 Mbit/s classic CAN (``[bus] bitrate``),
stuff bits counted on the real bit stream (SOF..CRC) of a payload like the drives send (positions
moving, statuswords, SYNC counter). Per bus cycle: SYNC, the RPDOs of the layout, the TPDO1 feedback
of the drives whose SYNC start/divider falls on it, and every asynchronous frame (TPDO2 on its
event timer, heartbeats, the master heartbeat) whose timer expires inside the cycle. The NMT start
reaches the drives within ~0.3 ms of each other (SDO-free broadcast order), as on the real bus.
"""
from __future__ import annotations

import dataclasses
import functools
import random
import statistics
from typing import Callable

from .cyclicdefs import master_heartbeat_s
from .layout import heartbeat_producer_ms, plan_layout, status_event_timer_ms
from . import torquepdo


def _crc15(bits: list[int]) -> int:
    crc = 0
    for b in bits:
        nxt = b ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if nxt:
            crc ^= 0x4599
    return crc


@functools.lru_cache(maxsize=4096)
def frame_bits(can_id: int, data: bytes) -> int:
    """Exact length in bits of a classic base-format data frame incl. stuff bits, IFS 3 bits."""
    bits = [0] + [(can_id >> (10 - i)) & 1 for i in range(11)] + [0, 0, 0]          # SOF, ID, RTR, IDE, r0
    bits += [(len(data) >> (3 - i)) & 1 for i in range(4)]
    for byte in data:
        bits += [(byte >> (7 - i)) & 1 for i in range(8)]
    crc = _crc15(bits)
    bits += [(crc >> (14 - i)) & 1 for i in range(15)]
    stuff, run, last = 0, 0, None
    for b in bits:
        if b == last:
            run += 1
            if run == 5:
                stuff += 1
                last, run = 1 - b, 1       # the stuff bit starts a new run
                continue
        else:
            last, run = b, 1
    return len(bits) + stuff + 1 + 2 + 7 + 3     # CRC delimiter, ACK slot + delimiter, EOF, IFS


def simulate(bus_cfg, period_s: float, seconds: float, staggered: bool, seed: int = 1,
             sdo_gap_s: float = 0.0, torque_pdo: bool = True) -> dict:
    """Per-cycle demand on the busiest bus (us): median, p99, max, p99/median.

    ``sdo_gap_s`` > 0: also the master's decimated SDO uploads (torque sampling,
    ``hexacnc.daemon.torqueread``): one 8-byte request every ``sdo_gap_s`` over all buses, round robin,
    answered (8 bytes) in the next cycle.  ``torque_pdo``: with the drives' torque TPDO3 when ``[bus]
    torque_pdo_every`` is set (:mod:`drivers.torquepdo`, on its staggered SYNC count)."""
    rng = random.Random(seed)
    plan = plan_layout(bus_cfg)
    us_per_bit = 1e6 / bus_cfg.bitrate
    n_cycles = int(seconds / period_s)
    worst = None
    for b, group in enumerate(plan.bus_nodes):
        demand = [0.0] * n_cycles
        frames = [f for f in plan.frames if f.bus == b]
        nodes = [plan.nodes[i] for i in group]
        pos = {nd.index: rng.randrange(-2 ** 20, 2 ** 20) for nd in nodes}
        tq_every = torquepdo.every(bus_cfg) if torque_pdo else 0
        tq_first: dict[int, int] = {}             # the SYNC of each drive's first TPDO3 (its start value)

        def add(k: int, can_id: int, data: bytes) -> None:
            if 0 <= k < n_cycles:
                demand[k] += frame_bits(can_id, data) * us_per_bit

        for k in range(n_cycles):
            for nd in nodes:
                pos[nd.index] += rng.randrange(-400, 400)
            counter = (k % plan.sync_counter_overflow) + 1 if plan.sync_counter_overflow else 0
            add(k, 0x80, bytes([counter]) if plan.sync_length else b"")
            for f in frames:
                add(k, f.cob_id, b"".join(pos[i].to_bytes(4, "little", signed=True) for i, _ in f.slots)
                    + bytes(max(0, f.length - 4 * len(f.slots))))
            for nd in nodes:
                d = plan.feedback_divider
                if (nd.tpdo1_sync_start == 0 and k % d == 0) or (nd.tpdo1_sync_start and counter == nd.tpdo1_sync_start):
                    add(k, nd.tpdo1_cob_id, pos[nd.index].to_bytes(4, "little", signed=True))
                if tq_every:
                    f = tq_first.get(nd.index)
                    if f is None and nd.tpdo1_sync_start in (0, counter):
                        tq_first[nd.index] = f = k
                    if f is not None and (k - f) % tq_every == 0:
                        add(k, torquepdo.cob_id(nd.node_id), rng.randrange(-3000, 3000).to_bytes(2, "little", signed=True))

        def periodic(first_s: float, every_s: float, emit: Callable[[int], None]) -> None:
            t = first_s
            while t < seconds:
                emit(int(t / period_s))
                t += every_s

        for j, nd in enumerate(nodes):
            start = j * 0.0003 + rng.uniform(0, 0.0001)          # NMT start reaches the drives in turn
            ev = status_event_timer_ms(nd.index) if staggered else 50
            hb = heartbeat_producer_ms(bus_cfg.heartbeat_ms, nd.index) if staggered else bus_cfg.heartbeat_ms
            periodic(start + ev * 1e-3, ev * 1e-3, lambda k, nd=nd: add(k, nd.tpdo2_cob_id, (0x1637).to_bytes(2, "little")))
            periodic(start + hb * 1e-3, hb * 1e-3, lambda k, nd=nd: add(k, 0x700 + nd.node_id, b"\x05"))
        mhb = master_heartbeat_s(bus_cfg)          # as drivers.cyclic sends it while cycling
        periodic(rng.uniform(0, mhb), mhb, lambda k: add(k, 0x77F, b"\x05"))
        if sdo_gap_s > 0:
            _sdo_traffic(add, periodic, rng, nodes, sdo_gap_s * bus_cfg.buses, seconds)
        q = statistics.quantiles(demand, n=100)
        rep = {"bus": b, "median_us": round(statistics.median(demand), 1), "p99_us": round(q[98], 1),
               "p999_us": round(statistics.quantiles(demand, n=1000)[998], 1), "max_us": round(max(demand), 1),
               "cycles_with_async_frames": round(sum(1 for x in demand if x > statistics.median(demand) + 40)
                                                 / n_cycles, 4)}
        rep["p99_over_median"] = round(rep["p99_us"] / rep["median_us"], 4)
        if worst is None or rep["p99_us"] > worst["p99_us"]:
            worst = rep
    return worst


def _sdo_traffic(add, periodic, rng, nodes, every_s: float, seconds: float) -> None:
    """Sample requests (0x600 + node) every ``every_s`` on this bus, each answered (0x580 + node) a cycle later."""
    turn = [0]

    def emit(k: int) -> None:
        nd = nodes[turn[0] % len(nodes)]
        turn[0] += 1
        add(k, 0x600 + nd.node_id, bytes([0x40, 0x77, 0x60, 0, 0, 0, 0, 0]))
        add(k + 1, 0x580 + nd.node_id, bytes([0x4B, 0x77, 0x60, 0, rng.randrange(256), 0, 0, 0]))
    periodic(rng.uniform(0, every_s), every_s, emit)


def demand_report(bus_cfg, period_s: float, seconds: float = 10.0, sdo_gap_s: float = 0.0,
                  torque_pdo_every: int = 0) -> dict:
    """``hexacnc bus demand``: the layout, the bus period and :func:`simulate` for the configured (staggered)
    timers and for the former uniform ones.  With ``[bus] torque_pdo_every`` set, also the configured
    timers without the torque TPDO3 (``staggered_without_torque_pdo``); ``torque_pdo_every`` > 0: also
    with a torque TPDO3 every that many SYNCs (``staggered_with_torque_pdo``, a preview)."""
    out = {"layout": plan_layout(bus_cfg).layout, "bus_period_us": period_s * 1e6, "seconds": seconds,
           "staggered": simulate(bus_cfg, period_s, seconds, True),
           "uniform_timers": simulate(bus_cfg, period_s, seconds, False),
           **({"staggered_with_torque_sdo": simulate(bus_cfg, period_s, seconds, True, sdo_gap_s=sdo_gap_s),
               "torque_sdo_gap_s": sdo_gap_s} if sdo_gap_s > 0 else {})}
    if torquepdo.every(bus_cfg):
        out["torque_pdo_every"] = torquepdo.every(bus_cfg)
        out["staggered_without_torque_pdo"] = simulate(bus_cfg, period_s, seconds, True, torque_pdo=False)
    if torque_pdo_every > 0:
        cfg_t = dataclasses.replace(bus_cfg, torque_pdo_every=int(torque_pdo_every))
        out["staggered_with_torque_pdo"] = {**simulate(cfg_t, period_s, seconds, True),
                                            "torque_pdo_every": int(torque_pdo_every)}
    return out
