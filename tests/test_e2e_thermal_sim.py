"""Thermal compensation in the running daemon, fed by the simulated thermal plant (accelerated).

Real daemon (hot-loop process, simulated drives with the coupled strut/carrier model) behind its
socket: the machine moves, its struts heat in the simulated plant (1800x faster than the wall
clock), the supervisor's observer turns the probe readings into strut offsets, and the strut
commands differ from the plain inverse kinematics by exactly the offsets the loop applies.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from hexacnc import sag as sagmod
from hexacnc.config import load_config
from hexacnc.kinematics import Hexapod
from hexacnc.pose import matrix_from_euler

from e2e_fixtures import client, running_machine  # noqa: F401  (shared fixtures; cfg and machine are overridden below)

pytestmark = pytest.mark.e2e


SCALE = 1800.0
RATE_MM_S = 0.0035      # the most the 0.5 ms cycle's acceleration guard allows (3.9 um/s)


@pytest.fixture(scope="module")
def cfg():
    base = load_config(None)
    cycle = dataclasses.replace(base.cycle, max_overruns_in_row=1000, following_error_mm=25.0)
    thermal = dataclasses.replace(base.thermal, source="sim", sim_time_scale=SCALE, probe_rate_hz=5.0,
                                  max_offset_rate_mm_s=RATE_MM_S, max_offset_mm=0.3)
    dyn = dataclasses.replace(base.dynamics, simulated_drives="coupled")
    bus = dataclasses.replace(base.bus, comm_loss_timeout_s=0.5)     # as tests/e2e_fixtures.py: machine stalls
    return base.replace(cycle=cycle, thermal=thermal, dynamics=dyn, bus=bus)


@pytest.fixture(scope="module")
def machine(cfg):
    """As the shared fixture, but the hot loop and the feeder with SCHED_FIFO when permitted: this test
    moves for seconds while the accelerated plant and the coupled drives load the 2-core machine,
    and a starved feeder would end it with a dead-setpoint-source stop."""
    yield from running_machine(cfg, realtime=True, name="thermal")


def _expected_cmd(cfg, hx, st):
    """Plain IK + sag of the commanded pose (shifted back by the applied spindle growth) - applied offsets."""
    p = np.array(st["pose_cmd"], dtype=float)
    R = matrix_from_euler(*np.radians(p[3:]))
    p[:3] -= st["thermal"]["spindle_growth_mm"] * (R @ np.asarray(cfg.tool.axis_platform))
    return hx.lengths(p) + sagmod.sag_compensation_mm(hx, p) - np.array(st["thermal"]["offsets_mm"])


def _queue_moves(daemon, home) -> None:
    """Out, across and back twice at 400 mm/s: the struts travel, the simulated plant heats."""
    for _ in range(2):
        daemon.move_to(home + [120.0, 0.0, 0.0, 0.0, 0.0, 0.0], 400.0, name="out")
        daemon.move_to(home + [0.0, 80.0, -60.0, 0.0, 0.0, 0.0], 400.0, name="across")
        daemon.move_to(home, 400.0, name="back")


@pytest.mark.slow
def test_simulated_plant_drives_offsets_into_the_strut_commands(cfg, machine, client):
    daemon, srv = machine
    hx = Hexapod(cfg)
    inc = 1.0 / cfg.bus.increments_per_mm
    home = np.asarray(cfg.home_pose, dtype=float)
    st0 = client.call("status")
    th0 = st0["thermal"]
    assert th0["source"] == "sim" and th0["time_scale"] == SCALE
    sub = client.send("subscribe", rate_hz=50.0)
    _queue_moves(daemon, home)
    wid = client.send("wait", timeout_s=60.0)
    samples = []
    while True:
        m = client.next_message(60.0)
        assert m is not None
        if m.get("id") == sub and m.get("ok"):
            samples.append((m["thermal"]["loop_cycles"], np.array(m["thermal"]["offsets_mm"]),
                            m["thermal"]["spindle_growth_mm"], m["state"]))
        elif m.get("id") == wid:
            break
    assert m["state"] == "idle" and m["fault"] is None, m["fault"]
    client.call("unsubscribe")
    # let the plant and the observer run on a little at rest, offsets keep slewing
    time.sleep(1.0)
    st = client.call("status")
    th = st["thermal"]
    assert th["state"] == "ok" and th["warning"] is None and th["rejected"] == 0
    assert th["time_s"] > 3600.0                   # > 1 h of plant time went by
    off = np.array(th["offsets_mm"])
    assert np.all(off > 0.003), off                # struts grew: > 3 um offsets applied
    assert np.all(np.abs(off) <= cfg.thermal.max_offset_mm)
    # the strut commands differ from the plain IK by exactly the applied offsets (one increment)
    got = np.array(st["struts_cmd_mm"])
    want = _expected_cmd(cfg, hx, st)
    assert np.max(np.abs(got - want)) <= inc, (got - want).tolist()
    # and the drives (coupled strut/carrier model) are there too, at rest within a few increments
    assert np.max(np.abs(np.array(st["struts_act_mm"]) - want)) < 5e-3
    # the observer follows the simulated truth (its model is deliberately wrong: 10 vs 40 segments,
    # uniform vs 3:1 heat, 15 % less heat), well within the offsets' size
    est = np.array(th["strut_offsets_est_mm"])
    true = np.array(th["sim"]["strut_growth_at_reading_mm"])     # the truth when the estimate's reading was taken
    assert np.max(np.abs(est - true)) < 0.15 * np.max(np.abs(true)) + 2e-3, (est, true)
    # probes: per strut [thermal] probes, ambient, frame, spindle housing; ages from the probe rate
    assert np.array(th["probes_C"]["struts"]).shape == (6, len(cfg.thermal.probes))
    assert th["probes_age_s"] < 5.0 and th["spindle_age_s"] < 5.0      # readings at 5 Hz (slack: loaded machine)
    assert np.all(np.array(th["strut_mean_C_est"]) > th["probes_C"]["frame"])
    # rate limit: applied offsets never changed faster than max_offset_rate_mm_s between samples, in
    # the loop's own time (cycles run; the offsets in a sample are up to 8 cycles older than its count,
    # and the loop slews every 16 cycles)
    period = cfg.cycle.period_s
    for (c1, o1, g1, _), (c2, o2, g2, _) in zip(samples, samples[1:]):
        allow = RATE_MM_S * period * (c2 - c1 + 24) + 1e-9
        assert np.max(np.abs(o2 - o1)) <= allow and abs(g2 - g1) <= allow, (c2 - c1, (o2 - o1).tolist())
    assert any(np.max(np.abs(o)) > 0 for _, o, _, _ in samples)


def test_drift_with_and_without_compensation_is_reported(cfg, machine, client):
    th = client.call("status")["thermal"]
    if th["sim"]["peak_drift_z_um"]["uncompensated"] <= 5.0:      # run alone: heat the plant by motion first
        _queue_moves(machine[0], np.asarray(cfg.home_pose, dtype=float))
        client.call("wait", timeout_s=60.0)
        th = client.call("status")["thermal"]
    d = th["sim"]["drift_um"]
    assert set(d) == {"compensated", "uncompensated"} and len(d["compensated"]) == 3
    pk = th["sim"]["peak_drift_z_um"]
    assert pk["uncompensated"] > 5.0
