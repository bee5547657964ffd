"""The calibration cycle end to end against the daemon and its simulated drives on a true machine.

The true machine is drawn at test time (``synth-machine`` with a fresh seed; ``HEXACNC_CALIB_SEED``
repeats one): the cycle must work on machines nobody tuned it for.  The seed is in every failure
message."""
from __future__ import annotations

import json
import os
import random
import shutil
import tempfile
import time

import numpy as np
import pytest

from hexacnc.calib.cyclerun import RunOptions, run_plan, tip_of
from hexacnc.calib.output import dumps_toml
from hexacnc.calib.plan import plan as calib_plan
from hexacnc.calib.synth import sample_poses
from hexacnc.calib.verify import verify_poses
from hexacnc.cli import main as cli
from hexacnc.config import load_config
from hexacnc.daemon import calibops
from hexacnc.daemon import core
from hexacnc.daemon import protocol as P
from hexacnc.daemon.server import SocketServer
from hexacnc.sim.instruments import TouchProbe, noise_floor_um
from hexacnc.sim.truth import parse_truth, synth_truth_doc

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.fixture(scope="module")
def work():
    d = tempfile.mkdtemp(prefix="hxcal", dir="/tmp")
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(scope="module")
def machine_file(work):
    base = load_config(None)
    doc = dict(base.raw)
    # shared 2-core test VM without SCHED_FIFO: tolerate stall bursts (as tests/e2e_fixtures.py)
    doc["cycle"] = dict(doc.get("cycle", {}), max_overruns_in_row=1000, following_error_mm=25.0)
    doc["bus"] = dict(doc.get("bus", {}), comm_loss_timeout_s=0.5)      # nor the drives' RPDO deadline
    p = os.path.join(work, "machine.toml")
    with open(p, "w") as f:
        f.write(dumps_toml(doc))
    return p


SEED = int(os.environ.get("HEXACNC_CALIB_SEED") or random.SystemRandom().randrange(1, 2 ** 31))


@pytest.fixture(scope="module")
def machine(work, machine_file):
    cfg = load_config(machine_file)
    print(f"true machine: synth-machine --seed {SEED} (HEXACNC_CALIB_SEED={SEED} repeats it)")
    truth = parse_truth(synth_truth_doc(cfg, SEED), f"<truth seed {SEED}>")
    daemon = core.Daemon(cfg, realtime=False)
    calibops.attach(daemon, truth)
    srv = SocketServer(daemon, cfg, os.path.join(work, "cal.sock")).start()
    yield cfg, srv, truth
    srv.close()
    if srv.daemon is not daemon:
        srv.daemon.close()
    daemon.close()


@pytest.fixture
def client(machine):
    c = P.Client.unix(machine[1].socket_path)
    if c.call("status")["state"] == "fault":
        c.call("reset", reply_timeout_s=30.0)
    yield c
    c.close()
    time.sleep(0.05)


def _opts(inst="tracker"):
    return RunOptions(instrument=inst, settle_s=0.1, progress=False, reset_faults=20)


def test_closed_cycle_measure_resume_fit_apply_reload_verify(machine, client, work, machine_file):
    cfg, srv, truth = machine
    rng = np.random.default_rng(SEED)
    plan = calib_plan(cfg, 10, "xyzabc", 300, SEED)["poses"]        # calib plan: a small D-optimal plan
    valid = sample_poses(cfg, rng, 3)
    before = verify_poses(client, cfg, valid, _opts())
    meas = os.path.join(work, "meas.csv")
    run_plan(client, cfg, plan[:4], meas, _opts(), {"instrument": "tracker", "sigma_mm": 0.008})   # interrupted
    first = open(meas).read()
    taken = run_plan(client, cfg, plan, meas, _opts(), {"instrument": "tracker", "sigma_mm": 0.008})  # resumed
    assert [r.index for r in taken] == list(range(4, 10))
    text = open(meas).read()
    assert text.startswith(first) and len(text.splitlines()) == 11
    assert json.load(open(meas + ".json"))["target"] == "platform"
    fit, cal = os.path.join(work, "fit.toml"), os.path.join(work, "calibrated.toml")
    assert cli(["calib", "fit", "--config", machine_file, "--data", meas, "--out", fit]) == 0
    assert cli(["calib", "apply", fit, "--config", machine_file, "--out", cal]) == 0
    r = client.call("reload", config=cal, reply_timeout_s=120.0)
    assert r["config"] == cal and srv.daemon.cfg.path == cal
    assert client.call("wait", timeout_s=30.0)["state"] == "idle"
    after = verify_poses(client, load_config(cal), valid, _opts())
    assert before["measured"] == after["measured"] == 3
    # the tracker's noise alone shows ~15 um on 3 poses (their RMS scatters up to ~1.6x that): a machine with
    # little error (seed 1992010430: 196 um before) ends at the noise, not at 10 % of before
    floor = noise_floor_um("tracker", np.c_[valid[:, :3], np.radians(valid[:, 3:])], cfg.tool.tip_platform_mm)
    # the error to calibrate away (offline, 2000 seeds of synth_truth_doc at these poses: smallest 86 um, 1 %
    # under 210 um; 100 um failed one seed in 2000)
    assert before["rms_um"] > 60.0, (SEED, before["rms_um"])
    assert after["rms_um"] < max(0.1 * before["rms_um"], 2.0 * floor), (SEED, before["rms_um"], after["rms_um"], floor)


def test_external_measurement_is_paired_with_drive_readings_and_late_ones_refused(machine, client):
    cfg, srv, truth = machine
    t = time.time()
    r = client.call("measurement", instrument="mytracker", t_s=t, values={"x": 1.0, "z": -900.0})
    st = client.call("status")
    q_now = np.asarray(st["struts_act_mm"]) - np.asarray(srv.daemon.cfg.strut_offset_mm)
    assert np.allclose(r["q_mm"], q_now, atol=1e-3) and r["pair_gap_s"] <= 0.02
    got = client.call("measure", instrument="mytracker", after_t_s=t - 1.0, wait_s=1.0)
    assert got["values"] == {"x": 1.0, "z": -900.0}
    with pytest.raises(P.DaemonError, match="late"):
        client.call("measurement", instrument="mytracker", t_s=t - 3600.0, values={"x": 1.0})
    with pytest.raises(P.DaemonError, match="unknown coordinate"):
        client.call("measurement", instrument="mytracker", t_s=t, values={"w": 1.0})


def test_probing_stops_on_contact_and_reports_the_readings_at_the_edge(machine, client, work):
    from hexacnc.calib.probing import probe_sphere
    from hexacnc.sim.probesignal import SPHERE_RADIUS_MM, STYLUS_RADIUS_MM
    cfg, srv, truth = machine
    cur = srv.daemon.cfg
    c = TouchProbe().spheres[13]                         # (0, 0, -1150)
    log = os.path.join(work, "probes.jsonl")
    for attempt in range(5):            # a stall of the loaded test VM can fault the drives: reset, again
        try:
            r = probe_sphere(client, c, [0.0, 0.0, 0.0], SPHERE_RADIUS_MM + STYLUS_RADIUS_MM, log_path=log)
            break
        except Exception:
            # the fault's controlled stop may still run ("stopping"): wait for the daemon to settle first
            if attempt == 4 or client.call("wait", timeout_s=30.0)["state"] != "fault":
                raise
            client.call("reset", reply_timeout_s=30.0)
            if os.path.exists(log):
                os.remove(log)
    assert len(r["contacts"]) == 5 and len(open(log).read().splitlines()) == 5
    art = TouchProbe(0)
    shift = []                                           # controller's tip minus the true tip at each contact
    for k in r["contacts"]:
        assert k["contact"] and k["params"]["5070"] == 1
        assert [k["params"][str(5061 + i)] for i in range(6)] == pytest.approx(k["tip_pose"])
        assert 0.0 < k["overtravel_mm"] < 2.0             # stopped after contact, within the stroke left
        # the readings at the edge put the TRUE tool tip on the sphere (radius + stylus), to a micrometre
        tip = truth.tool_tip_mm(truth.platform_pose_rad(np.asarray(k["q_mm"])))
        assert abs(np.linalg.norm(tip - (c + art.sphere_error[13])) - 13.5) < 0.002
        shift.append(np.asarray(k["tip_pose"][:3]) - tip)
    # the uncalibrated machine sees the sphere where its model puts the true contacts: the true centre moved by
    # the model's mean tip error there, give or take how much that error varies over the 5 contacts (probe noise ~1 um)
    seen = c + art.sphere_error[13] + np.mean(shift, axis=0)
    spread = float(np.max(np.ptp(np.asarray(shift), axis=0)))
    assert np.linalg.norm(r["centre_mm"] - seen) < 0.004 + 2.0 * spread, (SEED, r["centre_mm"], seen, spread)
    assert np.linalg.norm(r["centre_mm"] - c) < 3.0
    assert r["residual_um"] < 5.0
    # no contact: error for G38.2, none for G38.3 (#5070 = 0)
    far = tip_of(cur, cur.home_pose)
    start = [far[0] + 50.0, far[1] + 50.0, far[2], 0.0, 0.0, 0.0]
    client.call("program", text="G53 G0 " + " ".join(f"{a}{v:.4f}" for a, v in zip("XYZABC", start)) + "\nM2\n",
                name="away", reply_timeout_s=60.0)
    client.call("wait", timeout_s=30.0)
    end = list(start)
    end[0] += 3.0
    with pytest.raises(P.DaemonError, match="without the probe tripping"):
        client.call("probe", tip_mm=end, feed_mm_min=600.0, mode="38.2", reply_timeout_s=60.0)
    assert client.call("probe", tip_mm=start, feed_mm_min=600.0, mode="38.3", reply_timeout_s=60.0)["contact"] is False


def test_reload_is_validated_and_refused_while_moving(machine, client, work):
    cfg, srv, truth = machine
    bad = os.path.join(work, "bad.toml")
    with open(bad, "w") as f:
        f.write("[geometry]\nnonsense = 1\n")
    with pytest.raises(P.DaemonError, match="reload refused"):
        client.call("reload", config=bad)
    cur = srv.daemon.cfg
    home = tip_of(cur, cur.home_pose)
    prog = f"G53 G1 X{home[0] + 40:.3f} Y{home[1]:.3f} Z{home[2]:.3f} F300\nG53 G1 X{home[0]:.3f} F300\nM2\n"
    client.call("program", text=prog, name="long", reply_timeout_s=60.0)
    with pytest.raises(P.DaemonError, match="idle"):
        client.call("reload", config=cur.path)
    assert srv.daemon.cfg is cur                            # nothing reloaded
    client.call("stop")
    if client.call("wait", timeout_s=30.0)["state"] == "fault":     # a stall of the loaded VM
        client.call("reset", reply_timeout_s=30.0)


