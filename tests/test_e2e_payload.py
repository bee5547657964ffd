"""Payload identification from a live recording, end to end: a daemon on simulated drives whose true machine
carries a payload the config does not know; the drives send their torque in a decimated TPDO3 ([bus]
torque_pdo_every, drivers/torquepdo.py), so ``hexacnc record``'s status stream carries torques while moving
too.  The machine visits rest poses; ``hexacnc health`` on the recording identifies the payload mass within
5 % (from the rest poses, and from the torques while moving) and proposes the ``[carrier]`` update with its
effect on sag."""
from __future__ import annotations

import dataclasses
import json
import math
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from e2e_fixtures import cfg, running_machine  # noqa: F401

from drivers.simtorque import LEAD_MM
from hexacnc.calib.output import dumps_toml
from hexacnc.calib.payload import plan_rest_poses, sag_tip_deviation
from hexacnc.calib.recording import load
from hexacnc.cli import main as cli
from hexacnc.errors import HexacncError
from hexacnc.kinematics import Hexapod
from hexacnc.sim.truth import parse_truth, synth_truth_doc

pytestmark = [pytest.mark.e2e, pytest.mark.slow]     # a daemon, five rest poses, ~1 min on the loaded 2-core VM
RATED_TORQUE_MNM = 7958                         #: drivers/hexapod_drive.eds 0x6076
N_PER_PERMILLE = 2 * math.pi * RATED_TORQUE_MNM / LEAD_MM / 1000.0
TORQUE_PDO_EVERY = 40                           #: 20 ms per drive at 0.5 ms


@pytest.fixture(scope="module")
def loaded(cfg, tmp_path_factory):  # noqa: F811
    rng = np.random.default_rng()
    payload_kg = float(rng.uniform(40.0, 150.0))          # chosen at test time; the config knows none
    doc = synth_truth_doc(cfg, int(rng.integers(1, 1000)), magnitude=0.0)
    doc["truth"]["payload_kg"] = round(payload_kg, 3)
    d = tmp_path_factory.mktemp("payload")
    path = d / "truth.toml"
    path.write_text(dumps_toml(doc))
    truth = parse_truth(doc, str(path))
    c = cfg.replace(simulation_truth=str(path), bus=dataclasses.replace(cfg.bus, torque_pdo_every=TORQUE_PDO_EVERY))
    gen = running_machine(c, name="payload")
    daemon, srv = next(gen)
    yield daemon, srv, truth, d, int(rng.integers(0, 10_000))
    next(gen, None)


def _visit(daemon, poses) -> None:
    for pose in poses:
        st = {"state": "not moved", "fault": None}
        for attempt in range(5):       # a stall of the loaded test VM can fault a move: reset, again
            try:
                if daemon.status()["state"] == "fault":
                    daemon.reset(timeout_s=30.0)
                daemon.move_to(pose, 150.0)
            except HexacncError:       # faulted between the status and the move: reset and again
                time.sleep(0.2)
                continue
            st = daemon.wait(60.0)
            if st["state"] == "idle" or attempt == 4:
                break
        assert st["state"] == "idle", st.get("fault")
        time.sleep(0.7)                # a rest pose: >= 0.3 s still for hexacnc.calib.health.rest_windows


def test_payload_identified_within_5_percent_from_a_live_recording_with_torques_in_motion(cfg, loaded):  # noqa: F811
    daemon, srv, truth, d, seed = loaded
    poses = plan_rest_poses(cfg, 5, seed=seed, candidates=400, offsets=False)
    path = d / "live.npz"
    # hexacnc record in its own process, as a user runs it; Ctrl-C (SIGINT) ends it and writes the file
    proc = subprocess.Popen([sys.executable, "-m", "hexacnc", "record", "--socket", srv.socket_path, "--out",
                             str(path), "--rate", "25", "--duration", "600"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(1.5)
        _visit(daemon, poses)
        proc.send_signal(signal.SIGINT)
        out_, err_ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err_
    r = load(path)
    # torques while moving: the TPDO3 keeps them fresh (the SDO sampler alone gives none in motion)
    v = np.max(np.abs(np.gradient(r["struts_cmd_mm"], r["t_s"], axis=0)), axis=1)
    moving = v > 5.0
    assert moving.sum() > 50
    assert np.mean(np.all(np.isfinite(r["torque_permille"][moving]), axis=1)) > 0.9
    # hexacnc health on the recording: the payload, the proposed [carrier] update, its effect on sag
    out = d / "health.json"
    assert cli(["health", "--recording", str(path), "--assumed-payload-kg", "0", "--force-per-permille",
                f"{N_PER_PERMILLE:.6f}", "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    p = rep["payload"]
    true_kg = truth.extras.payload_kg
    assert p["available"] and p["rest_poses"] >= 4, p
    print(f"payload: true {true_kg:.3f} kg, identified {p['mass_kg']:.3f} +- {p['mass_std_kg']:.3f} kg "
          f"from {p['rest_poses']} rest poses; moving samples {int(moving.sum())}, with torques "
          f"{np.mean(np.all(np.isfinite(r['torque_permille'][moving]), axis=1)):.3f}")
    assert abs(p["mass_kg"] - true_kg) <= 0.05 * true_kg, (p["mass_kg"], true_kg)
    pm = p["in_motion"]
    print(f"payload in motion: {pm.get('mass_kg', float('nan')):.3f} +- {pm.get('mass_std_kg', float('nan')):.3f} kg "
          f"from {pm.get('samples')} samples ({pm.get('reason', 'ok')})")
    assert pm["available"] and abs(pm["mass_kg"] - true_kg) <= 0.05 * true_kg, (pm, true_kg)
    assert "payload_changed" in rep["causes"]
    upd = p["proposed_update"]
    assert upd["carrier"]["mass_kg"] == pytest.approx(cfg.mass_kg + p["mass_kg"], abs=1e-3)
    # the sag change it reports is the true payload's (at its identified COG) within 5 % + 1 um
    hx = Hexapod(cfg)
    home = np.asarray(cfg.home_pose, dtype=float)
    want = np.linalg.norm(sag_tip_deviation(hx, home, true_kg, truth.cfg.tool.tip_platform_mm)[:3]
                          - sag_tip_deviation(hx, home, 0.0, None)[:3]) * 1000.0
    print(f"sag change at home: reported {upd['sag_change_at_home']['position_um']:.2f} um, true payload "
          f"{want:.2f} um")
    assert upd["sag_change_at_home"]["position_um"] == pytest.approx(want, rel=0.05, abs=1.0)
