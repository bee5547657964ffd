"""Hot-path codec of the drive bus: prebuilt frames and ``struct`` codecs, one call per cycle each way.

Used by the daemon's hot loop (alone in its process, no canopen Network attached to the same bus
objects while cycling: detach the master first, see :meth:`drivers.master.Master.detach`)::

    io = CyclicIO(buses, cfg.bus, limits_inc=limits_inc(cfg))
    rc = io.send(targets_inc)          # RPDO1 targets (+ changed controlwords) + SYNC (+ master heartbeat)
    ev = io.poll()                     # non-blocking drain: feedback, statusword, heartbeats, EMCY
    io.pos_inc[i], io.pos_count[i], io.status[i], io.last_heartbeat_s[i], io.emcy (deque)

The drives consume the master heartbeat (``[bus] heartbeat_timeout_ms``): the first ``send`` sends
one, so keep the gap between ``Master.detach()`` and the first ``send`` well below that time-out.

Neither call raises for bus trouble or bad frames: ``send`` returns ``SEND_*`` bits, ``poll`` ``EV_*``
bits. Nothing is allocated per cycle except what python-can forces (received ``can.Message``
objects, the udp_multicast datagram).

Every cycle's frames are packed once, per bus, into prebuilt :mod:`drivers.framerec` records
(controlword events, RPDOs, SYNC, heartbeat, in that order). On buses with the record batch interface
(the daemon's shared-memory ring and pipe buses) they go out in one write per bus, and one read per
bus per poll is decoded in place with ``struct`` (no ``can.Message``). SocketCAN, udp_multicast and
virtual buses take the python-can path: one prebuilt ``can.Message`` per record, one ``bus.send``
each, as the kernel needs. Both paths put the same frames on each bus in the same order and decode
them into the same state.

Units: drive positions in increments, ``inc = round((strut_length_mm - strut_offset_mm) *
increments_per_mm)``, int32; strut index 0..5 in ``[bus] node_ids`` order.
"""
from __future__ import annotations

import collections
import struct
import time
from typing import Sequence

import can

from . import cia402, framerec, torquepdo
from .cyclictx import BusTx
from .layout import plan_layout
from .synctags import SyncTags

from .cyclicdefs import (EV_BAD_FRAME, EV_BOOTUP, EV_BUS_ERROR, EV_EMCY, EV_FEEDBACK, EV_HEARTBEAT,  # noqa: F401
                         EV_NMT, EV_OVERFLOW, EV_STATUS, EVENT_NAMES, NMT_OPERATIONAL, SEND_BUS_ERROR, SEND_LIMIT,
                         SEND_OK, event_text, increments_to_length, length_to_increments, limits_inc,
                         master_heartbeat_s)

_I32 = struct.Struct("<i")
_U16 = struct.Struct("<H")
_U8 = struct.Struct("<B")
_EMCY = struct.Struct("<HB5s")

_K_POS, _K_STATUS, _K_HEARTBEAT, _K_EMCY, _K_SDO, _K_TORQUE = 0, 1, 2, 3, 4, 5
_I16 = struct.Struct("<h")
INT32_MIN, INT32_MAX = -(1 << 31), (1 << 31) - 1


_HDR = framerec.HEADER
REC = framerec.RECORD
DATA_OFFSET = framerec.DATA_OFFSET


class CyclicIO:
    """Per-cycle frames of the configured layout on ``buses`` (one bus object per ``[bus] buses``).

    ``limits_inc``: (min list, max list) increments; a target outside is never sent.
    ``status`` / ``positions_inc``: last statuswords / positions the master read (``Master.statuswords()``,
    ``Master.positions_inc()``); statuswords arrive on change and every 50 ms (event timer) only.
    ``controlword``: the controlword the drives are assumed to hold already (the master left them
    there); in the ``paired``/``fd`` layouts a controlword is sent (RPDO2) only when it changes,
    in ``single`` it is part of every RPDO1.
    """

    def __init__(self, buses: can.BusABC | Sequence[can.BusABC], bus_cfg,
                 limits_inc: tuple[Sequence[int], Sequence[int]] | None = None,
                 controlword: int = cia402.CW_ENABLE_OPERATION, period_s: float = 0.0005,
                 status: Sequence[int] | None = None, positions_inc: Sequence[int] | None = None,
                 batch: bool | None = None, sync_every: int = 1):
        """``batch``: use the record batch interface (:mod:`drivers.framerec`); None: when every
        bus offers it, False: never (python-can ``send``/``recv`` on every bus).
        ``sync_every``: bus cycles (RPDOs + SYNC) only on every n-th :meth:`send` (the drives' 0x60C2
        is n loop periods, :attr:`drivers.master.Master.sync_every`); the other calls send nothing."""
        if isinstance(buses, can.BusABC):
            buses = [buses]
        self.plan = plan = plan_layout(bus_cfg)
        if len(buses) != plan.buses:
            raise ValueError(f"CyclicIO: {len(buses)} bus objects for [bus] buses = {plan.buses}")
        n = len(plan.nodes)
        self.n = n
        self.buses = list(buses)
        lo, hi = limits_inc if limits_inc is not None else ([INT32_MIN] * n, [INT32_MAX] * n)
        self._lo = [max(INT32_MIN, int(v)) for v in lo]
        self._hi = [min(INT32_MAX, int(v)) for v in hi]
        # state filled by poll()
        now = time.monotonic()
        self.pos_inc: list[int] = [int(v) for v in positions_inc] if positions_inc is not None else [0] * n
        self.pos_time_s: list[float] = [0.0] * n          #: monotonic time of the last TPDO1
        self.pos_count: list[int] = [0] * n               #: TPDO1 frames decoded per drive
        self.status: list[int] = [int(v) for v in status] if status is not None else [0] * n
        self.status_time_s: list[float] = [0.0] * n
        self.last_heartbeat_s: list[float] = [now] * n    #: monotonic; starts at construction
        self.nmt_state: list[int] = [-1] * n
        self.emcy: collections.deque = collections.deque(maxlen=64)  #: (strut, code, register, data, t_s)
        self.bootups = 0
        self.frames_sent = 0
        self.frames_received = 0
        self.cycles = 0
        # controlwords
        self.controlword: list[int] = [int(controlword)] * n
        self._cw_sent: list[int] = [int(controlword)] * n
        self._sync_counter = 0
        if not 1 <= int(sync_every) <= 100:
            raise ValueError(f"CyclicIO: sync_every = {sync_every} must be 1..100")
        self.sync_every = int(sync_every)
        self._phase = 0
        self._have_last = False                 #: the RPDO buffers hold valid targets
        self._sync_overflow = plan.sync_counter_overflow
        # master heartbeat (consumed by the drives, 0x1016)
        self._hb_period_s = master_heartbeat_s(bus_cfg)
        self._hb_next_s = 0.0                    # first heartbeat with the first send()
        # receive dispatch
        self._rx: dict[int, tuple[int, int]] = {}
        for nd in plan.nodes:
            self._rx[nd.tpdo1_cob_id] = (_K_POS, nd.index)
            self._rx[nd.tpdo2_cob_id] = (_K_STATUS, nd.index)
            self._rx[0x700 + nd.node_id] = (_K_HEARTBEAT, nd.index)
            self._rx[0x080 + nd.node_id] = (_K_EMCY, nd.index)
            self._rx[0x580 + nd.node_id] = (_K_SDO, nd.index)
            if torquepdo.every(bus_cfg):
                self._rx[torquepdo.cob_id(nd.node_id)] = (_K_TORQUE, nd.index)
        #: drive torque 0x6077 (per mille of rated) from the TPDO3 of drivers/torquepdo.py, its monotonic
        #: arrival time and how many arrived
        self.torque_pdo_permille: list[int] = [0] * n
        self.torque_pdo_time_s: list[float] = [0.0] * n
        self.torque_pdo_count: list[int] = [0] * n
        #: last SDO server response (8 bytes) per drive and how many arrived (:meth:`send_sdo`)
        self.sdo_resp: list[bytearray] = [bytearray(8) for _ in range(n)]
        self.sdo_count: list[int] = [0] * n
        self._sdo_rec = bytearray(REC)
        self._hb_timeout_s = bus_cfg.heartbeat_timeout_ms * 1e-3
        can_batch = all(framerec.supports_batch(b) for b in self.buses)
        if batch and not can_batch:
            raise ValueError("CyclicIO(batch=True): a bus lacks the frame record interface")
        self.batch = can_batch if batch is None else bool(batch)
        self._btx: list[BusTx] = [BusTx(self, b) for b in range(plan.buses)]
        # struts whose controlword travels inside RPDO1 (single layout): no event frame
        with_event = {nd.index for nd in plan.nodes if nd.rpdo2_cob_id is not None}
        self._cw_inline = [i for i in range(n) if i not in with_event]
        #: which SYNC each drive's last sample answers (pos_sync), see drivers.synctags; the drives'
        #: backlog where the transport tells it (records of two bus cycles still count as keeping pace)
        self.tags = SyncTags(plan, [getattr(b, "unread_by_peer", None) for b in self.buses],
                             [2 * (bt.hb_end - bt.frames_at) // REC + 2 * len(bt.cw_nodes) for bt in self._btx],
                             self.sync_every)
        self.pos_sync: list[int] = self.tags.pos_sync

    # -- transmit -----------------------------------------------------------------------------
    def set_controlword(self, strut: int, controlword: int) -> None:
        """Controlword for one drive, sent with the next :meth:`send` (only if changed)."""
        self.controlword[strut] = controlword

    def set_all_controlwords(self, controlword: int) -> None:
        for i in range(self.n):
            self.controlword[i] = controlword

    def send(self, targets_inc: Sequence[int], controlwords: Sequence[int] | None = None) -> int:
        """Send this cycle's targets (int32 increments, strut order) then SYNC on every bus.

        Returns ``SEND_OK`` or ``SEND_*`` bits. With any target outside the limits no new target
        goes out: the RPDO frames repeat the last valid targets (none before the first valid cycle),
        so the drives hold; SYNC, heartbeat and controlwords still go out; ``SEND_LIMIT`` is returned.
        """
        lo, hi = self._lo, self._hi
        limit = False
        for i in range(self.n):
            t = targets_inc[i]
            if t < lo[i] or t > hi[i]:
                limit = True
                break
        have_last = self._have_last
        cw = self.controlword
        if controlwords is not None:
            for i in range(self.n):
                cw[i] = controlwords[i]
        if self.sync_every > 1:                  # bus period = n loop periods: frames every n-th call
            self._phase += 1
            if self._phase < self.sync_every:
                self.cycles += 1
                return SEND_LIMIT if limit else SEND_OK
            self._phase = 0
        if self._sync_overflow:
            self._sync_counter = self._sync_counter % self._sync_overflow + 1
        now = time.monotonic()
        beat = now >= self._hb_next_s
        if beat:                                 # every [bus] heartbeat_ms, whatever the call rate
            self._hb_next_s = now + self._hb_period_s
        rc, sent = self._send(targets_inc, cw, limit, have_last, beat)
        self.frames_sent += sent
        self.cycles += 1
        if limit:
            return rc | SEND_LIMIT
        self._have_last = True
        return rc

    def _send(self, targets_inc, cw, limit: bool, have_last: bool, beat: bool) -> tuple[int, int]:
        """Per bus: controlword events, RPDOs (unless held), SYNC (+ heartbeat), packed into the
        bus's prebuilt records, then written in one call (record path) or sent as one
        ``can.Message`` per frame (python-can path); the same frames in the same order either way.
        A failed bus fails its whole cycle (its controlword events are retried next cycle)."""
        rc = SEND_OK
        sent = 0
        cw_sent = self._cw_sent
        for i in self._cw_inline:
            cw_sent[i] = cw[i]
        pack_i32 = _I32.pack_into
        pack_u16 = _U16.pack_into
        counter = self._sync_counter if self._sync_overflow else -1
        batch = self.batch
        for bt in self._btx:
            buf = bt.buf
            # controlword events, packed right-aligned in front of the RPDO records
            start = bt.frames_at
            changed = 0
            for i, cob in bt.cw_nodes:
                if cw[i] != cw_sent[i]:
                    changed |= 1 << i
            if changed:
                for i, cob in reversed(bt.cw_nodes):
                    if changed >> i & 1:
                        start -= REC
                        _HDR.pack_into(buf, start, cob, 0, 2)
                        pack_u16(buf, start + DATA_OFFSET, cw[i])
            if limit:
                if have_last:
                    for slots, has_cw in bt.frames:
                        if has_cw:
                            for i, off in slots:
                                pack_u16(buf, off - 2, cw[i])
            else:
                for slots, has_cw in bt.frames:
                    for i, off in slots:
                        pack_i32(buf, off, targets_inc[i])
                        if has_cw:
                            pack_u16(buf, off - 2, cw[i])
            if counter >= 0:
                buf[bt.sync_data] = counter
            end = bt.hb_end if beat else bt.sync_end
            try:
                if limit and not have_last:   # no valid target yet: events, SYNC (+ heartbeat) only
                    if batch:
                        if start < bt.frames_at:
                            bt.send_records(bt.view[start:bt.frames_at])
                        bt.send_records(bt.view[bt.sync_at:end])
                    else:
                        bt.send_messages(start, bt.frames_at)
                        bt.send_messages(bt.sync_at, end)
                    sent += (bt.frames_at - start + end - bt.sync_at) // REC
                else:
                    if batch:
                        bt.send_records(bt.cyclic_views[end] if start == bt.frames_at else bt.view[start:end])
                    else:
                        bt.send_messages(start, end)
                    sent += (end - start) // REC
            except can.CanError:
                rc |= SEND_BUS_ERROR
                continue
            if changed:
                for i, cob in bt.cw_nodes:
                    if changed >> i & 1:
                        cw_sent[i] = cw[i]
        return rc, sent

    def send_sdo(self, strut: int, data: bytes) -> bool:
        """One SDO client request (8 bytes, hand-packed by the caller) to drive ``strut`` at once,
        without waiting: the answer lands in ``sdo_resp[strut]`` (``sdo_count`` counts answers) at a
        later :meth:`poll`. False when the bus refused the frame."""
        nd = self.plan.nodes[strut]
        bus = self.buses[nd.bus]
        try:
            if self.batch:
                framerec.encode(self._sdo_rec, 0, 0x600 + nd.node_id, data)
                bus.send_records(memoryview(self._sdo_rec))
            else:
                bus.send(can.Message(arbitration_id=0x600 + nd.node_id, data=data, is_extended_id=False))
        except can.CanError:
            return False
        self.frames_sent += 1
        return True

    # -- receive ------------------------------------------------------------------------------
    def poll(self, max_frames: int = 256) -> int:
        """Drain received frames without blocking; returns ``EV_*`` bits (0: nothing new)."""
        if self.batch:
            return self._poll_batch(max_frames)
        ev = 0
        now = time.monotonic()
        rx = self._rx
        count = 0
        tag = self.tags.tag
        for bus in self.buses:
            recv = bus.recv
            for _ in range(max_frames):
                try:
                    msg = recv(0.0)
                except (can.CanError, OSError, ValueError):
                    ev |= EV_BUS_ERROR
                    break
                if msg is None:
                    break
                count += 1
                hit = rx.get(msg.arbitration_id)
                if hit is None or msg.is_remote_frame:
                    continue
                kind, i = hit
                data = msg.data
                if kind == _K_POS:
                    if len(data) < 4:
                        ev |= EV_BAD_FRAME
                        continue
                    self.pos_inc[i] = _I32.unpack_from(data)[0]
                    self.pos_time_s[i] = now
                    self.pos_count[i] += 1
                    tag(i, self.cycles)
                    ev |= EV_FEEDBACK
                else:
                    ev |= self._decode_event(kind, i, data, 0, len(data), now)
            else:
                ev |= EV_OVERFLOW
        self.tags.settle(self.cycles)
        self.frames_received += count
        return ev

    def _decode_event(self, kind: int, i: int, buf, d: int, length: int, now: float) -> int:
        """Statusword, heartbeat or EMCY frame of drive ``i`` (data at ``buf[d:d + length]``):
        update the state, return the ``EV_*`` bits.  Shared by both receive paths; position
        feedback, the frame of nearly every cycle, stays inline in them."""
        if kind == _K_STATUS:
            if length < 2:
                return EV_BAD_FRAME
            sw = _U16.unpack_from(buf, d)[0]
            ev = EV_STATUS if sw != self.status[i] else 0
            self.status[i] = sw
            self.status_time_s[i] = now
            return ev
        if kind == _K_HEARTBEAT:
            if length < 1:
                return EV_BAD_FRAME
            st = buf[d] & 0x7F
            self.last_heartbeat_s[i] = now
            self.nmt_state[i] = st
            if st == 0:
                self.bootups += 1
                return EV_HEARTBEAT | EV_BOOTUP
            return (EV_HEARTBEAT | EV_NMT) if st != NMT_OPERATIONAL else EV_HEARTBEAT
        if kind == _K_TORQUE:
            if length < 2:
                return EV_BAD_FRAME
            self.torque_pdo_permille[i] = _I16.unpack_from(buf, d)[0]
            self.torque_pdo_time_s[i] = now
            self.torque_pdo_count[i] += 1
            return 0
        if kind == _K_SDO:
            if length == 8:
                self.sdo_resp[i][:] = bytes(buf[d:d + 8])
                self.sdo_count[i] += 1
            return 0
        if length < 8:      # EMCY
            return EV_BAD_FRAME
        code, reg, extra = _EMCY.unpack_from(buf, d)
        self.emcy.append((i, code, reg, extra, now))
        return EV_EMCY

    def _poll_batch(self, max_frames: int) -> int:
        """Record path of :meth:`poll`: one read per bus, frames decoded in place (same state and
        events as the python-can path)."""
        ev = 0
        now = time.monotonic()
        rx = self._rx
        count = 0
        unpack_hdr = _HDR.unpack_from
        unpack_i32 = _I32.unpack_from
        pos_inc = self.pos_inc
        pos_time = self.pos_time_s
        pos_count = self.pos_count
        tag = self.tags.tag
        cycles = self.cycles
        for bus in self.buses:
            left = max_frames
            while True:
                try:
                    buf, p, end = bus.drain_records(left)
                except (can.CanError, OSError, ValueError):
                    ev |= EV_BUS_ERROR
                    break
                if p == end:
                    break
                left -= (end - p) // REC
                while p < end:
                    arb, flags, length = unpack_hdr(buf, p)
                    d = p + DATA_OFFSET
                    p += REC
                    hit = rx.get(arb)
                    if hit is None or flags & framerec.F_RTR:
                        continue
                    kind, i = hit
                    if kind == _K_POS:
                        if length < 4:
                            ev |= EV_BAD_FRAME
                            continue
                        pos_inc[i] = unpack_i32(buf, d)[0]
                        pos_time[i] = now
                        pos_count[i] += 1
                        tag(i, cycles)
                        ev |= EV_FEEDBACK
                    else:
                        ev |= self._decode_event(kind, i, buf, d, length, now)
                if left <= 0:
                    ev |= EV_OVERFLOW
                    break
                if end < len(buf):      # the read did not fill the buffer: the socket is empty
                    break
            count += max_frames - left
        self.tags.settle(self.cycles)
        self.frames_received += count
        return ev

    # -- supervision helpers (cheap, for the cycle) --------------------------------------------
    def heartbeat_lost(self, now: float | None = None) -> int:
        """Bitmask of struts (bit i) whose heartbeat is older than ``[bus] heartbeat_timeout_ms``."""
        t = time.monotonic() if now is None else now
        lim = self._hb_timeout_s
        mask = 0
        for i in range(self.n):
            if t - self.last_heartbeat_s[i] > lim:
                mask |= 1 << i
        return mask

    def feedback_stale(self, max_age_s: float, now: float | None = None) -> int:
        """Bitmask of struts whose last position feedback is older than ``max_age_s`` (or absent)."""
        t = time.monotonic() if now is None else now
        mask = 0
        for i in range(self.n):
            if t - self.pos_time_s[i] > max_age_s:
                mask |= 1 << i
        return mask

    def step_towards(self, wanted: int, mask: int = 0x3F) -> int:
        """Non-blocking CiA 402 walk for the cycle: set each masked strut's controlword for its next
        transition towards ``wanted`` (a :mod:`drivers.cia402` state) from its last statusword.

        Returns the bitmask of masked struts not yet in ``wanted`` (0: done). Call once per cycle
        before :meth:`send`; while walking to Operation enabled, send the actual positions
        (``pos_inc``) as targets so the drives take over where they stand.
        """
        todo = 0
        cw = self.controlword
        for i in range(self.n):
            if not mask >> i & 1:
                continue
            state = cia402.state_from_status(self.status[i])
            if state != wanted:
                todo |= 1 << i
                cw[i] = cia402.controlword_towards(state, wanted, cw[i])[0]
        return todo

    def status_faults(self, csp: bool = True) -> int:
        """Bitmask of struts (bit i) whose last statusword is not Operation enabled with remote (bit 9)
        set and, in CSP, bit 12 ("drive follows the command value") set and bit 13 (following error)
        clear - :func:`drivers.cia402.status_problem` names the cause. No allocation (hot loop)."""
        want = cia402.SW_REMOTE | (cia402.SW_DRIVE_FOLLOWS if csp else 0)
        bad13 = cia402.SW_FOLLOWING_ERROR if csp else 0
        mask = 0
        for i in range(self.n):
            sw = self.status[i]
            if (sw & cia402.SW_OP_ENABLED_MASK != cia402.SW_OP_ENABLED_VALUE or sw & want != want
                    or sw & bad13):
                mask |= 1 << i
        return mask

    def end_session(self) -> int:
        """NMT "enter pre-operational" (0x80, all nodes) on every bus, once the drives are disabled: PDOs
        and the drives' RPDO deadline monitoring stop, so a clean end is not reported as a silent master
        (EMCY 0x8250). Drives still enabled react per 0x6007/0x605E (they stop). Returns buses failed."""
        failed = 0
        for bus in self.buses:
            try:
                bus.send(can.Message(arbitration_id=0x000, data=bytes([0x80, 0]), is_extended_id=False))
            except (can.CanError, OSError):
                failed += 1
        return failed

    def states(self) -> list[int]:
        """CiA 402 state per strut from the last statuswords (slow path: allocates)."""
        return [cia402.state_from_status(s) for s in self.status]

    def all_in_state(self, state: int) -> bool:
        for s in self.status:
            if cia402.state_from_status(s) != state:
                return False
        return True
