"""Worst-case CAN bus time per control cycle of a bus layout.

Frame times (11-bit identifiers):

* classic CAN, n data bytes: ``47 + 8n`` bits plus up to ``floor((33 + 8n) / 4)`` stuff bits;
* CAN FD with bit-rate switch: the arbitration and tail (SOF, ID, RRS, IDE, FDF, res, BRS;
  CRC delimiter, ACK, ACK delimiter, EOF, IFS = 30 bits, up to 4 stuff bits) at the nominal
  rate, the data phase (ESI, DLC, 8n data bits, 4-bit stuff count, CRC-17 (n <= 16) or CRC-21,
  fixed stuff bits ``ceil((4 + crc) / 4)``, up to ``floor((5 + 8n) / 4)`` dynamic stuff bits)
  at ``[bus] data_bitrate``.

Per bus and cycle the budget counts: SYNC (1 counter byte when the feedback is staggered),
the RPDO1 frames of the layout, ceil(k / feedback_divider) TPDO1 feedback frames (staggered by
SYNC start value), and one asynchronous frame of up to 2 bytes (a heartbeat, a controlword or
statusword event, an NMT command: all lower priority than the cyclic frames, so one of them
can at worst block the cycle once, and their average rate is far below one per cycle).
EMCY (8 bytes) is reported apart (``fault_frame_us``): it is sent only by a faulting drive,
which ends cyclic motion. SDO traffic is not allowed while cycling.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

from .errors import BusError

from .description import bus_period_s
from .cyclicdefs import master_heartbeat_s
from .layout import heartbeat_producer_ms, plan_layout, status_event_timer_ms
from . import torquepdo

ASYNC_RESERVE_BYTES = 2
EMCY_BYTES = 8


def classic_frame_bits(n: int) -> tuple[int, int]:
    """(min, max) bits of a classic base-format data frame with ``n`` bytes."""
    if not 0 <= n <= 8:
        raise ValueError(f"classic CAN frame cannot carry {n} bytes")
    bits = 47 + 8 * n
    return bits, bits + (33 + 8 * n) // 4


def fd_frame_bits(n: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """((nominal min, max), (data-phase min, max)) bits of a CAN FD frame with ``n`` bytes."""
    crc = 17 if n <= 16 else 21
    nominal = 30
    data = 1 + 4 + 8 * n + 4 + crc + math.ceil((4 + crc) / 4)
    return (nominal, nominal + 4), (data, data + (5 + 8 * n) // 4)


def frame_time_us(n: int, bitrate: int, fd: bool = False, data_bitrate: int | None = None,
                  brs: bool = True) -> tuple[float, float]:
    """(min, max) microseconds on the wire for a frame with ``n`` data bytes."""
    if not fd:
        lo, hi = classic_frame_bits(n)
        return lo * 1e6 / bitrate, hi * 1e6 / bitrate
    (nlo, nhi), (dlo, dhi) = fd_frame_bits(n)
    dr = (data_bitrate or bitrate) if brs else bitrate
    return nlo * 1e6 / bitrate + dlo * 1e6 / dr, nhi * 1e6 / bitrate + dhi * 1e6 / dr


def bus_time(bus_cfg, period_s: float) -> dict[str, Any]:
    """Report of the worst-case bus time per cycle (see module doc). Never raises for load."""
    plan = plan_layout(bus_cfg)
    br, dbr = bus_cfg.bitrate, bus_cfg.data_bitrate
    loop_period_s = period_s
    period_s = bus_period_s(bus_cfg, period_s)      # whole ms for drives that take only 0x60C2 index -3
    period_us = period_s * 1e6

    def row(name, cob_id, nbytes, fd, count=1):
        lo, hi = frame_time_us(nbytes, br, fd, dbr)
        return {"frame": name, "cob_id": cob_id, "bytes": nbytes, "fd": fd, "count": count,
                "min_us": round(lo * count, 3), "max_us": round(hi * count, 3)}

    per_bus = []
    for b, group in enumerate(plan.bus_nodes):
        ids = [bus_cfg.node_ids[i] for i in group]
        rows = [row("SYNC", 0x80, plan.sync_length, False)]
        for f in plan.frames:
            if f.bus == b:
                who = "+".join(str(bus_cfg.node_ids[i]) for i, _ in f.slots)
                rows.append(row(f"RPDO1 targets node {who}", f.cob_id, f.length, f.fd))
        command_min = sum(r["min_us"] for r in rows)
        command_max = sum(r["max_us"] for r in rows)
        ntp = plan.tpdo_per_cycle(b)
        rows.append(row(f"TPDO1 position actual ({ntp} of {len(group)} per cycle)", 0x180 + ids[0], 4,
                        plan.fd, ntp))
        rows.append(row("async reserve (heartbeat / controlword / statusword / NMT)", 0x700, ASYNC_RESERVE_BYTES,
                        False))
        lo = sum(r["min_us"] for r in rows)
        hi = sum(r["max_us"] for r in rows)
        per_bus.append({
            "bus": b, "node_ids": ids, "frames": rows,
            "command_min_us": round(command_min, 3), "command_max_us": round(command_max, 3),
            "min_us": round(lo, 3), "max_us": round(hi, 3),
            "load_min": round(lo / period_us, 4), "load_max": round(hi / period_us, 4),
            "feedback_period_s": period_s * bus_cfg.feedback_divider,
        })
    worst = max(per_bus, key=lambda p: p["max_us"])
    emcy = frame_time_us(EMCY_BYTES, br, False)
    n = len(bus_cfg.node_ids)
    hb_rate = sum(1000.0 / heartbeat_producer_ms(bus_cfg.heartbeat_ms, i) for i in range(n)) \
        + 1.0 / master_heartbeat_s(bus_cfg)
    status_rate = sum(1000.0 / status_event_timer_ms(i) for i in range(n))
    torque = torquepdo.budget(bus_cfg, plan, period_us, per_bus, hb_rate + status_rate,
                              lambda nb: frame_time_us(nb, br), ASYNC_RESERVE_BYTES)
    return {
        "layout": plan.layout, "requested_layout": plan.requested_layout or bus_cfg.layout,
        "layout_note": plan.note, "bitrate": br, "fd": bool(bus_cfg.fd), "data_bitrate": dbr,
        "buses": bus_cfg.buses, "feedback_divider": bus_cfg.feedback_divider,
        "period_us": round(period_us, 3), "max_load": bus_cfg.max_load,
        "loop_period_us": round(loop_period_s * 1e6, 3), "sync_every": int(round(period_s / loop_period_s)),
        "min_us": worst["min_us"], "max_us": worst["max_us"],
        "load": round(worst["max_us"] / period_us, 4),
        "fits": worst["max_us"] <= bus_cfg.max_load * period_us + 1e-9 and (torque is None or torque["fits"]),
        "worst_bus": worst["bus"],
        "fault_frame_us": round(emcy[1], 3),
        "async_frames_per_s": round(hb_rate + status_rate, 1),
        "per_bus": per_bus,
        **({"torque_pdo": torque} if torque is not None else {}),
    }


def _split(cfg, period_s):
    if hasattr(cfg, "bus") and hasattr(cfg, "cycle"):
        return cfg.bus, (period_s if period_s is not None else cfg.cycle.period_s)
    if period_s is None:
        raise TypeError("check_layout(bus_cfg, period_s): period_s is required with a BusConfig")
    return cfg, period_s


def describe(report: dict[str, Any]) -> str:
    """One-line human summary of a :func:`bus_time` report."""
    return (f"layout {report['layout']!r}"
            + (f" (instead of {report['requested_layout']!r}: no dummy mapping)"
               if report.get("requested_layout", report["layout"]) != report["layout"] else "")
            + f" at {report['bitrate'] / 1e6:g} Mbit/s"
            + (f" (FD data {report['data_bitrate'] / 1e6:g} Mbit/s)" if report["fd"] else "")
            + f" on {report['buses']} bus(es), feedback every {report['feedback_divider']} cycle(s): "
            f"{report['min_us']:.0f}-{report['max_us']:.0f} us per cycle on the busiest bus = "
            f"{100 * report['load']:.1f} % of the {report['period_us']:.0f} us period "
            f"(limit [bus] max_load {100 * report['max_load']:.0f} %)"
            + (f"; the bus runs at {report['period_us'] / 1e3:g} ms (0x60C2) while the loop computes at "
               f"{report['loop_period_us'] / 1e3:g} ms" if report.get("sync_every", 1) > 1 else "")
            + (f"; drive torque TPDO3 every {report['torque_pdo']['every_syncs']} SYNCs "
               f"({'fits' if report['torque_pdo']['fits'] else 'does not fit'}: blocking within the reserve, "
               "sent in the idle time)" if "torque_pdo" in report else ""))


def check_layout(cfg, period_s: float | None = None) -> dict[str, Any]:
    """Check the configured layout; raise :class:`BusError` with the figures when it does not fit.

    ``cfg`` is a :class:`hexacnc.config.MachineConfig` (period from ``[cycle] period_s``) or a
    ``BusConfig`` with ``period_s``. Returns the :func:`bus_time` report.
    """
    bus_cfg, period = _split(cfg, period_s)
    report = bus_time(bus_cfg, period)
    if not report["fits"]:
        fits = suggest_layouts(bus_cfg, period)
        hint = "; layouts that fit: " + ", ".join(s["name"] for s in fits[:5]) if fits else \
            "; no layout fits this period: lengthen [cycle] period_s"
        raise BusError("bus layout does not fit the cycle: " + describe(report) + hint)
    return report


def suggest_layouts(cfg, period_s: float | None = None, max_load: float | None = None) -> list[dict[str, Any]]:
    """Variants of the configured bus (layout, buses, divider, FD) that fit, best first.

    Each entry: ``name`` (config keys to set), ``changes`` (dict of [bus] keys), ``max_us``, ``load``.
    Order: fewest buses, then fastest feedback (smallest divider), then lowest load.
    """
    bus_cfg, period = _split(cfg, period_s)
    limit = bus_cfg.max_load if max_load is None else max_load
    out = []
    for fd in ((False, True) if not bus_cfg.fd else (True,)):
        for layout in ("single", "paired", "separate", "fd"):
            if layout == "fd" and not fd:
                continue
            for buses in range(1, len(bus_cfg.node_ids) + 1):
                for div in (1, 2, 3, 6):
                    changes = {"layout": layout, "buses": buses, "feedback_divider": div, "fd": fd,
                               "max_load": limit}
                    try:
                        cand = dataclasses.replace(bus_cfg, **changes)
                        rep = bus_time(cand, period)
                    except BusError:
                        continue
                    if rep["fits"]:
                        changes.pop("max_load")
                        name = ", ".join(f"{k} = {str(v).lower() if isinstance(v, bool) else repr(v)}"
                                         for k, v in changes.items())
                        out.append({"name": name, "changes": changes, "max_us": rep["max_us"],
                                    "load": rep["load"]})
                        break   # smallest divider that fits for this (layout, buses, fd)
    # per (fd, layout): the fewest buses that fit, and one more bus when it buys faster feedback
    fewest: dict[tuple, int] = {}
    for s in out:
        key = (s["changes"]["fd"], s["changes"]["layout"])
        fewest[key] = min(fewest.get(key, 99), s["changes"]["buses"])
    out = [s for s in out if s["changes"]["buses"] <= fewest[(s["changes"]["fd"], s["changes"]["layout"])] + 1]
    out.sort(key=lambda s: (s["changes"]["buses"], s["changes"]["fd"], s["changes"]["feedback_divider"],
                            s["load"]))
    return out


def load_report(bus_cfg, period_s: float) -> dict[str, Any]:
    """``hexacnc bus load``: the :func:`bus_time` report with its one-line ``summary`` and the fitting
    layouts (``suggestions``, :func:`suggest_layouts`)."""
    rep = bus_time(bus_cfg, period_s)
    rep["summary"] = describe(rep)
    rep["suggestions"] = suggest_layouts(bus_cfg, period_s)
    return rep
