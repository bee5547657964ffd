"""SYNC loss: the simulated drives supervise the SYNC with the time-out the master configured (0x2010,
read back; else 1.5 x 0x1006) and react per 0x6007 (quick stop) / 0x605A with their 0x6085 ramp,
decoded from the frames on the bus (EMCY 0x8700, statuswords)."""
import time

from drivers import cia402
from drivers.simreact import sync_loss_timeout_s
from hexacnc.sim.rig import SimRig

from test_drivers_commloss import Recorder, move
import pytest

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)


def test_sync_loss_timeout_rule():
    assert sync_loss_timeout_s(30, 500) == 0.03            # 0x2010 set: it
    assert sync_loss_timeout_s(0, 500) == 0.00075          # else 1.5 x 0x1006
    assert sync_loss_timeout_s(0, 0) == 0.0                # 0x1006 = 0: no SYNC supervision


def test_master_writes_and_reads_back_the_sync_loss_timeout():
    with SimRig(comm_loss_timeout_s=0.04) as rig:
        rig.master.bring_up(enable=False)
        reps = rig.master.report["reactions"]
        assert [r["0x2010"] for r in reps] == [40] * 6
        assert all(d.react.sync_loss_s == 0.04 for d in rig.sim.drives)


def test_sync_stops_the_drives_quick_stop_on_their_0x6085_ramp():
    # RPDO deadline 0.5 s (the rig's comm_loss_timeout_s), master heartbeat consumer 350 ms; SYNC-loss time-out
    # 100 ms: SYNC loss comes first (100 ms: this process's own stalls while it moves must stay below it)
    with SimRig() as rig:
        rec = Recorder(rig.cfg)
        try:
            m = rig.master
            m.boot()
            m.configure()
            for nd in m.plan.nodes:
                m.sdo_write(nd, "test", 0x2010, None, 100)
                m.sdo_write(nd, "test", 0x6085, None, 10_000_000)      # 1000 mm/s^2 (1e4 units/mm)
            m.start()
            m.enable()
            start = m.positions_inc()
            io = rig.cyclic()
            move(io, start, 100, 300)                  # 20 mm/s after 100 cycles
            v_mm_s = [d.model.velocity_mm_s for d in rig.sim.drives]
            t_silent = time.monotonic()                # no SYNC from here (nor RPDO, heartbeat)
            time.sleep(0.3)
            states = rig.sim.states()
            for nd in m.plan.nodes:
                d = rig.sim.drives[nd.index]
                codes = [(t, int.from_bytes(x[:2], "little")) for t, x in rec.of(0x80 + nd.node_id)]
                assert codes and codes[0][1] == cia402.EMCY_SYNC_LOSS, codes        # not the RPDO deadline
                assert 0.099 <= codes[0][0] - t_silent < 0.1 + 0.2, codes[0][0] - t_silent
                seq = [cia402.state_from_status(int.from_bytes(x[:2], "little"))
                       for t, x in rec.of(0x280 + nd.node_id) if t > t_silent]
                assert cia402.QUICK_STOP_ACTIVE in seq and seq[-1] == cia402.SWITCH_ON_DISABLED, seq
                assert set(seq[:seq.index(cia402.QUICK_STOP_ACTIVE)]) <= {cia402.OPERATION_ENABLED}, seq
                assert states[nd.index] == cia402.SWITCH_ON_DISABLED
                ev = [e for _, e in d.react.events]
                assert any("no SYNC for 100 ms" in e and "0x6007 = 3" in e for e in ev), ev
                assert abs(v_mm_s[nd.index]) > 5 and any("1000 mm/s^2" in e for e in ev), ev
        finally:
            rec.close()
