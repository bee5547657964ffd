"""Holding brake of the simulated drives (0x2110 release / engage delays): a normal disable per 0x605C
keeps torque on until the brake is engaged, the cyclic walk (5 then 10) waits for Switched on, and the
frames on the bus show the order: 0x0007, the statusword staying Operation enabled for the engage delay,
Switched on, then 0x0000."""
import contextlib
import time

from drivers import cia402
from hexacnc.sim.rig import SimRig

from test_drivers_commloss import Recorder, move
import pytest

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)

ENGAGE_MS, RELEASE_MS = 60, 40


def _boot_with_brake(rig):
    m = rig.master
    m.boot()
    m.configure()
    for nd in m.plan.nodes:
        m.sdo_write(nd, "test", 0x2110, 1, RELEASE_MS)
        m.sdo_write(nd, "test", 0x2110, 2, ENGAGE_MS)
    m.start()
    m.enable()
    return m


@contextlib.contextmanager
def _moving_with_brake():
    """Drives booted with the brake delays, frames recorded, the struts moved 20 mm in 200 cycles:
    yields (rig, recorder, master, cyclic io, the last targets sent)."""
    with SimRig() as rig:
        rec = Recorder(rig.cfg)
        try:
            m = _boot_with_brake(rig)
            start = m.positions_inc()          # over SDO: before the cyclic exchange starts
            io = rig.cyclic()
            yield rig, rec, m, io, move(io, start, 20, 200)
        finally:
            rec.close()


def test_disable_keeps_torque_until_the_brake_is_engaged_and_the_walk_waits():
    with _moving_with_brake() as (rig, rec, m, io, last):
        assert rig.sim.states() == [cia402.OPERATION_ENABLED] * 6, [d.react.events[-2:] for d in rig.sim.drives]
        t_walk = time.monotonic()
        for _ in range(2000):                       # the loop's walk: 0x0007 until Switched on, then 0x0000
            if not io.step_towards(cia402.SWITCH_ON_DISABLED):
                break
            io.send(last)
            time.sleep(0.0005)
            io.poll()
        assert rig.sim.states() == [cia402.SWITCH_ON_DISABLED] * 6
        assert time.monotonic() - t_walk >= ENGAGE_MS * 1e-3
        time.sleep(0.02)
        for nd in m.plan.nodes:
            cw = [(t, int.from_bytes(x[:2], "little")) for t, x in rec.of(nd.rpdo2_cob_id) if t >= t_walk]
            assert [c for _, c in cw] == [0x0007, 0x0000], cw
            sw = [(t, cia402.state_from_status(int.from_bytes(x[:2], "little")))
                  for t, x in rec.of(0x280 + nd.node_id) if t >= t_walk]
            t_on = next(t for t, s in sw if s == cia402.SWITCHED_ON)
            # torque kept (Operation enabled) for at least the engage delay after 0x0007
            assert t_on - cw[0][0] >= ENGAGE_MS * 1e-3 * 0.95, (t_on - cw[0][0])
            assert all(s == cia402.OPERATION_ENABLED for t, s in sw if t < t_on)
            assert cw[1][0] >= t_on                 # 0x0000 only once the drive reported Switched on
            d = rig.sim.drives[nd.index]
            ev = [(t, e) for t, e in d.react.events]
            t_eng = next(t for t, e in ev if "holding brake engaged" in e)
            t_stop = next(t for t, e in ev if e.startswith("stopped at"))
            assert t_eng >= t_stop - 0.003 and d.react.brake.engaged
        m.attach()
        assert [m.sdo_read(nd, "test", 0x2110, 3) for nd in m.plan.nodes] == [1] * 6


def test_brake_releases_after_its_delay_on_enable():
    with SimRig() as rig:
        _boot_with_brake(rig)
        io = rig.cyclic()
        start = list(io.pos_inc)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.2:
            io.send(start)
            time.sleep(0.0005)
            io.poll()
        for d in rig.sim.drives:
            ev = d.react.events
            t_rel0 = next(t for t, e in ev if "holding brake releasing (40 ms" in e)
            t_rel = next(t for t, e in ev if e == "holding brake released")
            assert t_rel - t_rel0 >= RELEASE_MS * 1e-3 * 0.95 and not d.react.brake.engaged


def test_quick_stop_and_fault_reaction_keep_torque_until_the_brake_is_engaged():
    """Quick stop (0x605A = 2: ramp, then Switch on disabled) on struts 1-3 and a fault (0x605E = 2: ramp,
    then Fault) on strut 4, moving: each drive stays in Quick stop active / Fault reaction active, torque
    on, for the brake's engage delay after its ramp, and only then reports the state with the power off."""
    with _moving_with_brake() as (rig, rec, m, io, last):
        t0 = time.monotonic()
        for i in (0, 1, 2):
            io.set_controlword(i, cia402.CW_QUICK_STOP)
        with rig.sim.lock:
            rig.sim.drives[3].fault(0x2310)
        want = {0: cia402.SWITCH_ON_DISABLED, 1: cia402.SWITCH_ON_DISABLED, 2: cia402.SWITCH_ON_DISABLED,
                3: cia402.FAULT}
        for _ in range(2000):
            io.send(last)
            time.sleep(0.0005)
            io.poll()
            if all(rig.sim.states()[i] == s for i, s in want.items()):
                break
        assert all(rig.sim.states()[i] == s for i, s in want.items()), rig.sim.states()
        time.sleep(0.02)
        during = {0: cia402.QUICK_STOP_ACTIVE, 1: cia402.QUICK_STOP_ACTIVE, 2: cia402.QUICK_STOP_ACTIVE,
                  3: cia402.FAULT_REACTION_ACTIVE}
        for i, end in want.items():
            nd = m.plan.nodes[i]
            sw = [(t, cia402.state_from_status(int.from_bytes(x[:2], "little")))
                  for t, x in rec.of(0x280 + nd.node_id) if t >= t0]
            t_end = next(t for t, s in sw if s == end)
            assert [s for t, s in sw if t < t_end] == [during[i]], sw       # torque on until then
            assert t_end - t0 >= ENGAGE_MS * 1e-3 * 0.95, (i, t_end - t0)
            d = rig.sim.drives[i]
            ev = [(t, e) for t, e in d.react.events if t >= t0]
            assert any("holding brake engages with torque on for 60 ms" in e for _, e in ev), ev
            t_eng = next(t for t, e in ev if "holding brake engaged" in e)
            assert t_eng <= t_end and d.react.brake.engaged
