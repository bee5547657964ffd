"""One bus's prebuilt transmit records for :class:`drivers.cyclic.CyclicIO`: the controlword
events, RPDOs, SYNC and master heartbeat of a cycle packed once into :mod:`drivers.framerec`
records, and the matching python-can messages for buses without the record batch interface."""
from __future__ import annotations

from typing import TYPE_CHECKING

import can

from . import framerec
from .cyclicdefs import NMT_OPERATIONAL
from .layout import MASTER_NODE_ID, SYNC_COB_ID

if TYPE_CHECKING:
    from .cyclic import CyclicIO

_HDR = framerec.HEADER
REC = framerec.RECORD
DATA_OFFSET = framerec.DATA_OFFSET


class BusTx:
    """One bus's transmit buffer: ``[controlword event slots][RPDO records][SYNC][heartbeat]`` as
    :mod:`drivers.framerec` records, headers and constant bytes prebuilt; per cycle only data bytes
    are packed.  Both transmit paths use it: the record path writes the slice in one call, the
    python-can path sends one prebuilt ``can.Message`` per record of the slice."""

    __slots__ = ("bus", "send_records", "buf", "view", "cw_nodes", "frames_at", "frames", "sync_at",
                 "sync_data", "sync_end", "hb_end", "msgs", "cyclic_views")

    def __init__(self, io: "CyclicIO", b: int):
        plan = io.plan
        self.bus = bus = io.buses[b]
        self.send_records = getattr(bus, "send_records", None)
        self.cw_nodes = tuple((nd.index, nd.rpdo2_cob_id) for nd in plan.nodes
                              if nd.bus == b and nd.rpdo2_cob_id is not None)
        frames = [f for f in plan.frames if f.bus == b]
        n_rec = len(self.cw_nodes) + len(frames) + 2
        self.buf = buf = bytearray(REC * n_rec)
        self.view = memoryview(buf)
        p = self.frames_at = REC * len(self.cw_nodes)
        out = []
        msgs = {}                 # python-can path: one prebuilt message per COB-ID
        for f in frames:
            framerec.encode(buf, p, f.cob_id, bytes(f.length), is_fd=f.fd, bitrate_switch=f.fd)
            out.append((tuple((i, p + DATA_OFFSET + off) for i, off in f.slots), f.has_controlword))
            msgs[f.cob_id] = can.Message(arbitration_id=f.cob_id, data=bytearray(f.length), is_extended_id=False,
                                         is_fd=f.fd, bitrate_switch=f.fd)
            p += REC
        self.frames = tuple(out)
        self.sync_at = p
        framerec.encode(buf, p, SYNC_COB_ID, bytes(plan.sync_length))
        msgs[SYNC_COB_ID] = can.Message(arbitration_id=SYNC_COB_ID, data=bytearray(plan.sync_length),
                                        is_extended_id=False)
        self.sync_data = p + DATA_OFFSET
        p += REC
        self.sync_end = p
        framerec.encode(buf, p, 0x700 + MASTER_NODE_ID, bytes([NMT_OPERATIONAL]))
        msgs[0x700 + MASTER_NODE_ID] = can.Message(arbitration_id=0x700 + MASTER_NODE_ID,
                                                   data=bytearray([NMT_OPERATIONAL]), is_extended_id=False)
        for i, cob in self.cw_nodes:
            msgs[cob] = can.Message(arbitration_id=cob, data=bytearray(2), is_extended_id=False)
        self.hb_end = p + REC
        self.msgs = msgs
        # the usual cycle's slices (no controlword event), prebuilt: no view made per cycle
        self.cyclic_views = {self.sync_end: self.view[self.frames_at:self.sync_end],
                             self.hb_end: self.view[self.frames_at:self.hb_end]}

    def send_messages(self, start: int, end: int) -> None:
        """python-can path: the records ``buf[start:end]`` as prebuilt messages, one ``bus.send``
        each (raises ``can.CanError`` at the first refused frame)."""
        buf = self.buf
        msgs = self.msgs
        send = self.bus.send
        for p in range(start, end, REC):
            msg = msgs[_HDR.unpack_from(buf, p)[0]]
            data = msg.data
            d = p + DATA_OFFSET
            data[:] = buf[d:d + len(data)]
            send(msg)
