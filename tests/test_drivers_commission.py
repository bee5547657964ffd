"""Commissioning against the simulated drives: identity, 0x60C2 format, PDO layout without dummies,
units, reactions read back, boot time-out - the 'strict' profile behaves like the strictest real drives."""
import time

import pytest

from drivers import cia402
from drivers.jerkstop import STOP_SHARE
from drivers.cyclic import SEND_OK
from drivers.description import DEFAULT_EDS, STRICT_EDS, load_description
from hexacnc.sim.rig import SimRig
from hexacnc.errors import BusError

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)

STRICT_ID = (0x000001A7, 0x00402C53, 0x00030002)


def drive(io, n, targets):
    for k in range(n):
        assert io.send(targets(k)) == SEND_OK
        time.sleep(0.0005)
        io.poll()


def test_descriptions_differ_where_real_drives_do():
    p, s = load_description(str(DEFAULT_EDS)), load_description(str(STRICT_EDS))
    assert 0x0007 in p.dummies and not s.dummies
    assert p.ip_index_range == (-6, -3) and s.ip_index_range == (-3, -3)
    assert (s.vendor_id, s.product_code, s.revision) == STRICT_ID
    assert s.device_type == 0x00020192 and s.supported_modes & 0x80


def test_strict_drives_boot_with_ms_cycle_and_no_dummies_and_follow():
    with SimRig(simulate_profile="strict") as rig:
        m = rig.master
        assert m.plan.layout == "separate" and "DummyUsage" in m.plan.note
        m.bring_up()
        t = m.report["timing"]
        assert (t["value"], t["index"], t["bus_period_s"], t["sync_every"]) == (1, -3, 0.001, 2)
        assert [r["vendor_id"] for r in m.report["identity"]] == [STRICT_ID[0]] * 6
        assert m.report["identity"][0]["software_version"] == "FW 3.2.7 (simulated)"
        for nd in m.plan.nodes:              # read back: one target, no dummy entry
            assert m.sdo_read(nd, "t", 0x1600, 0) == 1 and m.sdo_read(nd, "t", 0x1600, 1) >> 16 == 0x607A
        start = m.positions_inc()
        io = rig.cyclic()
        assert io.sync_every == 2
        drive(io, 600, lambda k: [s + 20 * k for s in start])      # 1.2 mm in 600 loop cycles
        drive(io, 100, lambda k: [s + 12000 for s in start])      # hold the end
        moved = [p - s for p, s in zip(rig.sim.positions_inc(), start)]
        assert all(abs(d - 12000) <= 5 for d in moved), moved      # followed to the end (1e-4 mm units)
        assert io.frames_sent < 0.6 * 2 * 700 * 4                  # SYNC + RPDOs on every 2nd call only
        assert rig.sim.states() == [cia402.OPERATION_ENABLED] * 6


def test_description_wider_than_the_drive_falls_back_to_whole_ms():
    # the EDS claims index -6..-3, the (strict) drive takes only -3: aborts 0x06090030, then (1, -3)
    with SimRig(simulate_profile="strict", layout="single", node_identity=(STRICT_ID,) * 6,
                node_eds=(str(DEFAULT_EDS),) * 6) as rig:
        rig.master.boot()
        rig.master.configure()
        t = rig.master.report["timing"]
        assert (t["value"], t["index"], t["sync_every"]) == (1, -3, 2)
        assert len(t["refused"]) == 2 and all("0x06090030" in r for r in t["refused"])


def test_dummy_mapping_refused_by_strict_drive_before_any_enable():
    with SimRig(simulate_profile="strict", layout="paired", node_identity=(STRICT_ID,) * 6,
                node_eds=(str(DEFAULT_EDS),) * 6) as rig:
        with pytest.raises(BusError, match=r"node 1 .*PDO mapping.*0x06040041|node 1 .*PDO mapping.*refused"):
            rig.master.bring_up()
        assert rig.sim.states() == [cia402.SWITCH_ON_DISABLED] * 6


@pytest.mark.parametrize("changes,hook,match", [
    ({"node_identity": ((0x1234, -1, -1),) + ((-1, -1, -1),) * 5}, None,
     r"node 1 \(strut 1.*0x1018:01 vendor-ID: expected 0x00001234, found 0x00000000"),
    ({}, (2, 0x6502, 0x0000_0005), r"node 3 .*0x6502 supported drive modes: expected cyclic synchronous position"),
    ({}, (4, 0x1000, 0x0002_0191), r"node 5 .*0x1000 device type: expected a CiA 402 drive.*found 0x00020191"),
])
def test_wrong_drive_refused_naming_node_object_expected_found(changes, hook, match):
    with SimRig(**changes) as rig:
        if hook:
            i, index, value = hook
            rig.sim.drives[i].hooks.on_read(index, lambda sub, v=value: v)
        with pytest.raises(BusError, match=match):
            rig.master.bring_up()
        assert rig.sim.states() == [cia402.SWITCH_ON_DISABLED] * 6


def test_units_from_the_factor_group():
    with SimRig(feed_mm_per_rev=4.0) as rig:       # drives: 50000 units / rev, 4 mm lead -> 12500/mm != 10000
        with pytest.raises(BusError, match=r"units: 0x6092 feed constant 50000/1 .* 12500 units/mm.*10000"):
            rig.master.bring_up()
    with SimRig(feed_mm_per_rev=5.0) as rig:       # matches: read and accepted
        rig.master.bring_up(enable=False)
        assert rig.master.report["units"][0]["units_per_mm"] == pytest.approx(10000.0)
    with SimRig(feed_mm_per_rev=5.0, increments_per_mm=2000.0, write_factor_group=True) as rig:
        rig.master.bring_up(enable=False)           # written: 0x6092 = 2000 x 5 = 10000 units / rev
        nd = rig.master.plan.nodes[0]
        assert rig.master.sdo_read(nd, "t", 0x6092, 1) == 10000
        assert rig.sim.drives[0].k == pytest.approx(2000.0)


def test_reactions_written_and_read_back():
    with SimRig(comm_loss_timeout_s=0.03) as rig:
        rig.master.bring_up(enable=False)
        for r in rig.master.report["reactions"]:
            assert r["0x6007"] == cia402.ABORT_QUICK_STOP and r["0x605A"] == cia402.QS_QUICK_RAMP_DISABLE
            assert r["0x605C"] == cia402.DISABLE_OP_SLOW_DOWN and r["0x605E"] == cia402.FAULT_REACTION_QUICK_RAMP
            assert r["0x1029:1"] == cia402.COMM_ERROR_NO_CHANGE and r["0x1006"] == 500
            assert r["rpdo1_event_timer_ms"] == 30 and r["heartbeat_consumer"] >> 16 == 0x7F
            assert not r["missing"]
            # the drive's own quick stop at the controlled stop's share of the strut limits (units)
            ipm = rig.cfg.bus.increments_per_mm
            assert r["0x6085"] == round(STOP_SHARE * rig.cfg.max_acceleration_mm_s2[0] * ipm)
            assert r["0x60A4:1"] == round(STOP_SHARE * rig.cfg.max_jerk_mm_s3[0] * ipm)


def test_boot_timeout_names_the_silent_node():
    with SimRig(boot_timeout_s=0.3) as rig:
        rig.sim.drives[3].boot = lambda: None        # node 4 never sends its boot-up message
        with pytest.raises(BusError, match=r"node 4 .*no boot-up message within 0.3 s.*boot_timeout_s"):
            rig.master.bring_up()
