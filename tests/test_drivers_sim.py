"""Simulated drives and master on the virtual bus: boot, enable, follow targets, every injected fault."""
import dataclasses
import math
import time

import pytest

from drivers.layout import heartbeat_producer_ms

from hexacnc.errors import BusError
from drivers import cia402
from drivers.cyclic import EV_BOOTUP, EV_EMCY, SEND_OK
from drivers.simdrive import FaultSpec, SecondOrderStrut
from hexacnc.sim.rig import SimRig


pytestmark = pytest.mark.bus


def run(io, n, targets, period_s=0.0005):
    """n cycles of targets(k) -> OR of poll events; returns (events, cycles run)."""
    ev = 0
    for k in range(n):
        assert io.send(targets(k)) == SEND_OK
        time.sleep(period_s)
        ev |= io.poll()
    return ev


def run_until(io, cond, targets, timeout_s, period_s=0.0005):
    ev, k = 0, 0
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert io.send(targets(k)) == SEND_OK
        time.sleep(period_s)
        ev |= io.poll()
        k += 1
        if cond():
            return ev, True
    return ev, False


def test_boot_six_nodes_to_operation_enabled_and_back():
    with SimRig() as rig:
        m = rig.master
        m.boot()
        assert all(t > 0 for t in m.bootup_s)
        m.configure()
        m.start()
        assert m.nmt_states == [5] * 6                      # heartbeats report OPERATIONAL
        for nd in m.plan.nodes:
            assert m._read(nd, "test", 0x6061) == cia402.MODE_CSP
            assert m._read(nd, "test", 0x1017) == heartbeat_producer_ms(rig.cfg.bus.heartbeat_ms, nd.index)
        m.enable()
        assert [cia402.state_from_status(s) for s in m.statuswords()] == [cia402.OPERATION_ENABLED] * 6
        assert rig.sim.states() == [cia402.OPERATION_ENABLED] * 6
        m.disable()
        assert rig.sim.states() == [cia402.SWITCH_ON_DISABLED] * 6
        m.enable()
        m.quick_stop()
        time.sleep(0.05)
        assert rig.sim.states() == [cia402.SWITCH_ON_DISABLED] * 6   # quick stop, then 12 at standstill


def test_cyclic_targets_are_followed_by_the_simulated_drives():
    with SimRig() as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        io = rig.cyclic()
        amp = [20000, -15000, 10000, -5000, 30000, 25000]        # up to 3 mm
        n = 600

        def tg(k):
            s = 0.5 - 0.5 * math.cos(math.pi * min(k, n) / n)
            return [start[i] + round(amp[i] * s) for i in range(6)]
        ev = run(io, n + 200, tg)
        assert not ev & EV_EMCY, list(io.emcy)
        final = tg(n)
        sim_pos = rig.sim.positions_inc()
        for i in range(6):
            assert abs(sim_pos[i] - final[i]) <= 5, (i, sim_pos[i], final[i])
            assert abs(io.pos_inc[i] - sim_pos[i]) <= 5                 # feedback frames reach the master
            assert io.status[i] & cia402.SW_DRIVE_FOLLOWS
        assert io.heartbeat_lost() == 0
        # back to the slow path: the master resumes its heartbeat and disables the drives
        rig.master.attach()
        rig.master.disable()
        time.sleep(rig.cfg.bus.heartbeat_timeout_ms * 1e-3 + 0.1)
        assert rig.sim.states() == [cia402.SWITCH_ON_DISABLED] * 6
        assert not any(code == cia402.EMCY_HEARTBEAT for _i, code, *_r in rig.master.emcy_log)


def test_unanswering_node_is_named():
    with SimRig() as rig:
        # the master expects node 9 where the simulator has node 6
        cfg = rig.cfg.replace(bus=dataclasses.replace(rig.cfg.bus, node_ids=(1, 2, 3, 4, 5, 9)))
        from drivers.master import Master
        rig.master.detach()
        m = Master(cfg, rig.master_buses)
        try:
            with pytest.raises(BusError, match=r"node 9 \(strut 6, bus 1\): boot: no boot-up"):
                m.boot(timeout_s=0.5)
        finally:
            m.detach()


def test_refusing_drive_is_named_with_its_state():
    with SimRig(faults=[FaultSpec(5, "refuse")]) as rig:
        with pytest.raises(BusError) as ei:
            rig.master.bring_up(timeout_s=0.5)
        msg = str(ei.value)
        assert "node 5 (strut 5" in msg and "Switched on" in msg and "transition 4" in msg
        assert rig.sim.states()[4] == cia402.SWITCHED_ON
        assert all(s == cia402.OPERATION_ENABLED for i, s in enumerate(rig.sim.states()) if i != 4)


def test_emcy_injection_faults_the_drive_and_is_decoded():
    # 0.5 s after the enable: the cyclic I/O below is running by then (0.05 s was often too early on a loaded
    # machine: the EMCY came while only the SDO master listened)
    with SimRig(faults=[FaultSpec(2, "emcy", 0x3210, 0.5)]) as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        io = rig.cyclic()
        ev, ok = run_until(io, lambda: cia402.state_from_status(io.status[1]) == cia402.FAULT,
                           lambda k: start, 2.0)
        assert ok and ev & EV_EMCY
        strut, code, reg, data, t = io.emcy[0]
        assert (strut, code) == (1, 0x3210) and reg & 0x04
        assert cia402.emcy_text(code, reg) == "0x3210 DC link over-voltage [generic, voltage]"
        assert [cia402.state_from_status(s) for i, s in enumerate(io.status) if i != 1] == [cia402.OPERATION_ENABLED] * 5
        # fault reset through the cyclic controlword (non-blocking walk), then enable again
        for _ in range(400):
            if not io.step_towards(cia402.OPERATION_ENABLED, mask=1 << 1):
                break
            run(io, 4, lambda k: [io.pos_inc[1] if i == 1 else start[i] for i in range(6)])
        assert io.step_towards(cia402.OPERATION_ENABLED) == 0
        assert cia402.state_from_status(io.status[1]) == cia402.OPERATION_ENABLED
        assert any(c == 0 for s, c, *_ in io.emcy if s == 1)            # EMCY error reset after 15


def test_lost_drive_heartbeat_is_detected():
    with SimRig(faults=[FaultSpec(3, "heartbeat", 0.0)]) as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        io = rig.cyclic()
        timeout_s = rig.cfg.bus.heartbeat_timeout_ms * 1e-3
        ev, ok = run_until(io, lambda: io.heartbeat_lost() != 0, lambda k: start, timeout_s + 0.5)
        assert ok and io.heartbeat_lost() == 1 << 2
        assert time.monotonic() - io.last_heartbeat_s[2] > timeout_s
        assert all(time.monotonic() - io.last_heartbeat_s[i] < timeout_s for i in (0, 1, 3, 4, 5))


def test_stuck_strut_gives_following_error():
    with SimRig(faults=[FaultSpec(4, "stuck", 0.0)]) as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        io = rig.cyclic()
        # 20 mm/s on every strut: strut 4 does not move, its following error passes 1 mm in ~50 ms
        ev, ok = run_until(io, lambda: any(c == cia402.EMCY_FOLLOWING_ERROR for *_x, c, _r, _d, _t in
                                           [(e[0], e[1], e[2], e[3], e[4]) for e in io.emcy]),
                           lambda k: [s + 100 * k for s in start], 2.0)
        assert ok, list(io.emcy)
        assert io.emcy[0][0] == 3 and io.emcy[0][1] == 0x8611
        ev, ok = run_until(io, lambda: cia402.state_from_status(io.status[3]) == cia402.FAULT,
                           lambda k: start, 1.0)
        assert ok, cia402.status_text(io.status[3])
        assert "following error" in cia402.emcy_text(io.emcy[0][1])
        assert cia402.state_from_status(io.status[0]) == cia402.OPERATION_ENABLED


def test_master_silence_stops_the_drives_per_0x6007():
    with SimRig(comm_loss_timeout_s=0.05) as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        io = rig.cyclic()
        run(io, 10, lambda k: start)
        time.sleep(rig.cfg.bus.heartbeat_timeout_ms * 1e-3 + 0.15)     # the loop "dies": no SYNC, no heartbeat
        io.poll()
        # RPDO deadline (0x1400:05 = comm_loss_timeout_s) first, then the heartbeat consumer (0x1016)
        assert sorted(e[0] for e in io.emcy if e[1] == cia402.EMCY_RPDO_TIMEOUT) == list(range(6))
        assert sorted(e[0] for e in io.emcy if e[1] == cia402.EMCY_HEARTBEAT) == list(range(6))
        # 0x6007 = 3 quick stop, 0x605A = 2: quick stop ramp then Switch on disabled (not Fault)
        assert rig.sim.states() == [cia402.SWITCH_ON_DISABLED] * 6


def test_sdo_fault_injection_object():
    with SimRig() as rig:
        rig.master.bring_up()
        nd = rig.master.plan.nodes[5]
        rig.master._write(nd, "inject", 0x2000, 2, 0)
        rig.master._write(nd, "inject", 0x2000, 1, 0x4310)
        time.sleep(0.05)
        assert rig.sim.states()[5] in (cia402.FAULT, cia402.FAULT_REACTION_ACTIVE)
        assert rig.master._read(nd, "count", 0x2000, 6) == 1
        assert any("excess temperature drive" in t for t in rig.master.emcy_texts())
        with pytest.raises(BusError, match="node 6 .*Fault.*0x4310"):
            rig.master.enable(timeout_s=0.3)
        rig.master.fault_reset()
        rig.master.enable()
        assert rig.sim.states()[5] == cia402.OPERATION_ENABLED


def test_nmt_reset_while_cycling_is_reported():
    with SimRig() as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        io = rig.cyclic()
        run(io, 5, lambda k: start)
        rig.master_buses[0].send(__import__("can").Message(arbitration_id=0, data=[0x81, 2], is_extended_id=False))
        ev, ok = run_until(io, lambda: io.bootups > 0, lambda k: start, 1.0)
        assert ok and ev & EV_BOOTUP and io.nmt_state[1] in (0, 127)


def test_second_order_model_limits_and_settles():
    m = SecondOrderStrut(natural_hz=50, damping=0.9, max_velocity_mm_s=100.0, max_acceleration_mm_s2=2000.0)
    m.reset(0.0)
    dt, xs, vs = 0.0005, [], []
    for _ in range(4000):                   # 10 mm step
        xs.append(m.step(10.0, dt, True))
        vs.append(m.velocity_mm_s)
    assert max(abs(v) for v in vs) <= 100.0 + 1e-9
    acc = [abs(vs[k + 1] - vs[k]) / dt for k in range(len(vs) - 1)]
    assert max(acc) <= 2000.0 * 1.0001
    assert abs(xs[-1] - 10.0) < 1e-3
    assert xs[int(0.1 / dt)] < 10.0        # rate limited: 10 mm need > 0.1 s at 100 mm/s
    # disabled: brakes to rest at the acceleration limit
    m.reset(0.0)
    for _ in range(200):
        m.step(5.0 + 0.05 * _, dt, True)
    v0 = m.velocity_mm_s
    n = 0
    while abs(m.velocity_mm_s) > 0 and n < 10000:
        m.step(0.0, dt, False)
        n += 1
    assert n * dt == pytest.approx(abs(v0) / 2000.0, abs=2 * dt)


class IdealStrut:
    """A plug-in model: follows the target exactly (counts its calls)."""

    def __init__(self):
        self.velocity_mm_s = 0.0
        self.x = 0.0
        self.steps = 0

    def reset(self, position_mm):
        self.x = position_mm

    def step(self, target_mm, dt_s, enabled):
        self.steps += 1
        if enabled:
            self.velocity_mm_s = (target_mm - self.x) / dt_s
            self.x = target_mm
        else:
            self.velocity_mm_s = 0.0
        return self.x


def test_pluggable_strut_model():
    models = []

    def factory(strut, cfg):
        models.append(IdealStrut())
        return models[-1]
    with SimRig(model_factory=factory) as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        io = rig.cyclic()
        run(io, 50, lambda k: [s + 7 * k * (i + 1) for i, s in enumerate(start)])
        time.sleep(0.02)
        assert rig.sim.positions_inc() == [s + 7 * 49 * (i + 1) for i, s in enumerate(start)]
        assert len(models) == 6 and all(m.steps >= 50 for m in models)


def test_fault_spec_parsing():
    assert FaultSpec.parse("3:emcy:0x3210@1.5") == FaultSpec(3, "emcy", 0x3210, 1.5)
    assert FaultSpec.parse("2:heartbeat@2") == FaultSpec(2, "heartbeat", 0x1000, 2.0)
    assert FaultSpec.parse("5:refuse") == FaultSpec(5, "refuse", 0x1000, 0.0)
    for bad in ("x:stuck", "3:melt", "3:stuck:7", "0:stuck", "3:emcy:0x1FFFF", "3:stuck@-1"):
        with pytest.raises(Exception, match="--fault"):
            FaultSpec.parse(bad)
