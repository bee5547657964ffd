"""Drive torque 0x6077 in a decimated TPDO3 (drivers/torquepdo.py): mapped by the master, sent by the
simulated drives on their staggered SYNC count, decoded by the codec; counted by the bus budget and the
bus demand."""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest

from drivers import busdemand, busload, torquepdo
from drivers.errors import BusError
from drivers.layout import plan_layout
from drivers.simtorque import LEAD_MM
from hexacnc.calib.payload import rest_forces
from hexacnc.config import load_config
from hexacnc.kinematics import Hexapod

RATED_TORQUE_MNM = 7958                         #: drivers/hexapod_drive.eds 0x6076
N_PER_PERMILLE = 2 * math.pi * RATED_TORQUE_MNM / LEAD_MM / 1000.0


def _bus(**kw):
    cfg = load_config(None)
    return cfg, dataclasses.replace(cfg.bus, **kw)


@pytest.mark.unit
def test_budget_counts_the_torque_pdo_as_blocking_within_the_reserve_and_checks_the_idle_time():
    cfg, off = _bus()
    base = busload.bus_time(off, cfg.cycle.period_s)
    assert "torque_pdo" not in base
    n = int(np.random.default_rng().integers(3, 241))
    rep = busload.bus_time(dataclasses.replace(off, torque_pdo_every=n), cfg.cycle.period_s)
    tq = rep["torque_pdo"]
    assert rep["max_us"] == base["max_us"]            # the cyclic frames' worst case is unchanged
    assert tq["bytes"] <= busload.ASYNC_RESERVE_BYTES and tq["every_syncs"] == n
    assert tq["sample_period_s"] == pytest.approx(n * cfg.cycle.period_s)
    for row in tq["per_bus"]:
        assert row["frames_per_cycle"] == pytest.approx(3 / n, abs=1e-4)
        assert row["low_priority_us_per_cycle"] < row["idle_us_per_cycle"]
    assert tq["fits"] and rep["fits"]
    assert "torque TPDO3" in busload.describe(rep)
    # a bus too full to drain its low-priority traffic does not fit
    tight = dataclasses.replace(off, torque_pdo_every=1, buses=1, feedback_divider=6)
    assert not busload.bus_time(tight, 0.0006)["torque_pdo"]["fits"]
    with pytest.raises(BusError, match="torque_pdo_every"):
        torquepdo.every(dataclasses.replace(off, torque_pdo_every=241))


@pytest.mark.unit
def test_demand_carries_one_torque_frame_per_drive_every_n_syncs_never_two_on_a_bus_in_one_cycle(monkeypatch):
    cfg, bus = _bus(torque_pdo_every=7)
    seen = []
    real = busdemand.frame_bits

    def spy(can_id, data):
        seen.append(can_id)
        return real(can_id, data)
    monkeypatch.setattr(busdemand, "frame_bits", spy)
    busdemand.simulate(bus, cfg.cycle.period_s, 0.7, True, torque_pdo=True)
    tq = [c for c in seen if 0x381 <= c <= 0x386]
    # 0.7 s = 1400 SYNCs: each drive 200 frames (+-1 for its start), both buses simulated
    for nid in range(1, 7):
        assert abs(tq.count(0x380 + nid) - 200) <= 1
    seen.clear()
    busdemand.simulate(bus, cfg.cycle.period_s, 0.2, True, torque_pdo=False)
    assert not [c for c in seen if 0x381 <= c <= 0x386]


@pytest.mark.bus
def test_simulated_drives_send_their_torque_in_tpdo3_and_the_codec_decodes_it():
    from hexacnc.sim.rig import SimRig
    n = int(np.random.default_rng().integers(3, 9))
    with SimRig(torque_pdo_every=n) as rig:
        rig.master.bring_up()
        plan = plan_layout(rig.cfg.bus)
        for nd in plan.nodes:               # the mapping the master wrote, read back from the drive
            assert rig.master._read(nd, "test", 0x1802, 2) == n
            assert rig.master._read(nd, "test", 0x1A02, 1) == 0x60770010
        sdo = [rig.master._read(nd, "test", 0x6077) for nd in plan.nodes]
        start = rig.master.positions_inc()
        io = rig.cyclic()
        cycles = 30 * n
        for _ in range(cycles):
            io.send(start)
            time.sleep(0.0005)
            io.poll()
        time.sleep(0.05)
        io.poll()
        for i in range(6):
            assert abs(io.torque_pdo_count[i] - cycles / n) <= 2, (i, io.torque_pdo_count, n)
        # at rest at home: the static load of the carrier, as the SDO read gave it
        hx = Hexapod(rig.cfg)
        model = rest_forces(hx, np.asarray(rig.cfg.home_pose, dtype=float)[None])[0] / N_PER_PERMILLE
        assert np.all(np.abs(np.asarray(io.torque_pdo_permille) - model) <= 1.0), (io.torque_pdo_permille, model)
        assert list(io.torque_pdo_permille) == sdo
