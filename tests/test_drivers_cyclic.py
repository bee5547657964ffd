"""Hot-path frames on the virtual bus, decoded independently with canopen's PDO maps read from the drives."""
import struct
import time

import pytest

from drivers import cia402
from drivers.canbus import open_buses
from drivers.cyclic import (EV_FEEDBACK, SEND_LIMIT, SEND_OK, increments_to_length, length_to_increments,
                            limits_inc)
from drivers.testing import PdoDecoder
from hexacnc.sim.rig import SimRig


pytestmark = pytest.mark.bus


def cycle(io, targets, period_s=0.0005):
    ev = io.send(targets)
    assert ev == SEND_OK
    time.sleep(period_s)
    return io.poll()


LAYOUTS = [
    dict(layout="single", buses=1, feedback_divider=1),
    dict(layout="paired", buses=2, feedback_divider=3),
    dict(layout="paired", buses=1, feedback_divider=2),
    dict(layout="fd", buses=1, feedback_divider=3, fd=True),
]


@pytest.mark.parametrize("bus_changes", LAYOUTS, ids=lambda d: "-".join(f"{v}" for v in d.values()))
def test_frames_decode_with_canopen_pdo_maps(bus_changes):
    with SimRig(**bus_changes) as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        dec = PdoDecoder(rig.cfg)         # reads the mapping by SDO while the master still beats
        try:
            # the mapping the drives report is the layout's (paired: dummies skip the other's bytes)
            for nd, node in zip(rig.master.plan.nodes, dec.nodes):
                assert node.rpdo[1].cob_id == nd.rpdo1_cob_id
                assert [(v.index, v.length) for v in node.rpdo[1].map] == [(i, b) for i, s, b in nd.rpdo1_map]
                assert node.tpdo[1].trans_type == nd.tpdo1_trans_type
            io = rig.cyclic()
            assert not io.emcy
            sent = []
            ev = 0
            for k in range(60):
                tg = [start[i] + (k * 37 * (i + 1)) * (-1) ** i for i in range(6)]
                sent.append(tg)
                ev |= cycle(io, tg)
            assert ev & EV_FEEDBACK                               # positions flow
            time.sleep(0.05)
            io.poll()
            for i in range(6):
                assert dec.targets[i] == [tg[i] for tg in sent], f"strut {i + 1}"
                if bus_changes["layout"] == "single":
                    assert set(dec.controlwords[i]) == {cia402.CW_ENABLE_OPERATION}
                # feedback: what canopen decodes from the drives' TPDOs is what CyclicIO decoded
                assert dec.positions[i] and dec.positions[i][-1] == io.pos_inc[i]
                assert cia402.state_from_status(io.status[i]) == cia402.OPERATION_ENABLED, list(io.emcy)
            # with a divider d each drive sends its feedback on every d-th SYNC
            d = bus_changes["feedback_divider"]
            for i in range(6):
                assert abs(len(dec.positions[i]) - 60 / d) <= 1
        finally:
            dec.close()


def test_limits_block_the_whole_cycle_and_controlword_events_only_on_change():
    with SimRig() as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        io = rig.cyclic()
        sniff = open_buses(rig.cfg.bus)
        try:
            lo, hi = limits_inc(rig.cfg)
            cycle(io, start)
            time.sleep(0.02)
            for b in sniff:
                while b.recv(0) is not None:
                    pass
            bad = list(start)
            bad[4] = hi[4] + 1
            assert io.send(bad) == SEND_LIMIT
            bad[4] = lo[4] - 1
            assert io.send(bad) == SEND_LIMIT
            time.sleep(0.01)
            plan = rig.master.plan
            frames = {f.cob_id: f for f in plan.frames}
            seen = [m for b in sniff for m in iter(lambda b=b: b.recv(0), None)]
            rpdo = [m for m in seen if m.arbitration_id in frames]
            assert len(rpdo) == 2 * len(frames)                  # the frames still go out ...
            for m in rpdo:                                       # ... repeating the last valid targets
                for i, off in frames[m.arbitration_id].slots:
                    assert struct.unpack_from("<i", m.data, off)[0] == start[i]
            assert sum(m.arbitration_id == 0x080 for m in seen) == 2 * 2     # SYNC on both buses
            # controlword: one RPDO2 event when it changes, none while it stays
            io.set_controlword(0, cia402.CW_QUICK_STOP)
            for _ in range(20):
                cycle(io, start)
            seen = []
            for b in sniff:
                while (m := b.recv(0)) is not None:
                    seen.append(m.arbitration_id)
            assert seen.count(0x301) == 1 and all(c not in seen for c in (0x302, 0x303, 0x304, 0x305, 0x306))
            assert seen.count(0x080) == 2 * 20              # SYNC on both buses every cycle
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline and \
                    cia402.state_from_status(io.status[0]) != cia402.SWITCH_ON_DISABLED:
                cycle(io, start)
            assert cia402.state_from_status(io.status[0]) == cia402.SWITCH_ON_DISABLED   # 11 then 12
            assert all(cia402.state_from_status(s) == cia402.OPERATION_ENABLED for s in io.status[1:])
        finally:
            for b in sniff:
                b.shutdown()


def test_increment_conversion():
    assert length_to_increments(512.34567, 500.0, 10000.0) == 123457
    assert increments_to_length(123457, 500.0, 10000.0) == pytest.approx(512.3457)
    for x in (-3.2, 0.0, 17.77777):
        inc = length_to_increments(600 + x, 600, 10000.0)
        assert abs(increments_to_length(inc, 600, 10000.0) - (600 + x)) <= 0.5 / 10000


def test_no_target_before_the_first_valid_cycle():
    with SimRig() as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        io = rig.cyclic()
        sniff = open_buses(rig.cfg.bus)
        try:
            lo, hi = limits_inc(rig.cfg)
            bad = list(start)
            bad[0] = hi[0] + 10
            assert io.send(bad) == SEND_LIMIT
            time.sleep(0.01)
            ids = [m.arbitration_id for b in sniff for m in iter(lambda b=b: b.recv(0), None)]
            assert not {f.cob_id for f in rig.master.plan.frames} & set(ids)   # zeros never go out
            assert ids.count(0x080) == 2
        finally:
            for b in sniff:
                b.shutdown()


def test_statusword_heartbeat_emcy_and_short_frames_decode_alike_on_both_receive_paths():
    """The python-can path (frames on a virtual bus) and the record path (the same bytes at an
    offset inside a record buffer) share one decoder: same events, same state, short frames
    flagged and ignored."""
    import dataclasses
    import uuid

    import can

    from hexacnc.config import load_config
    from drivers.cyclic import (EV_BAD_FRAME, EV_BOOTUP, EV_EMCY, EV_HEARTBEAT, EV_NMT, EV_STATUS,
                                CyclicIO)
    base = load_config()
    cfg = base.replace(bus=dataclasses.replace(base.bus, interface="virtual", buses=1, layout="single",
                                               channel=f"dec-{uuid.uuid4().hex[:10]}"))
    node = cfg.bus.node_ids[2]
    frames = [  # (COB-ID, data, events expected, check of the state afterwards)
        (0x280 + node, b"\x37\x02", EV_STATUS, lambda io: io.status[2] == 0x0237),
        (0x280 + node, b"\x37\x02", 0, lambda io: io.status[2] == 0x0237),            # unchanged
        (0x280 + node, b"\x37", EV_BAD_FRAME, lambda io: io.status[2] == 0x0237),     # too short
        (0x700 + node, b"\x05", EV_HEARTBEAT, lambda io: io.nmt_state[2] == 5),
        (0x700 + node, b"\x7f", EV_HEARTBEAT | EV_NMT, lambda io: io.nmt_state[2] == 127),
        (0x700 + node, b"\x00", EV_HEARTBEAT | EV_BOOTUP, lambda io: io.bootups == 1),
        (0x700 + node, b"", EV_BAD_FRAME, lambda io: io.bootups == 1),
        (0x080 + node, bytes([0x30, 0x81, 0x11, 1, 2, 3, 4, 5]), EV_EMCY,
         lambda io: io.emcy[-1][:3] == (2, 0x8130, 0x11)),
        (0x080 + node, b"\x30\x81", EV_BAD_FRAME, lambda io: len(io.emcy) == 1),
    ]
    from drivers.canbus import open_buses
    buses, inject, spare = open_buses(cfg.bus), open_buses(cfg.bus), open_buses(cfg.bus)
    try:
        io_can = CyclicIO(buses, cfg.bus, period_s=cfg.cycle.period_s)
        io_rec = CyclicIO(spare, cfg.bus, period_s=cfg.cycle.period_s)
        for cob, data, want, check in frames:
            inject[0].send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
            time.sleep(0.005)
            assert io_can.poll() == want, (hex(cob), data)
            assert check(io_can), (hex(cob), data)
            kind, i = io_rec._rx[cob]
            buf = bytearray(5) + data + bytearray(3)          # the record path: data at an offset
            assert io_rec._decode_event(kind, i, buf, 5, len(data), time.monotonic()) == want
            assert check(io_rec), (hex(cob), data)
    finally:
        for b in buses + inject + spare:
            b.shutdown()


def test_status_faults_and_sync_every_without_a_rig():
    import dataclasses
    import uuid

    from drivers.cyclic import CyclicIO
    from hexacnc.config import load_config
    cfg = load_config()
    bus_cfg = dataclasses.replace(cfg.bus, interface="virtual", channel=f"sf-{uuid.uuid4().hex[:8]}")
    tx, rx = open_buses(bus_cfg), open_buses(bus_cfg)
    try:
        ok = cia402.drive_statusword(cia402.OPERATION_ENABLED) | cia402.SW_DRIVE_FOLLOWS
        io = CyclicIO(tx, bus_cfg, status=[ok] * 6, sync_every=2)
        assert io.status_faults() == 0
        io.status[1] = ok & ~cia402.SW_REMOTE
        io.status[4] = ok & ~cia402.SW_DRIVE_FOLLOWS
        io.status[5] = cia402.drive_statusword(cia402.QUICK_STOP_ACTIVE)
        assert io.status_faults() == 0b110010
        assert io.status_faults(csp=False) == 0b100010
        got = []
        for k in range(4):                                  # bus frames on every 2nd call only
            assert io.send([0] * 6) == SEND_OK
            time.sleep(0.01)
            while (m := rx[0].recv(0)) is not None:
                got.append((k, m.arbitration_id))
        assert {k for k, c in got if c == 0x80} == {1, 3}
        assert io.end_session() == 0
        m = rx[1].recv(0.5)
        while m is not None and m.arbitration_id != 0:
            m = rx[1].recv(0.5)
        assert m is not None and bytes(m.data) == b"\x80\x00"          # NMT pre-operational, all nodes
    finally:
        for b in tx + rx:
            b.shutdown()
