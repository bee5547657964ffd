"""Find every CANopen node on the drive bus(es) and compare it with the configuration (commissioning).

SDO reads only (no NMT command, nothing enabled): an SDO upload of 0x1000 to every node id 1..127
(canopen's scanner), the heartbeats heard meanwhile, then per node found 0x1000 device type, 0x1018
identity, 0x6502 supported modes, 0x1008/0x1009/0x100A name and version strings, 0x1017 heartbeat.
Each configured node gets ``match`` true/false with the differences (object, expected, found) from
:func:`drivers.description.identity_problems`; nodes not in ``[bus] node_ids`` are listed as extra.
"""
from __future__ import annotations

import time
from typing import Sequence

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from .description import expected_identity, identity_problems, modes_text, node_descriptions
from .layout import plan_layout

_U32 = ("device_type", 0x1000, 0), ("vendor_id", 0x1018, 1), ("product_code", 0x1018, 2), \
    ("revision", 0x1018, 3), ("serial", 0x1018, 4), ("supported_modes", 0x6502, 0)
_STR = ("device_name", 0x1008), ("hardware_version", 0x1009), ("software_version", 0x100A)


def _upload(node, index: int, sub: int):
    try:
        return node.sdo.upload(index, sub)
    except (SdoAbortedError, SdoCommunicationError):
        return None


def read_node(net: canopen.Network, node_id: int, sdo_timeout_s: float = 0.3) -> dict:
    """What node ``node_id`` reports (None for objects it lacks or does not answer)."""
    node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
    node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
    net.add_node(node)
    try:
        out: dict = {"node_id": node_id}
        for key, index, sub in _U32:
            raw = _upload(node, index, sub)
            out[key] = int.from_bytes(raw[:4], "little") if raw else None
        for key, index in _STR:
            raw = _upload(node, index, 0)
            out[key] = raw.decode("latin-1").rstrip("\0") if raw else None
        raw = _upload(node, 0x1017, 0)
        out["heartbeat_ms"] = int.from_bytes(raw[:2], "little") if raw else None
        if out["supported_modes"] is not None:
            out["modes"] = modes_text(out["supported_modes"])
        return out
    finally:
        del net[node_id]


def scan(buses: Sequence[can.BusABC], bus_cfg, listen_s: float = 0.5, sdo_timeout_s: float = 0.3) -> dict:
    """Scan ``buses`` (one per ``[bus] buses``). Returns ``{"nodes": [...], "all_match": bool}``: one
    entry per node found or configured, with ``bus``, ``configured``, ``found``, ``match``, ``problems``,
    ``heartbeat_state`` (last NMT state heard) and what :func:`read_node` read."""
    plan = plan_layout(bus_cfg)
    descs = node_descriptions(bus_cfg)
    nets = [canopen.Network(b) for b in buses]
    heard: dict[tuple[int, int], int] = {}
    for b, net in enumerate(nets):
        net.notifier = can.Notifier(net.bus, net.listeners, 0.05)
        for nid in range(1, 128):
            net.subscribe(0x700 + nid, lambda cob, data, ts, b=b: heard.__setitem__((b, cob - 0x700), data[0] & 0x7F
                                                                                   if data else -1))
    try:
        for net in nets:
            net.scanner.reset()
            net.scanner.search()
        time.sleep(listen_s)
        found = {(b, nid) for b, net in enumerate(nets) for nid in net.scanner.nodes}
        found |= set(heard)
        where = {nd.node_id: nd for nd in plan.nodes}
        out = []
        for b, nid in sorted(found | {(nd.bus, nd.node_id) for nd in plan.nodes}):
            nd = where.get(nid)
            entry = {"bus": b, "node_id": nid, "configured": nd is not None and nd.bus == b,
                     "found": (b, nid) in found, "heartbeat_state": heard.get((b, nid))}
            if entry["found"]:
                entry.update(read_node(nets[b], nid, sdo_timeout_s))
            if entry["configured"]:
                desc = descs[nd.index]
                entry["strut"] = nd.index + 1
                entry["description"] = desc.path
                if entry["found"]:
                    entry["problems"] = identity_problems(entry, expected_identity(bus_cfg, nd.index, desc), desc)
                    missing = [k for k in ("device_type", "vendor_id", "supported_modes") if entry.get(k) is None]
                    entry["problems"] += [f"{k}: no SDO answer" for k in missing]
                else:
                    entry["problems"] = ["not found on the bus"]
                entry["match"] = not entry["problems"]
            out.append(entry)
        return {"nodes": out, "all_match": all(e.get("match", True) for e in out if e["configured"])}
    finally:
        for net in nets:
            if net.notifier is not None:
                net.notifier.stop(1.0)
                net.notifier = None


def format_scan(result: dict) -> str:
    """Human-readable table of a :func:`scan` result."""
    lines = ["bus node strut  device type  vendor     product    revision   modes            firmware / hardware"
             "                 heartbeat  config"]
    for e in result["nodes"]:
        def h(k):
            v = e.get(k)
            return f"0x{v:08X}" if isinstance(v, int) else "-".ljust(10)
        hb = f"{e['heartbeat_ms']} ms" if e.get("heartbeat_ms") is not None else "-"
        fw = f"{e.get('software_version') or '-'} / {e.get('hardware_version') or '-'}"
        verdict = ("match" if e.get("match") else "MISMATCH: " + "; ".join(e.get("problems", []))) \
            if e["configured"] else "not in [bus] node_ids"
        lines.append(f"{e['bus']:>3} {e['node_id']:>4} {str(e.get('strut', '-')):>5}  {h('device_type')}   "
                     f"{h('vendor_id')} {h('product_code')} {h('revision')} {(e.get('modes') or '-'):<16} "
                     f"{fw:<36} {hb:>9}  {verdict}")
    lines.append("all configured nodes match" if result["all_match"] else "configuration does NOT match the bus")
    return "\n".join(lines)
