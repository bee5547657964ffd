"""The record batch path of CyclicIO (pipe bus) puts the same frames on each bus and decodes received
frames into the same state as the python-can path (one ``bus.send``/``bus.recv`` per frame)."""
import dataclasses
import random
import socket
import struct

import can
import pytest

from drivers import cia402, framerec
from drivers.cyclic import (EV_OVERFLOW, SEND_LIMIT, SEND_OK, CyclicIO, limits_inc)
from drivers.layout import plan_layout
from hexacnc.config import load_config
from hexacnc.daemon.pipebus import PipeBus, socket_pairs

pytestmark = pytest.mark.bus


LAYOUTS = [
    dict(layout="single", buses=1, feedback_divider=1),
    dict(layout="paired", buses=2, feedback_divider=3),
    dict(layout="fd", buses=1, feedback_divider=3, fd=True),
]


def _cfg(changes):
    cfg = load_config()
    return cfg.replace(bus=dataclasses.replace(cfg.bus, **changes))


class Pair:
    """CyclicIO on one end of pipe buses, python-can PipeBus objects on the other."""

    def __init__(self, cfg, batch):
        pairs = socket_pairs(cfg.bus.buses)
        self.mine = [PipeBus(fd=a.detach()) for a, _ in pairs]
        self.peer = [PipeBus(fd=b.detach()) for _, b in pairs]
        start = [100000 + 1000 * i for i in range(6)]
        self.io = CyclicIO(self.mine, cfg.bus, limits_inc=limits_inc(cfg), period_s=cfg.cycle.period_s,
                           status=[0x0237] * 6, positions_inc=start, batch=batch)
        assert self.io.batch is batch

    def frames(self):
        out = []
        for b in self.peer:
            seen = []
            while (m := b.recv(0.05)) is not None:
                seen.append((m.arbitration_id, bytes(m.data), m.is_fd, m.bitrate_switch, m.is_remote_frame))
            out.append(seen)
        return out

    def close(self):
        for b in self.mine + self.peer:
            b.shutdown()


@pytest.mark.parametrize("changes", LAYOUTS, ids=lambda d: f"{d['layout']}-{d['buses']}")
def test_batch_sends_the_same_frames_as_python_can(changes):
    cfg = _cfg(changes)
    lo, hi = limits_inc(cfg)
    rng = random.Random(7)
    a, b = Pair(cfg, True), Pair(cfg, False)
    try:
        def both(targets, rc, cw=None):
            for p in (a, b):
                if cw is not None:
                    p.io.set_controlword(*cw)
                assert p.io.send(targets) == rc

        bad = [lo[i] + 5 for i in range(6)]
        bad[3] = hi[3] + 1
        both(bad, SEND_LIMIT, cw=(2, cia402.CW_QUICK_STOP))     # before any valid target: no RPDO
        for k in range(40):
            tg = [rng.randint(lo[i], hi[i]) for i in range(6)]
            cw = (rng.randrange(6), rng.choice([cia402.CW_ENABLE_OPERATION, cia402.CW_SHUTDOWN])) \
                if k % 7 == 3 else None
            both(tg, SEND_OK, cw=cw)
        bad[0] = lo[0] - 1
        both(bad, SEND_LIMIT, cw=(5, cia402.CW_DISABLE_VOLTAGE))  # repeats the last valid targets
        fa, fb = a.frames(), b.frames()
        assert fa == fb
        assert a.io.frames_sent == b.io.frames_sent == sum(len(f) for f in fa)
        plan = plan_layout(cfg.bus)
        n_cyclic = sum(len([f for f in plan.frames if f.bus == k]) for k in range(plan.buses))
        # 42 SYNCs per bus, 41 cycles of RPDOs, one master heartbeat per bus (all within 100 ms)
        assert sum(f[0] == 0x080 for bus in fa for f in bus) == 42 * plan.buses
        assert sum(f[0] == 0x77F for bus in fa for f in bus) == plan.buses
        assert sum(f[0] in {fr.cob_id for fr in plan.frames} for bus in fa for f in bus) == 41 * n_cyclic
    finally:
        a.close()
        b.close()


def _random_frames(cfg, rng, n):
    plan = plan_layout(cfg.bus)
    out = []
    for _ in range(n):
        nd = rng.choice(plan.nodes)
        kind = rng.randrange(8)
        if kind == 0:
            cob, data = nd.tpdo1_cob_id, struct.pack("<i", rng.randint(-2**31, 2**31 - 1))
        elif kind == 1:
            cob, data = nd.tpdo1_cob_id, bytes(rng.randrange(4))            # too short
        elif kind == 2:
            cob, data = nd.tpdo2_cob_id, struct.pack("<H", rng.choice([0x0237, 0x0233, 0x0218]))
        elif kind == 3:
            cob, data = 0x700 + nd.node_id, bytes([rng.choice([0, 5, 5, 5, 127, 0x85])])
        elif kind == 4:
            cob, data = 0x080 + nd.node_id, bytes([0x10, 0x82, 0x11, 1, 2, 3, 4, 5])
        elif kind == 5:
            cob, data = 0x080 + nd.node_id, bytes(rng.randrange(8))           # short EMCY
        elif kind == 6:
            cob, data = rng.choice([0x123, 0x600 + nd.node_id, 0x080]), bytes(rng.randrange(9))
        else:
            out.append((nd.bus, can.Message(arbitration_id=nd.tpdo1_cob_id, is_remote_frame=True, dlc=4,
                                            is_extended_id=False)))
            continue
        out.append((nd.bus, can.Message(arbitration_id=cob, data=data, is_extended_id=False,
                                        is_fd=plan.fd, bitrate_switch=plan.fd)))
    return out


def _state(io):
    return (list(io.pos_inc), list(io.status), list(io.nmt_state), io.bootups, io.frames_received,
            [(e[0], e[1], e[2], bytes(e[3])) for e in io.emcy],
            [t > 0 for t in io.pos_time_s], [t > 0 for t in io.status_time_s])


@pytest.mark.parametrize("changes", LAYOUTS, ids=lambda d: f"{d['layout']}-{d['buses']}")
def test_batch_decodes_received_frames_like_python_can(changes):
    cfg = _cfg(changes)
    rng = random.Random(11)
    a, b = Pair(cfg, True), Pair(cfg, False)
    try:
        for rnd in range(30):
            frames = _random_frames(cfg, rng, rng.randrange(0, 12))
            for p in (a, b):
                for bus, msg in frames:
                    p.peer[bus].send(msg)
            evs = [p.io.poll() for p in (a, b)]
            assert evs[0] == evs[1], rnd
            assert _state(a.io) == _state(b.io), rnd
        assert a.io.frames_received > 100
        # overflow: the drain stops at max_frames, the rest comes with the next poll
        frames = _random_frames(cfg, rng, 40)
        for p in (a, b):
            for bus, msg in frames:
                p.peer[bus].send(msg)
        evs = [p.io.poll(max_frames=5) for p in (a, b)]
        assert evs[0] == evs[1] and evs[0] & EV_OVERFLOW
        assert _state(a.io) == _state(b.io)
        evs = [p.io.poll() for p in (a, b)]
        assert evs[0] == evs[1] and not evs[0] & EV_OVERFLOW
        assert _state(a.io) == _state(b.io)
    finally:
        a.close()
        b.close()


def test_batch_poll_reassembles_a_record_split_across_reads():
    cfg = _cfg({})
    a = Pair(cfg, True)
    try:
        nd = plan_layout(cfg.bus).nodes[0]
        rec = bytearray(framerec.RECORD)
        framerec.encode(rec, 0, nd.tpdo1_cob_id, struct.pack("<i", -123456))
        raw = a.peer[0].sock
        raw.send(rec[:30])
        a.io.poll()
        assert a.io.pos_inc[0] == 100000                  # half a record: nothing decoded yet
        raw.send(rec[30:])
        a.io.poll()
        assert a.io.pos_inc[0] == -123456
    finally:
        a.close()


def test_send_records_never_blocks_and_keeps_the_stream_aligned():
    s1, s2 = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    for s in (s1, s2):
        s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    tx, rx = PipeBus(fd=s1.detach()), PipeBus(fd=s2.detach())
    try:
        batch = bytearray(framerec.RECORD * 5)
        for k in range(5):
            framerec.encode(batch, k * framerec.RECORD, 0x181 + k, struct.pack("<i", k))
        lost = 0
        sent = 0
        for _ in range(400):                              # far more than the socket buffers hold
            lost += tx.send_records(memoryview(batch))
            sent += 5
        assert lost > 0 and tx.dropped == lost
        got = []
        while (m := rx.recv(0.05)) is not None:
            got.append(m)
        assert len(got) == sent - lost
        # every record arrives whole: ids and data stay paired
        assert all(struct.unpack("<i", m.data)[0] == m.arbitration_id - 0x181 for m in got)
    finally:
        tx.shutdown()
        rx.shutdown()
