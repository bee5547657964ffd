"""CiA 402 touch probe 1 (0x60B8-0x60BB) of the simulated drives; its input from the true machine."""
import time

import numpy as np
import pytest

from drivers.touchprobe import (FN_CONTINUOUS, FN_ENABLE, FN_NEG_EDGE, FN_POS_EDGE, ST_ENABLED, ST_NEG_STORED,
                                ST_POS_STORED, TouchProbe)

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)


def test_latch_interpolates_the_edge_and_keeps_the_first_event():
    tp = TouchProbe()
    tp.sample(100, 1.0)                        # disabled: ignored
    assert tp.status == 0
    tp.write_function(FN_ENABLE | FN_POS_EDGE | FN_NEG_EDGE)
    assert tp.status == ST_ENABLED
    for pos, sig in ((0, 3.0), (100, 1.0), (200, -1.0), (300, -3.0)):   # contact between 100 and 200
        tp.sample(pos, sig)
    assert tp.status & ST_POS_STORED and tp.pos_value == 150
    tp.sample(400, 1.0)                        # release between 300 and 400 at signal 0: 300 + 3/4 * 100
    assert tp.status & ST_NEG_STORED and tp.neg_value == 375
    tp.sample(500, -1.0)                       # second contact: first-event mode keeps 150
    assert tp.pos_value == 150
    tp.write_function(FN_ENABLE | FN_POS_EDGE | FN_NEG_EDGE | FN_CONTINUOUS)
    tp.sample(600, 1.0)
    tp.sample(700, -1.0)
    assert tp.pos_value == 650
    tp.write_function(0)
    assert tp.status == 0


def test_simulated_drive_latches_its_position_at_the_input_edge_not_a_cycle_later():
    from drivers.cyclic import SEND_OK
    from hexacnc.sim.rig import SimRig
    with SimRig() as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        nd = rig.master.plan.nodes[0]
        threshold = start[0] + 20000                   # contact when drive 1 passes +2 mm
        k = rig.sim.increments_per_mm

        def signal(strut, now, d=rig.sim.drives[0]):
            return (threshold - d.pos_inc) / k          # mm to go, <= 0 in contact
        rig.sim.probe_signal = signal
        rig.master._write(nd, "probe", 0x60B8, None, FN_ENABLE | FN_POS_EDGE)
        assert rig.master._read(nd, "probe", 0x60B9) == ST_ENABLED
        io = rig.cyclic()
        n = 400                                         # 4 mm in 0.2 s: 20 mm/s, 10 um per cycle
        for j in range(n + 100):
            t = [start[i] + (round(40000 * min(j, n) / n) if i == 0 else 0) for i in range(6)]
            assert io.send(t) == SEND_OK
            time.sleep(0.0005)
            io.poll()
        rig.master.attach()
        st = rig.master._read(nd, "probe", 0x60B9)
        latched = rig.master._read(nd, "probe", 0x60BA)
        assert st & ST_POS_STORED
        assert abs(latched - threshold) <= 2, (latched, threshold)     # within 0.2 um of the edge
        rig.master.disable()


def test_probe_signal_is_the_true_tool_tips_distance_to_the_nearest_sphere():
    from hexacnc.config import load_config
    from hexacnc.sim.probesignal import ProbeSignal
    from hexacnc.sim.truth import parse_truth, synth_truth_doc
    cfg = load_config(None)
    tm = parse_truth(synth_truth_doc(cfg, 3))

    class Drive:
        def __init__(self, i, inc):
            self.strut, self.pos_inc = i, inc

    class Sim:
        increments_per_mm = 10000.0
    sim = Sim()
    q = tm.hx.lengths(cfg.home_pose) - cfg.strut_offset_mm
    sim.drives = [Drive(i, round(q[i] * 1e4)) for i in range(6)]
    spheres = np.array([[0.0, 0.0, -1170.0], [300.0, 0.0, -1150.0]])
    sig = ProbeSignal(tm, sim, spheres, radius_mm=13.5)
    qm = np.array([d.pos_inc / 1e4 for d in sim.drives])
    want = np.min(np.linalg.norm(spheres - tm.tool_tip_mm(tm.platform_pose_rad(qm))[None], axis=1)) - 13.5
    for t in range(3):                              # converges within a step or two of Newton
        got = sig(0, float(t))
        for d in sim.drives:                        # every drive stepped (the per-step hook)
            sig.count_step(d, float(t))
    assert got == pytest.approx(want, abs=1e-6)
    assert sig(5, 3.0) == sig(0, 3.0)               # one evaluation per step, the same for every drive


def test_probe_signal_between_exact_evaluations_matches_the_exact_distance():
    """The per-SYNC value (first order about the last exact evaluation) against a fresh exact one, along
    a probing stroke at 2.5 um of strut travel per step, with the dynamic deflection changing."""
    from hexacnc.config import load_config
    from hexacnc.sim.probesignal import ProbeSignal
    from hexacnc.sim.truth import parse_truth, synth_truth_doc
    cfg = load_config(None)
    tm = parse_truth(synth_truth_doc(cfg, 5))
    X0 = np.array(cfg.home_pose, dtype=float)
    X0[3:] = np.radians(X0[3:])
    spheres = (tm.tool_tip_mm(X0) - [0.0, 0.0, 13.5 + 0.3])[None]     # 0.3 mm over the sphere, moving down
    sig = ProbeSignal(tm, None, spheres, radius_mm=13.5)
    q0 = tm.hx.lengths_rad(X0) - cfg.strut_offset_mm
    dq = tm.hx.lengths_rad(X0 - np.r_[0, 0, 0.6, 0, 0, 0]) - cfg.strut_offset_mm - q0
    worst, crossed = 0.0, False
    for i in range(240):
        q = q0 + dq * i / 239
        extra = 1e-3 * np.sin(np.arange(6) + i / 30)
        got = sig.distance_mm(q, i * 5e-4, extra)
        ref = ProbeSignal(tm, None, spheres, radius_mm=13.5)
        ref._X = sig._X.copy()
        want = ref.exact_mm(ref.lengths_mm(q, i * 5e-4, extra), i * 5e-4)
        worst = max(worst, abs(got - want))
        crossed = crossed or got <= 0.0
    assert crossed and worst < 1e-4, worst
