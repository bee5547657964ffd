"""Homing mode 6 of the simulated drives (drivers.simhoming): methods 35/37 and limit-switch 17/18,
statusword bits 10/12/13, controlword bit 4, on-the-fly switching between modes 6 and 8."""
import struct
import time

import pytest

from drivers import cia402, simhoming
from drivers.cyclic import SEND_OK
from hexacnc.sim.rig import SimRig

pytestmark = pytest.mark.bus

CW_HOME = cia402.CW_ENABLE_OPERATION | simhoming.CW_HOMING_START


def sdo(rig, i, index, sub, fmt, value):
    rig.master.nodes[i].sdo.download(index, sub, struct.pack(fmt, value))


def sdo_read(rig, i, index, sub, fmt):
    return struct.unpack(fmt, rig.master.nodes[i].sdo.upload(index, sub))[0]


def cycle_until(io, targets, cond, timeout_s):
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        assert io.send(targets) == SEND_OK
        time.sleep(0.0005)
        io.poll()
        if cond():
            return True
    return False


def setup_homing(rig, method, offsets, search=40000, zero=10000, acc=400000):
    m = rig.master
    m.bring_up()
    for i in range(6):
        sdo(rig, i, 0x6098, 0, "<b", method[i] if isinstance(method, list) else method)
        sdo(rig, i, 0x6099, 1, "<I", search)
        sdo(rig, i, 0x6099, 2, "<I", zero)
        sdo(rig, i, 0x609A, 0, "<I", acc)
        sdo(rig, i, 0x607C, 0, "<i", offsets[i])
        sdo(rig, i, 0x6060, 0, "<b", simhoming.MODE_HOMING)     # while Operation enabled: on the fly
        assert sdo_read(rig, i, 0x6061, 0, "<b") == simhoming.MODE_HOMING
    sw = m.statuswords()
    assert all(s & cia402.SW_TARGET_REACHED and not s & simhoming.SW_HOMING_ATTAINED for s in sw)


def test_method_35_sets_the_position_to_the_home_offset_without_moving():
    with SimRig() as rig:
        start = None
        rig.master.bring_up()
        start = rig.master.positions_inc()
        offsets = [start[i] + 1000 * (i + 1) for i in range(6)]
        setup_homing(rig, 35, offsets)
        phys0 = [d.model.x for d in rig.sim.drives]
        io = rig.cyclic(controlword=cia402.CW_ENABLE_OPERATION)
        io.set_all_controlwords(CW_HOME)
        held = list(start)          # the cyclic target: ignored in mode 6
        assert cycle_until(io, held, lambda: all(s & simhoming.SW_HOMING_ATTAINED for s in io.status), 2.0)
        for i, d in enumerate(rig.sim.drives):
            assert d.pos_inc == offsets[i]
            assert abs(d.homing.shift_inc - 1000 * (i + 1)) <= 1
            assert abs(d.model.x - d.pos_inc / d.k) < 1e-9
            assert abs((d.pos_inc - d.homing.shift_inc) / d.k - phys0[i]) < 2e-3     # not moved
            assert io.status[i] & cia402.SW_TARGET_REACHED and not io.status[i] & simhoming.SW_HOMING_ERROR
        assert cycle_until(io, held, lambda: all(p == o for p, o in zip(io.pos_inc, offsets)), 1.0)


def test_limit_switch_methods_move_to_the_switch_and_set_the_offset_there():
    with SimRig() as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        offsets = [500] * 6
        methods = [17, 18, 17, 18, 17, 18]
        setup_homing(rig, methods, offsets)
        sw_mm = [d.homing.home_switch_mm for d in rig.sim.drives]
        io = rig.cyclic(controlword=cia402.CW_ENABLE_OPERATION)
        io.set_all_controlwords(CW_HOME)
        moved = [0.0] * 6

        def watch():
            for i, d in enumerate(rig.sim.drives):
                moved[i] = max(moved[i], abs((d.pos_inc - d.homing.shift_inc) - start[i]) / d.k)
            return all(s & simhoming.SW_HOMING_ATTAINED for s in io.status)
        assert cycle_until(io, list(start), watch, 6.0), [hex(s) for s in io.status]
        for i, d in enumerate(rig.sim.drives):
            edge_mm = sw_mm[i][0] if methods[i] == 17 else sw_mm[i][1]
            phys_mm = (d.pos_inc - d.homing.shift_inc) / d.k
            # the strut stands just past the releasing edge; its position reads offset + that distance,
            # the edge latched at the drive's cycle: within one cycle of travel at the zero speed
            # (10000 increments/s) plus the rounding
            assert abs(phys_mm - edge_mm) < 0.05, (i, phys_mm, edge_mm)
            assert abs(d.pos_inc - (500 + (phys_mm - edge_mm) * d.k)) <= 10000 * d._dt_s + 2
            assert moved[i] >= simhoming.SWITCH_FROM_START_MM - 0.05     # it really went to the switch
            assert (phys_mm - start[i] / d.k) * (-1 if methods[i] == 17 else 1) > 1.9
        # back to cyclic synchronous position on the fly, targets = the measured positions: no step
        pos = list(io.pos_inc)
        io.set_all_controlwords(cia402.CW_ENABLE_OPERATION)
        io.send(pos)
        rig.master.attach()
        for i in range(6):
            sdo(rig, i, 0x6060, 0, "<b", cia402.MODE_CSP)
        assert [cia402.state_from_status(s) for s in rig.master.statuswords()] == [cia402.OPERATION_ENABLED] * 6
        for i, d in enumerate(rig.sim.drives):
            assert d.mode == cia402.MODE_CSP
            assert abs(d.target_inc - d.pos_inc) <= 2


def test_unknown_method_is_a_homing_error():
    with SimRig() as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        setup_homing(rig, 1, start)              # method 1 (index pulse) is not simulated
        io = rig.cyclic(controlword=cia402.CW_ENABLE_OPERATION)
        io.set_all_controlwords(CW_HOME)
        assert cycle_until(io, list(start), lambda: all(s & simhoming.SW_HOMING_ERROR for s in io.status), 2.0)
        assert not any(s & simhoming.SW_HOMING_ATTAINED for s in io.status)
        assert [d.pos_inc for d in rig.sim.drives] == start


def test_switch_search_gives_up_after_the_travel_limit():
    with SimRig() as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        for d in rig.sim.drives:
            d.homing.home_switch_mm = (-1e9, 1e9)        # no switch anywhere
        setup_homing(rig, 18, start, search=2_000_000, acc=20_000_000)
        old = simhoming.MAX_SEARCH_MM
        simhoming.MAX_SEARCH_MM = 3.0
        try:
            io = rig.cyclic(controlword=cia402.CW_ENABLE_OPERATION)
            io.set_all_controlwords(CW_HOME)
            assert cycle_until(io, list(start), lambda: all(s & simhoming.SW_HOMING_ERROR for s in io.status), 4.0)
        finally:
            simhoming.MAX_SEARCH_MM = old


def test_a_power_cycle_drops_the_home_shift_and_the_reference():
    """NMT reset node: the position counter restarts from the raw encoder count (the power-up scale)."""
    with SimRig() as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        offsets = [start[i] + 500 * (i + 1) for i in range(6)]
        setup_homing(rig, 35, offsets)
        io = rig.cyclic(controlword=cia402.CW_ENABLE_OPERATION)
        io.set_all_controlwords(CW_HOME)
        assert cycle_until(io, list(start), lambda: all(s & simhoming.SW_HOMING_ATTAINED for s in io.status), 2.0)
        d = rig.sim.drives[2]
        assert d.homing.referenced and d.pos_inc == offsets[2]
        with rig.sim.lock:
            d.on_nmt(0x81)
        assert not d.homing.referenced and d.homing.shift_inc == 0
        assert abs(d.pos_inc - start[2]) <= 2            # the raw count again: the shift of 1500 is gone
        assert abs(d.model.x - d.pos_inc / d.k) < 1e-9
        assert rig.sim.drives[1].pos_inc == offsets[1]   # the others keep theirs
