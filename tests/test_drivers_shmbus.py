"""The shared-memory frame ring (hexacnc.daemon.shmbus): the same CAN frames as the pipe bus,
decoded with canopen from the PDO mapping the drives got by SDO; never blocks; the daemon runs on it."""
import dataclasses
import random
import struct

import can
import canopen
import numpy as np
import pytest

from drivers import EDS_PATH, cia402, framerec
from drivers.cyclic import SEND_LIMIT, SEND_OK, CyclicIO, limits_inc
from drivers.layout import plan_layout
from drivers.master import Master
from hexacnc.sim.drives import sim_drives
from hexacnc.config import load_config
from hexacnc.daemon.pipebus import PipeBus, socket_pairs
from hexacnc.daemon.shmbus import ShmBus, create_segments, release_segments

pytestmark = pytest.mark.bus


LAYOUTS = [
    dict(layout="single", buses=1, feedback_divider=1),
    dict(layout="paired", buses=2, feedback_divider=3),
    dict(layout="fd", buses=1, feedback_divider=3, fd=True),
]


def _cfg(changes=None):
    cfg = load_config()
    return cfg.replace(bus=dataclasses.replace(cfg.bus, **(changes or {})))


class ShmPair:
    """Side 0 and side 1 of one frame ring per bus (records: small rings to test wrapping)."""

    def __init__(self, n, records=64):
        self.segs = create_segments(n, records)
        self.mine = [ShmBus(s.name, side=0) for s in self.segs]
        self.peer = [ShmBus(s.name, side=1, poll_interval_s=0.0001) for s in self.segs]

    def close(self):
        for b in self.mine + self.peer:
            b.shutdown()
        release_segments(self.segs)


class PipePair:
    def __init__(self, n):
        pairs = socket_pairs(n)
        self.mine = [PipeBus(fd=a.detach()) for a, _ in pairs]
        self.peer = [PipeBus(fd=b.detach()) for _, b in pairs]

    def close(self):
        for b in self.mine + self.peer:
            b.shutdown()


def _drain(buses):
    out = []
    for b in buses:
        seen = []
        while (m := b.recv(0.02)) is not None:
            seen.append((m.arbitration_id, bytes(m.data), m.is_fd, m.bitrate_switch, m.is_remote_frame))
        out.append(seen)
    return out


@pytest.mark.parametrize("changes", LAYOUTS, ids=lambda d: f"{d['layout']}-{d['buses']}")
def test_shm_ring_carries_the_same_frames_as_the_pipe(changes):
    cfg = _cfg(changes)
    lo, hi = limits_inc(cfg)
    rng = random.Random(5)
    shm, pipe = ShmPair(cfg.bus.buses), PipePair(cfg.bus.buses)
    start = [100000 + 1000 * i for i in range(6)]
    ios = [CyclicIO(p.mine, cfg.bus, limits_inc=(lo, hi), period_s=cfg.cycle.period_s, status=[0x0237] * 6,
                    positions_inc=start) for p in (shm, pipe)]
    assert all(io.batch for io in ios)
    try:
        got = [[[] for _ in range(cfg.bus.buses)] for _ in ios]
        for k in range(60):             # more records than the 64-slot ring holds: wraps around
            tg = [rng.randint(lo[i], hi[i]) for i in range(6)]
            if k == 0:
                tg[2] = hi[2] + 1       # before any valid target: no RPDO, SYNC still goes out
            cw = (rng.randrange(6), rng.choice([cia402.CW_ENABLE_OPERATION, cia402.CW_SHUTDOWN])) \
                if k % 5 == 2 else None
            for j, io in enumerate(ios):
                if cw is not None:
                    io.set_controlword(*cw)
                assert io.send(tg) == (SEND_LIMIT if k == 0 else SEND_OK)
            if k % 4 == 3:
                for j, p in enumerate((shm, pipe)):
                    for b, frames in enumerate(_drain(p.peer)):
                        got[j][b] += frames
        for j, p in enumerate((shm, pipe)):
            for b, frames in enumerate(_drain(p.peer)):
                got[j][b] += frames
        assert got[0] == got[1]
        assert sum(len(f) for f in got[0]) == ios[0].frames_sent == ios[1].frames_sent
        # and the other way: frames from the peer decode into the same state
        plan = plan_layout(cfg.bus)
        for rnd in range(20):
            for nd in plan.nodes:
                v = rng.randint(-2 ** 31, 2 ** 31 - 1)
                for p in (shm, pipe):
                    p.peer[nd.bus].send(can.Message(arbitration_id=nd.tpdo1_cob_id, data=struct.pack("<i", v),
                                                    is_extended_id=False))
            evs = [io.poll() for io in ios]
            assert evs[0] == evs[1]
            assert ios[0].pos_inc == ios[1].pos_inc
    finally:
        shm.close()
        pipe.close()


def test_shm_ring_never_blocks_drops_whole_records_and_counts_them():
    p = ShmPair(1, records=16)
    try:
        batch = bytearray(framerec.RECORD * 5)
        for k in range(5):
            framerec.encode(batch, k * framerec.RECORD, 0x181 + k, struct.pack("<i", k))
        lost = sum(p.mine[0].send_records(memoryview(batch)) for _ in range(5))
        assert lost == 25 - 16 and p.mine[0].dropped == lost
        assert p.peer[0].pending_records() == 16
        got = []
        while (m := p.peer[0].recv(0.0)) is not None:
            got.append(m)
        assert len(got) == 16
        assert all(struct.unpack("<i", m.data)[0] == m.arbitration_id - 0x181 for m in got)
        # drain_records: zero-copy views, contiguous up to the ring's end, consumed by the next call
        assert p.mine[0].send_records(memoryview(batch)) == 0
        assert p.mine[0].send_records(memoryview(batch)) == 0
        n = 0
        while True:
            buf, a, e = p.peer[0].drain_records(3)
            if a == e:
                break
            assert (e - a) % framerec.RECORD == 0 and (e - a) // framerec.RECORD <= 3
            for q in range(a, e, framerec.RECORD):
                arb, _, length = framerec.HEADER.unpack_from(buf, q)
                assert struct.unpack_from("<i", buf, q + framerec.DATA_OFFSET)[0] == arb - 0x181
                n += 1
        assert n == 10 and p.peer[0].pending_records() == 0
        assert p.mine[0].unread_by_peer() == 0
        # the sender sees the peer's backlog; records the peer holds from a drain count until it drains again
        assert p.mine[0].send_records(memoryview(batch)) == 0
        assert p.mine[0].unread_by_peer() == 5
        p.peer[0].drain_records(2)
        assert p.mine[0].unread_by_peer() == 5
        p.peer[0].drain_records(2)
        assert p.mine[0].unread_by_peer() == 3 and p.peer[0].unread_by_peer() == 0
        with pytest.raises(can.CanInitializationError):
            _attach_garbage()
    finally:
        p.close()


def _attach_garbage():
    from multiprocessing import shared_memory
    seg = shared_memory.SharedMemory(create=True, size=4096)
    try:
        ShmBus(seg.name, side=0)
    finally:
        seg.close()
        seg.unlink()


def test_cyclic_frames_on_the_shm_ring_decode_with_canopen_from_the_sdo_mapping():
    """Master boots simulated drives over the ring (SDO mapping, NMT, CiA 402); the cyclic frames
    then decode, with canopen PdoMaps read back from the drives by SDO, to the targets sent."""
    cfg = _cfg()
    plan = plan_layout(cfg.bus)
    segs = create_segments(plan.buses)
    drive_side = [ShmBus(s.name, side=1, poll_interval_s=0.0001) for s in segs]
    master_side = [ShmBus(s.name, side=0, poll_interval_s=0.0001) for s in segs]
    sim = sim_drives(cfg, drive_side).start()
    try:
        m = Master(cfg, master_side)
        m.bring_up(enable=True)
        assert all(cia402.state_from_status(s) == cia402.OPERATION_ENABLED for s in m.statuswords())
        pos0 = m.positions_inc()
        sw0 = m.statuswords()
        m.detach()
        # independent decoders: canopen RemoteNodes from the EDS on their own Network objects,
        # RPDO maps read back from the drives by SDO
        nets = [canopen.Network(b) for b in master_side]
        for net in nets:
            net.notifier = can.Notifier(net.bus, net.listeners, 0.05)
        nodes = []
        for nd in plan.nodes:
            node = canopen.RemoteNode(nd.node_id, canopen.import_od(str(EDS_PATH), nd.node_id))
            node.sdo.RESPONSE_TIMEOUT = 1.0
            nets[nd.bus].add_node(node)
            node.rpdo.read()
            nodes.append(node)
        for net in nets:
            net.notifier.stop(1.0)
            net.notifier = None
        sim.stop()                      # from here on the frames stay in the ring for the decoder
        lo, hi = limits_inc(cfg)
        io = CyclicIO(master_side, cfg.bus, limits_inc=(lo, hi), period_s=cfg.cycle.period_s,
                      status=sw0, positions_inc=pos0)
        sent = []
        for k in range(12):
            tg = [pos0[i] + 37 * k * (1 if i % 2 else -1) for i in range(6)]
            assert io.send(tg) == SEND_OK
            sent.append(tg)
        decoded = [[] for _ in range(6)]
        syncs = 0
        for b, bus in enumerate(drive_side):
            while (msg := bus.recv(0.02)) is not None:
                if msg.arbitration_id == 0x080:
                    syncs += 1
                    continue
                for nd, node in zip(plan.nodes, nodes):
                    if nd.bus != b:
                        continue
                    for pm in node.rpdo.map.values():
                        if pm.enabled and pm.cob_id == msg.arbitration_id:
                            pm.on_message(msg.arbitration_id, msg.data, msg.timestamp)
                            for var in pm.map:
                                if var.index == 0x607A:
                                    decoded[nd.index].append(var.raw)
        assert syncs == 12 * plan.buses
        assert decoded == [[tg[i] for tg in sent] for i in range(6)]
    finally:
        sim.stop()
        for b in master_side + drive_side:
            b.shutdown()
        release_segments(segs)


@pytest.mark.parametrize("mode", ["shm", "pipe"])
def test_daemon_moves_on_both_simulated_transports(mode):
    from hexacnc.daemon.core import Daemon
    cfg = _cfg()
    with Daemon(cfg, io_mode=mode, log_level="WARNING") as d:
        assert d.info["io_mode"] == mode
        target = [15.0, -5.0, -890.0, 1.0, -1.0, 2.0]
        d.move_to(target, 200.0)
        st = d.wait(20.0)
        assert st["state"] == "idle" and st["fault"] is None
        np.testing.assert_allclose(st["pose_act"][:3], target[:3], atol=0.01)
        assert st["cycle"]["compute_phases_us"]["send"]["mean"] > 0
