"""The drives supervise the master: silence the master mid-move and decode, from the frames on the bus,
what the simulated drives did (EMCY 0x8250, quick stop ramp at 0x6085, then Switch on disabled per
0x605A); and the normal disable walks 0x0007 (0x605C ramp) before 0x0000."""
import threading
import time

import can

from drivers import cia402
from drivers.canbus import open_buses
from drivers.cyclic import SEND_OK
from hexacnc.sim.rig import SimRig
import pytest

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)


class Recorder:
    """An independent listener on every bus: (monotonic s, COB-ID, data) of each frame."""

    def __init__(self, cfg):
        self.buses = open_buses(cfg.bus)
        self.frames: list[tuple[float, int, bytes]] = []
        self.lock = threading.Lock()
        self.notifiers = [can.Notifier(b, [self._on], 0.01) for b in self.buses]

    def _on(self, msg):
        with self.lock:
            self.frames.append((time.monotonic(), msg.arbitration_id, bytes(msg.data)))

    def of(self, cob_id):
        with self.lock:
            return [(t, d) for t, c, d in self.frames if c == cob_id]

    def close(self):
        for n in self.notifiers:
            n.stop(1.0)
        for b in self.buses:
            b.shutdown()


def move(io, start, v_inc_per_cycle, n, accel_inc_per_cycle2=1.0):
    """n cycles accelerating to v_inc_per_cycle; returns the last targets."""
    x = 0.0
    for k in range(n):
        x += min(v_inc_per_cycle, accel_inc_per_cycle2 * k)
        t = [s + int(x) for s in start]
        assert io.send(t) == SEND_OK
        time.sleep(0.0005)
        io.poll()
    return t


def test_silent_master_mid_move_quick_stop_then_disabled():
    # 0.1 s: this test's process (master and drives) must not itself stall that long while moving
    with SimRig(comm_loss_timeout_s=0.1) as rig:
        rec = Recorder(rig.cfg)
        try:
            m = rig.master
            m.bring_up()
            decel_units = 10_000_000                       # 0x6085 = 1000 mm/s^2 (1e4 units/mm)
            for nd in m.plan.nodes:
                m.sdo_write(nd, "test", 0x6085, None, decel_units)
            start = m.positions_inc()
            io = rig.cyclic()
            # up to 50 mm/s (250 units of 1e-4 mm per 0.5 ms drive period) in 250 cycles, then cruise
            move(io, start, 250, 500)
            v_mm_s = [d.model.velocity_mm_s for d in rig.sim.drives]
            io.poll()
            p_silent = list(io.pos_inc)                    # last position feedback (TPDO1 frames)
            t_silent = time.monotonic()                    # the master goes silent: no SYNC, RPDO, heartbeat
            time.sleep(1.2)
            m.attach()
            p_end = m.positions_inc()                      # SDO reads of 0x6064 after the stop
            emcy = {nd.node_id: rec.of(0x80 + nd.node_id) for nd in m.plan.nodes}
            status = {nd.node_id: rec.of(0x280 + nd.node_id) for nd in m.plan.nodes}
            for nd in m.plan.nodes:
                d = rig.sim.drives[nd.index]
                codes = [(t, int.from_bytes(x[:2], "little")) for t, x in emcy[nd.node_id]]
                t_emcy = [t for t, c in codes if c == cia402.EMCY_RPDO_TIMEOUT]
                assert t_emcy, f"node {nd.node_id}: no EMCY 0x8250 (RPDO timeout): {codes}"
                # reaction after the configured 0.1 s (+ the simulated drive's 2 ms tick; on this shared,
                # loaded machine its own stalls postpone it: drivers/README.md has the 20 ms figures)
                assert 0.098 <= t_emcy[0] - t_silent < 0.1 + 0.5, t_emcy[0] - t_silent
                states = [(t, cia402.state_from_status(int.from_bytes(x[:2], "little"))) for t, x in status[nd.node_id]
                          if t > t_silent]
                seq = [s for _, s in states]
                assert cia402.QUICK_STOP_ACTIVE in seq and seq[-1] == cia402.SWITCH_ON_DISABLED, seq
                t_qs = next(t for t, s in states if s == cia402.QUICK_STOP_ACTIVE)
                t_off = next(t for t, s in states if s == cia402.SWITCH_ON_DISABLED)
                v = abs(v_mm_s[nd.index])
                assert v > 10.0, v
                ramp_s = v / 1000.0
                # stopped by the 0x6085 ramp: about v / a and v^2 / 2a (the model's own brake, 20000 mm/s^2,
                # would stop in 2.5 ms and 0.06 mm); the feedback lags by up to 3 cycles at v
                assert 0.6 * ramp_s < t_off - t_qs < ramp_s + 0.5, (t_off - t_qs, ramp_s)
                dist_mm = abs(p_end[nd.index] - p_silent[nd.index]) / rig.cfg.bus.increments_per_mm
                assert 0.9 * v * v / 2000.0 <= dist_mm <= 1.1 * v * v / 2000.0 + v * 0.003, (dist_mm, v)
                ev = [e for _, e in d.react.events]
                assert any("0x6007 = 3" in e for e in ev) and any("1000 mm/s^2" in e for e in ev), ev
        finally:
            rec.close()


def test_normal_disable_walks_0x0007_then_0x0000():
    with SimRig() as rig:
        rec = Recorder(rig.cfg)
        try:
            m = rig.master
            m.bring_up()
            start = m.positions_inc()
            io = rig.cyclic()
            last = move(io, start, 10, 200)
            io.set_all_controlwords(cia402.CW_DISABLE_OPERATION)   # transition 5: ramp per 0x605C
            moving = [abs(d.model.velocity_mm_s) for d in rig.sim.drives]
            for _ in range(200):
                io.send(last)
                time.sleep(0.0005)
                io.poll()
                if all(s == cia402.SWITCHED_ON for s in rig.sim.states()):
                    break
            assert rig.sim.states() == [cia402.SWITCHED_ON] * 6
            io.set_all_controlwords(cia402.CW_DISABLE_VOLTAGE)     # transition 10
            for _ in range(20):
                io.send(last)
                time.sleep(0.0005)
                io.poll()
            time.sleep(0.02)
            assert rig.sim.states() == [cia402.SWITCH_ON_DISABLED] * 6
            for nd in m.plan.nodes:
                cws = [int.from_bytes(x[:2], "little") for _, x in rec.of(nd.rpdo2_cob_id)]
                assert cws[-2:] == [0x0007, 0x0000], cws
                ev = [e for _, e in rig.sim.drives[nd.index].react.events]
                if moving[nd.index] > 1e-3:
                    assert any("disable operation (0x605C = 1)" in e for e in ev), ev
        finally:
            rec.close()


def test_master_disable_walk_is_5_then_10():
    with SimRig() as rig:
        rec = Recorder(rig.cfg)
        try:
            rig.master.bring_up()
            rig.master.disable()
            assert rig.sim.states() == [cia402.SWITCH_ON_DISABLED] * 6
            time.sleep(0.02)
            for nd in rig.master.plan.nodes:     # SDO downloads of 0x6040 (expedited, 2 bytes)
                cws = [int.from_bytes(x[4:6], "little") for _, x in rec.of(0x600 + nd.node_id)
                       if x[0] == 0x2B and x[1:4] == b"\x40\x60\x00"]
                assert cws[-2:] == [cia402.CW_DISABLE_OPERATION, cia402.CW_DISABLE_VOLTAGE], cws
        finally:
            rec.close()
