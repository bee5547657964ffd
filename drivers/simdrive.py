"""Simulated CiA 402 strut drives: six CANopen nodes built from ``hexapod_drive.eds``.

canopen's ``LocalNode`` answers SDO, NMT and produces the heartbeat; everything else is done
here: RPDOs applied per the SDO-configured mapping (synchronous ones latched until SYNC,
asynchronous ones at once), TPDOs sent on SYNC (transmission type, SYNC counter start value) and
on statusword change (inhibit time, event timer), the CiA 402 state machine
(:mod:`drivers.cia402`), software position limits (0x607D), following error supervision
(0x6065 window, 0x6066 time-out -> EMCY 0x8611 + Fault), consumer heartbeat of the master
(0x1016 -> EMCY 0x8130 + Fault) and fault injection.

Each strut moves through a pluggable model (:class:`StrutModel`): by default
:class:`SecondOrderStrut`, a second-order position loop with velocity feed-forward, velocity and
acceleration limits, stepped once per SYNC by the interpolation period 0x60C2.

Fault injection (manufacturer object 0x2000, or ``--fault`` / ``faults=``):

=========== ====================== =========================================================
 0x2000 sub  spec (``--fault``)     effect
=========== ====================== =========================================================
 1 (+2)      ``N:emcy:CODE@T``       EMCY CODE and Fault, T s after the drive is enabled
 3           ``N:heartbeat@T``       stop producing the heartbeat
 4           ``N:stuck@T``           strut stuck: following error grows -> EMCY 0x8611, Fault
 5           ``N:refuse``            drive refuses transition 4 (stays Switched on)
=========== ====================== =========================================================

``N`` is the node id; via SDO, sub 2 is a delay in ms from the write.

``SimDrives(cfg, buses, model_factory=..., start_positions_inc=...).start()`` / ``.stop()``; the values that
come from the machine description (strut model of ``[dynamics] simulated_drives``, readings at the home
pose) are computed by the host (:mod:`hexacnc.sim.drives`, which also runs the drives as a process):
this layer imports nothing from ``hexacnc``.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from typing import Sequence

import can
import canopen

from .errors import ConfigError
from .framerec import DATA_OFFSET, F_EXT, F_RTR, HEADER, RECORD, supports_batch

from . import EDS_PATH
from .description import STRICT_EDS, load_description
from .layout import plan_layout
from .simreact import TICK_S
from .simnode import FaultSpec, SimDrive
from . import simhoming  # noqa: F401  (registers homing mode 6 in simhooks.EXTENSIONS)
from . import simdio  # noqa: F401  (registers 0x60FD/0x60FE digital I/O in simhooks.EXTENSIONS)
from . import simtorque  # noqa: F401  (registers 0x6077 / 0x6078 in simhooks.EXTENSIONS)
from .strutmodel import ModelFactory, SecondOrderStrut, StrutModel, default_model_factory, load_model_factory

__all__ = ["SimDrives", "SimDrive", "FaultSpec", "StrutModel", "SecondOrderStrut", "ModelFactory",
           "default_model_factory", "load_model_factory"]

log = logging.getLogger("hexacnc.simdrive")

#: how often the record reader looks for frames when a bus names no ``poll_interval_s`` (s)
RX_POLL_S = 0.0002
#: records taken from one bus before the next bus's turn (~2-3 cycles of the default layout's frames)
RX_BATCH = 16


# --------------------------------------------------------------------------------------------
# the six drives
# --------------------------------------------------------------------------------------------
def _nothing_pending() -> int:
    """``pending_records`` of a bus that cannot tell (python-can's own buses)."""
    return 0


class SimDrives:
    """Six simulated drives on ``buses`` (one bus object per ``[bus] buses``, strut split per layout).

    ``cfg``: the machine config (its ``bus`` section, ``max_*`` strut limits; read, never imported);
    ``model_factory(strut, cfg) -> StrutModel``; ``start_positions_inc``: initial drive readings (6);
    ``faults``: FaultSpecs.
    """

    def __init__(self, cfg, buses: can.BusABC | Sequence[can.BusABC], *,
                 model_factory: ModelFactory, start_positions_inc: Sequence[int],
                 faults: Sequence[FaultSpec] = (), eds_path=None):
        """``eds_path``: description of the simulated drives; default per ``[bus] simulate_profile``
        (``permissive``: hexapod_drive.eds, ``strict``: strict_drive.eds)."""
        if isinstance(buses, can.BusABC):
            buses = [buses]
        self.cfg = cfg
        self.plan = plan_layout(cfg.bus)
        if len(buses) != self.plan.buses:
            raise ValueError(f"SimDrives: {len(buses)} bus objects for [bus] buses = {self.plan.buses}")
        self.buses = list(buses)
        self.profile = getattr(cfg.bus, "simulate_profile", "permissive")
        if eds_path is None:
            eds_path = STRICT_EDS if self.profile == "strict" else EDS_PATH
        self.eds_path = str(eds_path)
        self.dummies = load_description(self.eds_path).dummies
        self.lock = threading.RLock()
        self.increments_per_mm = cfg.bus.increments_per_mm
        if len(start_positions_inc) != len(self.plan.nodes):
            raise ValueError(f"SimDrives: {len(start_positions_inc)} start positions for {len(self.plan.nodes)} drives")
        factory = model_factory
        self.networks = [canopen.Network(b) for b in self.buses]
        self._hb_subs: list[list] = [[] for _ in self.buses]
        self.drives: list[SimDrive] = []
        self.by_node: dict[int, SimDrive] = {}
        for nd in self.plan.nodes:
            od = canopen.import_od(str(eds_path), nd.node_id)
            d = SimDrive(self, nd.index, nd.node_id, nd.bus, factory(nd.index, cfg),
                         int(start_positions_inc[nd.index]), od)
            self.networks[nd.bus].add_node(d.node)
            self.drives.append(d)
            self.by_node[nd.node_id] = d
        for f in faults:
            d = self.by_node.get(f.node_id)
            if d is None:
                raise ConfigError(f"fault {f}: node {f.node_id} is not in [bus] node_ids {list(cfg.bus.node_ids)}")
            if f.kind == "refuse":
                d.refuse = True
            else:
                d.pending_faults.append(f)
        for b, net in enumerate(self.networks):
            net.subscribe(0x000, self._make_nmt_handler(b))
            net.subscribe(0x080, self._make_sync_handler(b))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._rx: threading.Thread | None = None
        self._fd = self.plan.fd

    def _make_nmt_handler(self, b: int):
        drives = [d for d in self.drives if d.bus_index == b]

        def handler(can_id, data, timestamp):
            if len(data) < 2:
                return
            cmd, nid = data[0], data[1]
            with self.lock:
                for d in drives:
                    if nid in (0, d.node_id):
                        try:
                            d.on_nmt(cmd)
                        except Exception:
                            log.exception("node %d NMT 0x%02X", d.node_id, cmd)
        return handler

    def _make_sync_handler(self, b: int):
        drives = [d for d in self.drives if d.bus_index == b]

        def handler(can_id, data, timestamp):
            counter = data[0] if len(data) else 0
            now = time.monotonic()
            with self.lock:
                for d in drives:
                    try:
                        d.on_sync(counter, now)
                    except Exception:
                        log.exception("node %d SYNC", d.node_id)
        return handler

    def _on_master_heartbeat(self, can_id, data, timestamp):
        now = time.monotonic()
        with self.lock:
            for d in self.drives:
                if d._consumer[0] == can_id - 0x700:
                    d.master_hb_s = now

    def send(self, bus_index: int, cob_id: int, data: bytes) -> None:
        msg = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False,
                          is_fd=self._fd, bitrate_switch=self._fd)
        try:
            self.buses[bus_index].send(msg)
        except can.CanError as exc:
            log.warning("bus %d: cannot send 0x%03X: %s", bus_index, cob_id, exc)

    def start(self) -> "SimDrives":
        """Attach to the buses, boot every node (boot-up message, pre-operational).

        Buses with the record batch interface (:mod:`.framerec`: the daemon's shared-memory and
        pipe buses) are read by one thread for all of them (:meth:`_receive_records`); others
        (SocketCAN, udp_multicast, virtual) by a python-can notifier per bus."""
        if all(supports_batch(b) for b in self.buses):
            self._rx = threading.Thread(target=self._receive_records, name="simdrive-rx", daemon=True)
            self._rx.start()
        else:
            for net in self.networks:
                net.notifier = can.Notifier(net.bus, net.listeners, 0.05)
        with self.lock:
            for d in self.drives:
                d.boot()
        self._thread = threading.Thread(target=self._housekeeping, name="simdrive-housekeeping", daemon=True)
        self._thread.start()
        return self

    def _receive_records(self) -> None:
        """Hand every frame that arrived on any bus to canopen's subscribers for its COB-ID (what
        canopen's MessageListener does, without a ``can.Message`` per frame or a thread per bus).

        The buses take turns in batches of ``RX_BATCH`` records, so after a stall of this process
        their backlogs drain side by side, as on separate CAN controllers (a bus drained 256 records
        at a time fell silent for ~8 ms meanwhile: the master took its drives for caught up and
        tagged their late samples with too new SYNCs, a spurious following error). Between turns
        the CPU is yielded (same-priority SCHED_FIFO threads: the heartbeat producers) and, once
        every bus is empty, the thread sleeps for the buses' poll interval: a CAN controller
        nobody has to wake."""
        subs = [net.subscribers for net in self.networks]
        buses = self.buses
        poll_s = min(float(getattr(b, "poll_interval_s", RX_POLL_S) or RX_POLL_S) for b in buses)
        unpack = HEADER.unpack_from
        skip = F_RTR | F_EXT
        yield_cpu = getattr(os, "sched_yield", None) or (lambda: time.sleep(0))
        while not self._stop.is_set():
            busy = False
            for b, bus in enumerate(buses):
                try:
                    buf, i, end = bus.drain_records(RX_BATCH)
                except can.CanError as exc:
                    log.error("bus %d: receiving stopped: %s", b, exc)
                    return
                if i == end:
                    continue
                busy = True
                ts = time.time()
                sb = subs[b]
                while i < end:
                    arb, flags, n = unpack(buf, i)
                    if not flags & skip:
                        cbs = sb.get(arb)
                        if cbs:
                            data = bytes(buf[i + DATA_OFFSET:i + DATA_OFFSET + n])
                            for cb in cbs:
                                try:
                                    cb(arb, data, ts)
                                except Exception:     # as canopen's MessageListener: log, go on
                                    log.exception("bus %d: frame 0x%03X", b, arb)
                    i += RECORD
            if busy:
                yield_cpu()
            else:
                time.sleep(poll_s)

    def _housekeeping(self) -> None:
        """Every ``TICK_S``: each drive's timers and supervision. Where a bus tells how many received
        frames wait unread (``pending_records``: the daemon's frame rings), its drives' communication
        deadlines count from now while any do (:meth:`drivers.simreact.Reactions.frames_waiting`)."""
        buses = self.buses
        while not self._stop.wait(TICK_S):
            now = time.monotonic()
            with self.lock:
                behind = [getattr(b, "pending_records", _nothing_pending)() > 0 for b in buses]
                for d in self.drives:
                    try:
                        if behind[d.bus_index]:
                            d.react.frames_waiting(now)
                        d.housekeeping(now)
                    except Exception:     # keep the simulator alive; log the bug
                        log.exception("node %d housekeeping", d.node_id)

    def stop(self) -> None:
        """Stop heartbeats and listeners; the bus objects stay open (owned by the caller)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
        for d in self.drives:
            d.node.nmt.stop_heartbeat()
        if self._rx is not None:
            self._rx.join(2.0)
            self._rx = None
        for net in self.networks:
            if net.notifier is not None:
                net.notifier.stop(2.0)
                net.notifier = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # -- inspection (tests) -----------------------------------------------------------------
    def positions_inc(self) -> list[int]:
        with self.lock:
            return [d.pos_inc for d in self.drives]

    def states(self) -> list[int]:
        with self.lock:
            return [d.state for d in self.drives]
