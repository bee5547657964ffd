"""Commissioning steps of the master, before any drive is enabled (pre-operational, SDO only):

* :func:`check_identity` - 0x1000, 0x1018, 0x6502 against the node's description and the config;
* :func:`set_interpolation_period` - 0x60C2 in a format the description allows (index searched
  from -3 to -6 within the EDS limits), read back; the bus period may be a multiple of the loop's;
* :func:`configure_units` - factor group 0x608F / 0x6091 / 0x6092 read (or 0x6092 written) and
  compared with ``[bus] increments_per_mm`` x ``[bus] feed_mm_per_rev``;
* :func:`configure_reactions` - communication-loss and fault reactions (0x1006, 0x6007, 0x1029,
  0x605A, 0x605C, 0x605E; the quick stop 0x6085 and profile jerk 0x60A4:1 at ``STOP_SHARE`` of the
  strut limits) written and read back.

Each function takes the :class:`drivers.master.Master` (its ``sdo_read``/``sdo_write`` name the node,
the step and the object in every error) and returns a plain dict for the boot report.
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from canopen.sdo.exceptions import SdoAbortedError

from .errors import BusError

from . import cia402
from .jerkstop import STOP_SHARE
from .description import bus_period_s, expected_identity, identity_problems, interpolation_candidates, modes_text

if TYPE_CHECKING:
    from .master import Master

log = logging.getLogger("hexacnc.master")

ABORT_VALUE_RANGE = 0x06090030

#: what the master configures (CiA 402 option codes, see drivers.cia402)
ABORT_CONNECTION_OPTION = cia402.ABORT_QUICK_STOP
COMM_ERROR_BEHAVIOUR = cia402.COMM_ERROR_NO_CHANGE
QUICK_STOP_OPTION = cia402.QS_QUICK_RAMP_DISABLE
DISABLE_OPERATION_OPTION = cia402.DISABLE_OP_SLOW_DOWN
FAULT_REACTION_OPTION = cia402.FAULT_REACTION_QUICK_RAMP


# -- identity ------------------------------------------------------------------------------------
def read_identity(m: "Master", nd, optional_strings: bool = True) -> dict:
    """What node ``nd`` reports: device type, identity, supported modes (+ version strings, heartbeat)."""
    r = m.sdo_read
    out = {"node_id": nd.node_id,
           "device_type": r(nd, "identity check", 0x1000),
           "vendor_id": r(nd, "identity check", 0x1018, 1),
           "product_code": r(nd, "identity check", 0x1018, 2),
           "revision": r(nd, "identity check", 0x1018, 3),
           "serial": m.sdo_read_optional(nd, 0x1018, 4),
           "supported_modes": r(nd, "identity check", 0x6502)}
    if optional_strings:
        out["hardware_version"] = m.sdo_read_optional(nd, 0x1009)
        out["software_version"] = m.sdo_read_optional(nd, 0x100A)
        out["heartbeat_ms"] = m.sdo_read_optional(nd, 0x1017)
    return out


def check_identity(m: "Master") -> list[dict]:
    """Read and compare every node's identity; BusError naming node, object, expected and found."""
    report = []
    for nd in m.plan.nodes:
        desc = m.descriptions[nd.index]
        found = read_identity(m, nd)
        found["description"] = desc.path
        problems = identity_problems(found, expected_identity(m.bus_cfg, nd.index, desc), desc)
        if problems:
            raise m.fail(nd, "identity check", "; ".join(problems) + f" (description {desc.path})")
        log.info("%s: device type 0x%08X, vendor 0x%08X product 0x%08X revision 0x%08X, modes %s, "
                 "firmware %r", m.who(nd), found["device_type"], found["vendor_id"], found["product_code"],
                 found["revision"], modes_text(found["supported_modes"]), found.get("software_version"))
        report.append(found)
    return report


# -- interpolation time period 0x60C2 --------------------------------------------------------------
def set_interpolation_period(m: "Master", period_s: float) -> dict:
    """Write 0x60C2 to every drive in the first format all of them accept, read it back.

    Candidates come from the intersection of the descriptions' index ranges; an SDO abort moves to
    the next candidate (logged); a value read back different from the one written, or no candidate
    left, is a BusError naming the node, what was tried and the abort codes."""
    lo = max(d.ip_index_range[0] for d in m.descriptions)
    hi = min(d.ip_index_range[1] for d in m.descriptions)
    if lo > hi:
        raise BusError(f"the drive descriptions allow no common 0x60C2 index ({[d.ip_index_range for d in m.descriptions]})")
    tried = []
    for value, idx, bus_period in interpolation_candidates(period_s, (lo, hi)):
        refused = None
        for nd in m.plan.nodes:
            try:
                m.sdo_write_raw(nd, 0x60C2, 1, value)
                m.sdo_write_raw(nd, 0x60C2, 2, idx)
            except SdoAbortedError as exc:
                refused = (nd, exc.code)
                break
        if refused is not None:
            tried.append(f"({value}, {idx}) refused by node {refused[0].node_id} with SDO abort 0x{refused[1]:08X}")
            log.info("0x60C2 = (%d, %d) = %g s refused by node %d (abort 0x%08X); trying the next format",
                     value, idx, bus_period, refused[0].node_id, refused[1])
            continue
        for nd in m.plan.nodes:
            back = (m.sdo_read(nd, "interpolation period read-back", 0x60C2, 1),
                    m.sdo_read(nd, "interpolation period read-back", 0x60C2, 2))
            if back != (value, idx):
                raise m.fail(nd, "interpolation period", f"0x60C2 written ({value}, {idx}), read back {back}")
        every = int(round(bus_period / period_s))
        if abs(bus_period - bus_period_s(m.bus_cfg, period_s)) > 1e-12:
            from .busload import check_layout     # not the period checked before the boot: check again
            check_layout(m.bus_cfg, bus_period)
        log.info("0x60C2 interpolation period (%d, %d) = %g ms on every drive: the bus runs at %g ms%s",
                 value, idx, bus_period * 1e3, bus_period * 1e3,
                 "" if every == 1 else f", the loop computes at {period_s * 1e3:g} ms (SYNC every {every} cycles)")
        return {"value": value, "index": idx, "bus_period_s": bus_period, "sync_every": every, "refused": tried}
    raise BusError(f"no 0x60C2 interpolation period format accepted for [cycle] period_s = {period_s:g} s "
                   f"(description index range {lo}..{hi}): " + "; ".join(tried))


# -- units (factor group) --------------------------------------------------------------------------
def configure_units(m: "Master") -> list[dict]:
    """Factor group per node. With ``[bus] write_factor_group`` and ``feed_mm_per_rev`` the feed
    constant 0x6092 is written as (round(increments_per_mm x feed_mm_per_rev), 1). With
    ``feed_mm_per_rev`` > 0 the drive's position units per mm (feed / shaft revolutions / lead) must
    equal ``increments_per_mm`` (0.01 % tolerance), else BusError. Nodes whose description lacks
    the factor group are reported as such (and refused when ``feed_mm_per_rev`` asks for a check)."""
    b = m.bus_cfg
    lead = float(getattr(b, "feed_mm_per_rev", 0.0))
    out = []
    for nd in m.plan.nodes:
        desc = m.descriptions[nd.index]
        if not all(desc.has(i) for i in (0x608F, 0x6091, 0x6092)):
            if lead > 0:
                raise m.fail(nd, "units", f"[bus] feed_mm_per_rev = {lead:g} needs the factor group 0x608F/0x6091/"
                                          f"0x6092, which {desc.path} does not describe")
            out.append({"node_id": nd.node_id, "factor_group": None})
            continue
        if getattr(b, "write_factor_group", False) and lead > 0:
            feed = int(round(b.increments_per_mm * lead))
            m.sdo_write(nd, "units: feed constant", 0x6092, 1, feed)
            m.sdo_write(nd, "units: feed constant", 0x6092, 2, 1)
        r = m.sdo_read
        enc = (r(nd, "units", 0x608F, 1), r(nd, "units", 0x608F, 2))
        gear = (r(nd, "units", 0x6091, 1), r(nd, "units", 0x6091, 2))
        feed = (r(nd, "units", 0x6092, 1), r(nd, "units", 0x6092, 2))
        if 0 in enc or 0 in gear or 0 in feed:
            raise m.fail(nd, "units", f"factor group has a zero: 0x608F {enc}, 0x6091 {gear}, 0x6092 {feed}")
        units_per_rev = feed[0] / feed[1]
        rep = {"node_id": nd.node_id, "encoder_increments_per_motor_rev": enc[0] / enc[1],
               "motor_revs_per_shaft_rev": gear[0] / gear[1], "units_per_shaft_rev": units_per_rev}
        if lead > 0:
            per_mm = units_per_rev / lead
            rep["units_per_mm"] = per_mm
            if abs(per_mm - b.increments_per_mm) > 1e-4 * b.increments_per_mm:
                raise m.fail(nd, "units", f"0x6092 feed constant {feed[0]}/{feed[1]} units per shaft revolution with "
                             f"[bus] feed_mm_per_rev = {lead:g} gives {per_mm:g} units/mm, but [bus] increments_per_mm "
                             f"= {b.increments_per_mm:g} (set write_factor_group = true or fix the config)")
        out.append(rep)
    return out


# -- communication-loss and fault reactions --------------------------------------------------------
#: objects a drive may lack although its description lists them (a refusal is logged, not fatal)
OPTIONAL_OBJECTS = frozenset({0x60A4})


def stop_ramp_objects(cfg, bus_cfg, strut: int) -> list[tuple]:
    """The drive's own quick stop within the strut's limits, at :data:`drivers.jerkstop.STOP_SHARE`
    of them as the loop's controlled stop: 0x6085 quick-stop deceleration and 0x60A4:1 profile jerk
    (the simulated drives ramp jerk-limited with it), in position units."""
    ipm = float(bus_cfg.increments_per_mm)
    dec = int(round(STOP_SHARE * float(cfg.max_acceleration_mm_s2[strut]) * ipm))
    jerk = int(round(STOP_SHARE * float(cfg.max_jerk_mm_s3[strut]) * ipm))
    return [(0x6085, None, max(1, min(0xFFFFFFFF, dec)), "quick stop deceleration"),
            (0x60A4, 1, max(1, min(0xFFFFFFFF, jerk)), "profile jerk 1")]


def configure_reactions(m: "Master", bus_period_s: float) -> list[dict]:
    """Write the reactions each description supports and read every one back (BusError on a
    difference). RPDO event timers (comm loss) and the heartbeat consumer are written with the PDO
    mapping / heartbeats (:meth:`Master.configure`); they are read back here too."""
    out = []
    for nd in m.plan.nodes:
        desc = m.descriptions[nd.index]
        want = [(0x1006, None, int(round(bus_period_s * 1e6)), "communication cycle period (us)"),
                (0x6007, None, ABORT_CONNECTION_OPTION, "abort connection option"),
                (0x1029, 1, COMM_ERROR_BEHAVIOUR, "error behaviour: communication"),
                (0x605A, None, QUICK_STOP_OPTION, "quick stop option"),
                (0x605C, None, DISABLE_OPERATION_OPTION, "disable operation option"),
                (0x605E, None, FAULT_REACTION_OPTION, "fault reaction option"),
                *stop_ramp_objects(m.cfg, m.bus_cfg, nd.index)]
        if desc.has_bundled(0x2010):        # the bundled EDS's SYNC-loss time-out = the RPDO deadline
            want.append((0x2010, None, m.comm_loss_ms(), "SYNC-loss time-out (ms)"))
        rep = {"node_id": nd.node_id, "missing": []}
        refused = set()
        for index, sub, value, name in want:
            if not desc.has(index):
                rep["missing"].append(f"0x{index:04X}")
                continue
            try:
                m.sdo_write(nd, name, index, sub, value)
            except BusError as exc:
                if index not in OPTIONAL_OBJECTS:
                    raise
                refused.add(index)          # described but not in the drive: its ramps stay trapezoids
                rep["missing"].append(f"0x{index:04X}")
                log.warning("%s: %s; its quick stop ramps without a jerk limit", m.who(nd), exc)
        for index, sub, value, name in want:
            if not desc.has(index) or index in refused:
                continue
            back = m.sdo_read(nd, f"{name} read-back", index, sub)
            if back != value:
                raise m.fail(nd, name, f"0x{index:04X} written {value}, read back {back}")
            rep[f"0x{index:04X}" + (f":{sub}" if sub else "")] = back
        rep["0x6085_quick_stop_decel"] = m.sdo_read_optional(nd, 0x6085)
        rep["rpdo1_event_timer_ms"] = m.sdo_read(nd, "RPDO1 event timer read-back", 0x1400, 5)
        rep["heartbeat_consumer"] = m.sdo_read(nd, "heartbeat consumer read-back", 0x1016, 1)
        if desc.has_bundled(0x2110):        # the drive manages its brake: the disable walk waits for it
            rep["brake_release_ms"] = m.sdo_read(nd, "brake release delay", 0x2110, 1)
            rep["brake_engage_ms"] = m.sdo_read(nd, "brake engage delay", 0x2110, 2)
        if 0x6007 not in desc.objects:
            log.warning("%s: no 0x6007 in %s: the drive's reaction to a silent master is its own default",
                        m.who(nd), desc.path)
        out.append(rep)
    return out
