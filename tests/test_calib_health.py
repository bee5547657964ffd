"""Model health: payload from torques, drift patterns by cause, recordings, ``hexacnc record/health`` (issue 17)."""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import threading

import numpy as np
import pytest

from hexacnc.calib import recording
from hexacnc.calib.health import analyse
from hexacnc.calib.healthsim import Drift, simulate
from hexacnc.calib.payload import DriveTorqueModel, identify_payload, plan_rest_poses, simulate_torques
from hexacnc.calib.synth import sample_poses
from hexacnc.cli import main as cli
from hexacnc.config import load_config
from hexacnc.kinematics import Hexapod


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def fresh_seed() -> int:
    return int.from_bytes(os.urandom(4), "little")


def test_payload_mass_and_cog_from_rest_torques(cfg):
    """Rest poses planned for the mass (plan_rest_poses), each rest's torque averaged over 25 readings
    (the static friction does not average out); a tare set without the payload fixes the drives'
    offsets.  Offline sweep (1000 seeds): worst mass error 3.3 %, issue 17 asks 5 %."""
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    hx = Hexapod(cfg)
    model = DriveTorqueModel(rest_samples=25)
    m_true = rng.uniform(30.0, 60.0)
    c_true = np.array([rng.uniform(-60, 60), rng.uniform(-60, 60), rng.uniform(-220, -120)])
    P = plan_rest_poses(cfg, 60, seed=seed, candidates=800)
    off = rng.normal(0.0, model.offset_permille, 6)
    T = simulate_torques(hx, P, m_true, c_true, model, rng, off)
    P0 = sample_poses(cfg, rng, 60)
    T0 = simulate_torques(hx, P0, 0.0, None, model, rng, off)
    r = identify_payload(hx, P, T, model, tare=(P0, T0))
    msg = f"seed {seed}: true {m_true:.2f} kg at {c_true.round(1)}, got {r.mass_kg:.2f} +- {r.mass_std_kg:.2f}"
    assert abs(r.mass_kg - m_true) <= 0.05 * m_true, msg
    assert abs(r.mass_kg - m_true) <= 4.5 * r.mass_std_kg, msg
    assert np.all(np.abs(r.cog_platform_mm - c_true) <= 5 * r.cog_std_mm + 1.0), (msg, r.cog_platform_mm)


def test_payload_mass_from_torques_while_moving(cfg):
    """Torques sampled while moving (the drives' torque TPDO3): each strut's Coulomb and viscous friction
    fitted as nuisance parameters; the drives' small constant offsets are left in as a bias."""
    seed = fresh_seed()
    m_true = float(np.random.default_rng(seed).uniform(20.0, 150.0))
    rec = simulate(cfg, seed, Drift(payload_kg=m_true), n_moves=10)
    t, L = rec["t_s"], rec["struts_cmd_mm"]
    v = np.gradient(L, t, axis=0)
    a = np.gradient(v, t, axis=0)
    from hexacnc.calib.payload import identify_payload_in_motion
    res = identify_payload_in_motion(Hexapod(cfg), rec["pose_cmd"], rec["torque_permille"], v, a, DriveTorqueModel())
    assert abs(res.mass_kg - m_true) <= 0.05 * m_true, (seed, res.mass_kg, m_true)
    assert np.allclose(res.extra["coulomb_N"], 60.0, atol=6.0), (seed, res.extra["coulomb_N"])
    # health reports it beside the rest-pose result
    rep = analyse(cfg, rec, DriveTorqueModel(), None, 0.0)
    assert rep["payload"]["in_motion"]["available"]
    assert rep["payload"]["in_motion"]["mass_kg"] == pytest.approx(res.mass_kg)
    # too little motion: a clear refusal, not a number
    with pytest.raises(Exception, match="at least 60 strut samples"):
        identify_payload_in_motion(Hexapod(cfg), rec["pose_cmd"][:5], rec["torque_permille"][:5], v[:5], a[:5],
                                   DriveTorqueModel())


def test_planned_rest_poses_carry_more_mass_information(cfg):
    from hexacnc.calib.payload import _design
    rng = np.random.default_rng(fresh_seed())
    planned = plan_rest_poses(cfg, 30, seed=int(rng.integers(2 ** 31)), candidates=600)
    assert planned.shape == (30, 6) and not Hexapod(cfg).batch_violations(planned).any()

    def mass_var(P):   # variance of the mass (COG and drive offsets free, a 60-pose tare) per unit noise
        _, D = _design(Hexapod(cfg), P)
        A = np.zeros((10, 10))
        A[4:, 4:] = 60.0 * np.eye(6)
        for Dk in D:
            B = np.hstack([Dk, np.eye(6)])
            A += B.T @ B
        return np.linalg.inv(A)[0, 0]
    assert mass_var(planned) < 0.9 * mass_var(sample_poses(cfg, rng, 30))


@pytest.fixture(scope="module")
def reference(cfg):
    return simulate(cfg, 11, Drift(), n_moves=60, rate_hz=50.0)


@pytest.mark.parametrize("case", ["healthy", "payload", "thermal", "friction", "stiffness"])
def test_health_separates_drift_by_cause(cfg, reference, case):
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    k = int(rng.integers(6))
    drift = {"healthy": Drift(),
             "payload": Drift(payload_kg=float(rng.uniform(30, 60)), payload_cog_mm=(10.0, -20.0, -160.0)),
             "thermal": Drift(temperature_rise_K=float(rng.uniform(3, 8)), thermal_compensated=False),
             "friction": Drift(friction_N=tuple(150.0 if i == k else 60.0 for i in range(6))),
             "stiffness": Drift(extra_compliance_mm_per_kN=tuple(1.0 if i == k else 0.0 for i in range(6)))}[case]
    # the payload needs many rests: the static friction held at each rest averages out only across rests
    n_moves = 60 if case == "payload" else 24
    rep = analyse(cfg, simulate(cfg, seed % 100000, drift, n_moves=n_moves, rate_hz=50.0), reference=reference)
    msg = f"{case} seed {seed}: {rep['status']} {rep['warnings']}"
    want = {"healthy": [], "payload": ["payload_changed"], "thermal": ["thermal_not_compensated"],
            "friction": ["friction_changed"], "stiffness": ["stiffness_changed"]}[case]
    assert rep["causes"] == want, msg
    assert rep["status"] == ("ok" if case == "healthy" else "warning"), msg
    if case in ("friction", "stiffness"):
        assert [f["strut"] for f in rep["findings"]] == [k + 1], msg
    if case == "payload":
        p = rep["payload"]
        assert abs(p["mass_kg"] - drift.payload_kg) <= 0.05 * drift.payload_kg, msg
        upd = p["proposed_update"]
        assert upd["carrier"]["mass_kg"] == pytest.approx(cfg.mass_kg + p["mass_kg"], abs=1e-3)
        assert "[carrier]" in upd["toml"] and upd["sag_change_at_home"]["position_um"] > 0


def test_in_motion_payload_differentiates_over_the_loop_time_not_the_stream_delivery_time(cfg):
    """Under load the status stream arrives with tens of ms of jitter: the recorder's clock ``t_s`` is not
    the samples' time, and rates from it spoil the payload in motion (84 kg against a true 81.8 kg on the
    loaded VM).  The recording's ``t_loop_s`` (the daemon loop's time) is the time base health uses."""
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    m_true = float(rng.uniform(40.0, 150.0))
    rec = simulate(cfg, seed, Drift(payload_kg=m_true), n_moves=10, rate_hz=25.0)
    clean = analyse(cfg, rec, DriveTorqueModel(), None, 0.0)["payload"]["in_motion"]
    t = rec["t_s"]
    late = np.maximum.accumulate(t + rng.uniform(0.0, 0.06, len(t)))      # delivery delays of 0-60 ms
    rec.data["t_s"] = late + 1e-6 * np.arange(len(t))
    jit = analyse(cfg, rec, DriveTorqueModel(), None, 0.0)["payload"]["in_motion"]
    msg = (seed, m_true, clean["mass_kg"], jit["mass_kg"])
    assert jit["mass_kg"] == pytest.approx(clean["mass_kg"], rel=1e-9), msg
    assert abs(jit["mass_kg"] - m_true) <= 0.05 * m_true, msg
    v, _ = recording.strut_rates(rec)
    np.testing.assert_allclose(v, np.gradient(rec["struts_cmd_mm"], t, axis=0), atol=1e-9)
    # without the loop time the rates come from the jittered clock: the fit is visibly worse
    rec.data["t_loop_s"] = np.full(len(t), np.nan)
    bad = analyse(cfg, rec, DriveTorqueModel(), None, 0.0)["payload"]["in_motion"]
    assert bad["residual_rms_N"] > 1.5 * clean["residual_rms_N"], (msg, bad["residual_rms_N"], clean["residual_rms_N"])


def test_a_rest_with_the_drives_disabled_is_no_rest_pose_of_the_payload(cfg):
    """A fault (or a disable) leaves the commanded struts still, but its drives hold no load (torque 0):
    such a stretch is not a rest pose (drives_enabled 0 in the recording), nor is the part of it the status
    still reported enabled (it reports the drop late: here 0.4 s after the torques fell)."""
    from hexacnc.calib.health import rest_windows
    seed = fresh_seed()
    m_true = float(np.random.default_rng(seed).uniform(40.0, 150.0))
    rec = simulate(cfg, seed, Drift(payload_kg=m_true), n_moves=8)
    w = rest_windows(rec)
    k = w[len(w) // 2]
    t = rec["t_s"]
    off = (t >= t[k[0]] - 0.1) & (t <= t[k[-1]])          # the drives faulted during that rest
    rec.data["torque_permille"][off] = 0.0
    rec.data["drives_enabled"][off & (t >= t[k[0]] + 0.3)] = 0.0
    rep = analyse(cfg, rec, DriveTorqueModel(), None, 0.0)
    p = rep["payload"]
    msg = (seed, m_true, p["mass_kg"], p["mass_std_kg"])
    assert p["rest_poses"] == len(w) - 1, msg
    # Seven short rests of a random program pin the mass to about 1 kg (the 5 % of issue 17 is met by a
    # planned rest set, test above), and the reported std is honest: offline sweep of 7,500 seeds, |error|/std
    # median 0.66, 99.9 % 3.4, worst 4.4; std at most 2.8 % of the mass.  Had the faulted rest been used (its
    # torques 0) the mass would be 18-36 % low with a std of 7-12 kg.
    assert p["mass_std_kg"] <= 0.04 * m_true, msg
    assert abs(p["mass_kg"] - m_true) <= 6.0 * p["mass_std_kg"], msg


def test_recorder_keeps_the_loop_time_and_rates_skip_a_snapshot_read_twice():
    from hexacnc.calib.recorder import Recorder, parse_trigger
    r = Recorder(parse_trigger("none"), 10)
    loop_s = [100.0, 100.004, 100.004, 100.012, 100.016]     # the third reading is the second snapshot again
    for k, tl in enumerate(loop_s):
        L = [1000.0 + 10.0 * (tl - 100.0)] * 6
        r.add({"state": "running", "struts_cmd_mm": L, "struts_act_mm": L, "loop_time_s": tl}, 5.0 + 0.03 * k)
    rec = r.recording({})
    np.testing.assert_allclose(rec["t_loop_s"], np.array(loop_s) - 100.0, atol=1e-12)
    v, a = recording.strut_rates(rec)
    np.testing.assert_allclose(v, 10.0, rtol=1e-6)                  # 10 mm/s, not skewed by the recorder's clock
    np.testing.assert_allclose(a, 0.0, atol=1e-6)
    rec.data["t_loop_s"][:] = np.nan                                 # no loop time: the recorder's clock
    np.testing.assert_allclose(recording.sample_times(rec), rec["t_s"])


def test_recording_files_open_in_numpy_and_roundtrip(cfg, tmp_path):
    rec = simulate(cfg, 3, Drift(), n_moves=3)
    for ext in ("npz", "csv"):
        p = tmp_path / f"r.{ext}"
        recording.save(p, rec)
        back = recording.load(p)
        assert back.n == rec.n
        for nm in ("struts_cmd_mm", "torque_permille", "t_s"):
            np.testing.assert_allclose(back[nm], rec[nm], rtol=1e-8, atol=1e-9)
    z = np.load(tmp_path / "r.npz")
    assert z["following_error_mm"].shape == (rec.n, 6)
    arr = np.genfromtxt(tmp_path / "r.csv", delimiter=",", names=True)
    assert "torque_permille_3" in arr.dtype.names and len(arr) == rec.n
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,x\n0,1\n1,zz\n")
    from hexacnc.errors import DataError
    with pytest.raises(DataError, match="line 3, column 2"):
        recording.load(bad)


def test_health_cli_reads_a_recording(cfg, reference, tmp_path):
    rec = simulate(cfg, 5, Drift(payload_kg=40.0), n_moves=24, rate_hz=50.0)
    recording.save(tmp_path / "run.npz", rec)
    recording.save(tmp_path / "ref.npz", reference)
    out = tmp_path / "h.json"
    assert cli(["health", "--recording", str(tmp_path / "run.npz"), "--reference", str(tmp_path / "ref.npz"),
                "--json", str(out)]) == 0
    j = json.loads(out.read_text())
    assert j["status"] == "warning" and j["causes"] == ["payload_changed"]
    assert cli(["health", "--recording", str(tmp_path / "missing.npz")]) == 2


@pytest.mark.e2e
def test_record_from_the_daemon_socket(cfg, tmp_path):
    """``hexacnc record`` against the socket server (fake daemon): a trigger, decimated samples, a file."""
    import sys
    sys.path.insert(0, os.path.dirname(__file__))
    from test_protocol_fake import FakeDaemon

    from hexacnc.daemon.server import SocketServer
    d = tempfile.mkdtemp(prefix="hxrec", dir="/tmp")
    daemon = FakeDaemon(block_s=0.01)
    srv = SocketServer(daemon, cfg, os.path.join(d, "s.sock")).start()
    try:
        out = tmp_path / "rec.csv"
        t = threading.Timer(0.3, lambda: daemon.load_program("\n".join(f"G1 X{i}" for i in range(200)), "p"))
        t.start()
        rc = cli(["record", "--socket", os.path.join(d, "s.sock"), "--out", str(out), "--rate", "50",
                  "--count", "10", "--trigger", "state=running", "--timeout", "20"])
        t.join()
        assert rc == 0
        r = recording.load(out)
        assert r.n == 10 and r.meta["trigger"]["kind"] == "state"
        assert np.all(np.diff(r["t_s"]) > 0)
        assert np.all(r["struts_cmd_mm"] >= 1000.0)
        assert np.all(np.isnan(r["torque_permille"]))   # the daemon's status carries no torques (yet)
        js = tmp_path / "h.json"
        assert cli(["health", "--live", "--socket", os.path.join(d, "s.sock"), "--duration", "0.5", "--rate", "20",
                    "--json", str(js)]) == 0
        assert json.loads(js.read_text())["status"] == "insufficient_data"   # no torques, temperatures, motion
    finally:
        srv.close()
        daemon.close()
        shutil.rmtree(d, ignore_errors=True)
