"""G38.2-G38.5 in programs and MDI, end to end: the daemon runs up to the probe, probes the simulated
artefact (a true machine equal to the model, so the contact is where the artefact's surface is),
sets #5061-#5070 and only then lets the interpreter go on."""
from __future__ import annotations

import numpy as np
import pytest
from e2e_fixtures import cfg, client, running_machine  # noqa: F401

from hexacnc.calib.output import dumps_toml
from hexacnc.daemon import calibops
from hexacnc.daemon.jog import tip_poses
from hexacnc.daemon import protocol as P
from hexacnc.sim.instruments import TouchProbe
from hexacnc.sim.probesignal import SPHERE_RADIUS_MM, STYLUS_RADIUS_MM
from hexacnc.sim.truth import parse_truth, synth_truth_doc

# Once a known failure on the 2-core test VM (a drive's heartbeat lost, the setpoint ring run empty in the
# first move): the simulated drives' bus threads starved their own heartbeat threads, and 0.3 s of queued
# setpoints did not cover the supervisor's stalls ([daemon] feed_ahead_s, 1.0 s since)
pytestmark = pytest.mark.e2e
R = SPHERE_RADIUS_MM + STYLUS_RADIUS_MM
C = TouchProbe().spheres[13]                  # sphere centre (0, 0, -1150), machine frame
CENTRE = C + TouchProbe(0).sphere_error[13]   # where it really is (artefact calibration error ~1 um)


@pytest.fixture(scope="module")
def machine(cfg, tmp_path_factory):  # noqa: F811
    doc = synth_truth_doc(cfg, 3, magnitude=0.0)
    path = tmp_path_factory.mktemp("truth") / "truth.toml"
    path.write_text(dumps_toml(doc))
    truth = parse_truth(doc, str(path))
    cfg = cfg.replace(simulation_truth=str(path))       # the simulated drives' probe input (their latch)
    gen = running_machine(cfg, name="probe")
    daemon, srv = next(gen)
    calibops.attach(daemon, truth)
    yield daemon, srv
    srv.daemon.calib_history.stop_event.set()
    next(gen, None)


def _run(client, text, name="probe.ngc"):
    for attempt in range(3):     # a stall of the loaded 2-core test VM can fault the drives: reset, again
        try:
            return client.call("program", text=text, name=name, reply_timeout_s=120.0)
        except P.DaemonError:
            if attempt == 2 or client.call("wait", timeout_s=30.0)["state"] != "fault":
                raise
            client.call("reset", reply_timeout_s=30.0)


HEAD = "G21 G90 G94\nG10 L2 P1 X0 Y0 Z0\nG54\n"


def test_probe_sets_results_and_the_program_moves_to_them(machine, client):
    # top of the sphere from above, then from the side along +X; the program moves relative to #5061/#5063
    text = HEAD + (f"G1 X{C[0]:.3f} Y{C[1]:.3f} Z{C[2] + 16:.3f} F3000\n"
                   f"G38.2 Z{C[2]:.3f} F600\n"
                   "#<ztop> = #5063\n"
                   "G1 Z[#5063 + 2]\n"
                   f"G0 X{C[0] - 18:.3f}\nG0 Z{C[2]:.3f}\n"
                   f"G38.2 X{C[0]:.3f} F600\n"
                   "#<xside> = #5061\n#<ok> = #5070\n"
                   "G1 X[#5061 - 2] F1200\n"
                   "G38.3 X[#5061 - 6] F1200\n"        # away from the sphere: no contact, #5070 = 0
                   "G1 Y[#5070 * 100 + 3] Z[#<ztop> + 10]\n"
                   "M2\n")
    r = _run(client, text)
    assert [p["contact"] for p in r["probes"]] == [True, True, False]
    top, side = (np.asarray(p["tip_mm"][:3]) for p in r["probes"][:2])
    # the contacts lie on the artefact's surface (sphere + stylus radius) within the probe noise
    for p in (top, side):
        assert abs(np.linalg.norm(p - CENTRE) - R) < 0.003
    assert top[2] == pytest.approx(C[2] + R, abs=0.003) and side[0] == pytest.approx(C[0] - R, abs=0.003)
    # every contact went into the probe log (strut readings, pose, time)
    log = list(machine[0].calib_probe_log)[-2:]
    assert all(len(e["q_mm"]) == 6 and len(e["tip_pose"]) == 6 and e["t_s"] > 0 for e in log)
    # ... with the readings the drives latched at the edge (CiA 402 0x60BA over SDO by the hot loop)
    assert all(e["latched"] for e in log)
    # the last move used #5070 (= 0 after the G38.3) and #5063 of the first probe: Y 3, Z top + 10
    client.call("wait", timeout_s=30.0)
    tip = tip_poses(machine[0].cfg, np.asarray(client.call("status")["pose_cmd"])[None, :], 0.0)[0]
    assert tip[1] == pytest.approx(3.0, abs=0.01)
    assert tip[2] == pytest.approx(top[2] + 10.0, abs=0.01)
    assert tip[0] == pytest.approx(side[0] - 6.0, abs=0.01)   # where the G38.3 ended


def test_no_contact_for_g38_2_aborts_the_program_naming_the_line(machine, client):
    text = HEAD + (f"G1 X{C[0] + 40:.3f} Y{C[1]:.3f} Z{C[2]:.3f} F3000\n"
                   f"G38.2 X{C[0] + 36:.3f} F1200\n"        # line 5: moves away, never touches
                   "G1 X0\nM2\n")
    with pytest.raises(P.DaemonError, match=r"line 5: .*without the probe tripping"):
        _run(client, text, "miss.ngc")
    last = client.call("status").get("program") or {}
    assert "line 5" in str(last.get("aborted", "")), last


def test_mdi_probe(machine, client):
    _run(client, HEAD + f"G0 X{C[0]:.3f} Y{C[1]:.3f} Z{C[2] + 16:.3f}\nM2\n", "pre.ngc")
    client.call("wait", timeout_s=30.0)
    r = client.call("mdi", text=f"G38.2 Z{C[2]:.3f} F600", reply_timeout_s=120.0)
    assert r["probes"][0]["contact"]
    assert r["probes"][0]["tip_mm"][2] == pytest.approx(C[2] + R, abs=0.003)
