"""[calibration] in the config and in the cycle: loader errors, exact IK/FK with a calibrated
strut map, generated path = general path, limits on the final command and the physical length."""
from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from hexacnc import transform as T
from hexacnc.config import default_config_path, parse_config
from hexacnc.cyclegen import generate_source
from hexacnc.errors import ConfigError
from hexacnc.strutmap import strut_map_from_config

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)


def default_doc() -> dict:
    return tomllib.loads(default_config_path().read_text())


def calibrated_doc(seed: int = 3, degree: int = 3, tol_mm: float | None = 1e-11) -> dict:
    """The default machine with a random, plausible calibrated strut map (gain 0.95..1.05,
    Legendre coefficients up to 2 mm / k^2 for P_k)."""
    rng = np.random.default_rng(seed)
    d = default_doc()
    d["calibration"] = {
        "strut_scale": [float(v) for v in rng.uniform(0.95, 1.05, 6)],
        "strut_nonlinearity_mm": [[float(v) / (k + 1) ** 2 for k, v in enumerate(rng.uniform(-2, 2, degree))]
                                  for _ in range(6)],
        "strut_nonlinearity_center_mm": [float(v) for v in rng.uniform(250, 350, 6)],
        "strut_nonlinearity_half_range_mm": [float(v) for v in rng.uniform(300, 340, 6)],
        "source": "test", "date": "2026-11-21",
    }
    if tol_mm is not None:
        d.setdefault("kinematics", {})["fk_tolerance_mm"] = tol_mm
    return d


def home_rad(cfg) -> np.ndarray:
    h = np.array(cfg.home_pose, dtype=float)
    h[3:] = np.radians(h[3:])
    return h


def test_absent_section_is_identity_and_generates_the_same_code():
    d = default_doc()
    cfg = parse_config(d, "a")
    assert cfg.calibration.identity
    ct = T.CycleTransform(cfg)
    assert not ct.calibrated and ct.phys_mm is ct.cmd_mm
    # an explicit identity section changes nothing, not even the generated code
    d2 = default_doc()
    d2["calibration"] = {"strut_scale": 1.0, "source": "identity"}
    ct2 = T.CycleTransform(parse_config(d2, "a"))
    assert generate_source(ct2) == generate_source(ct)
    assert "phys_mm" not in generate_source(ct)


@pytest.mark.parametrize("mutate, words", [
    (lambda c: c.update(bogus=1), ["[calibration]", "bogus", "unknown"]),
    (lambda c: c.update(strut_scale=[1.0] * 5), ["[calibration] strut_scale", "6 values"]),
    (lambda c: c.update(strut_scale=[1.0] * 5 + [3.0]), ["strut_scale", "element 6", "3.0"]),
    (lambda c: c.update(strut_scale=[1.0] * 5 + [math.nan]), ["strut_scale", "nan"]),
    (lambda c: c.update(strut_nonlinearity_mm=[[0.1, 0.2]] * 5), ["strut_nonlinearity_mm", "6 rows"]),
    (lambda c: c.update(strut_nonlinearity_mm=[[0.1] * 8] * 6), ["strut_nonlinearity_mm", "1 to 7"]),
    (lambda c: c.pop("strut_nonlinearity_center_mm"), ["strut_nonlinearity_center_mm", "missing"]),
    (lambda c: c.update(strut_nonlinearity_half_range_mm=[0.0] * 6), ["strut_nonlinearity_half_range_mm", "0.0"]),
    (lambda c: c.update(strut_nonlinearity_mm=[[0.0, 400.0, 0.0]] * 6), ["strut_nonlinearity_mm", "slope"]),
    (lambda c: c.update(date=5), ["[calibration] date", "5"]),
    (lambda c: c.update(source=["x"]), ["[calibration] source", "string"]),
])
def test_calibration_errors_name_file_section_and_key(mutate, words):
    d = calibrated_doc()
    mutate(d["calibration"])
    with pytest.raises(ConfigError) as ei:
        parse_config(d, "machine.toml")
    msg = str(ei.value)
    assert "machine.toml" in msg
    for wd in words:
        assert wd in msg, (wd, msg)


def test_strut_map_batch_inverse_is_exact():
    cfg = parse_config(calibrated_doc(seed=5, degree=5), "m")
    sm = strut_map_from_config(cfg)
    L = np.random.default_rng(1).uniform(cfg.min_length_mm[0], cfg.max_length_mm[0], (2000, 6))
    D = sm.drive_from_strut(L)
    assert np.max(np.abs(sm.strut_from_drive(D) - L)) < 1e-9
    # the map is what the config says: L = o + s q + sum c_k P_k(t)
    c = cfg.calibration
    q = D - cfg.strut_offset_mm
    t = (q - c.strut_nonlinearity_center_mm) / c.strut_nonlinearity_half_range_mm
    want = cfg.strut_offset_mm + c.strut_scale * q
    for i in range(6):
        want[:, i] += np.polynomial.legendre.legval(t[:, i], np.r_[0.0, c.strut_nonlinearity_mm[i]])
    assert np.max(np.abs(want - L)) < 1e-9


@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("seed", [3, 11])
def test_calibrated_ik_fk_round_trip(fast, seed):
    cfg = parse_config(calibrated_doc(seed=seed), "m")
    ct = T.CycleTransform(cfg, fast=fast)
    assert ct.calibrated
    sm = strut_map_from_config(cfg)
    home = home_rad(cfg)
    rng = np.random.default_rng(seed)
    worst_mm = worst_deg = 0.0
    for _ in range(400):
        X = home + rng.uniform(-1, 1, 6) * np.r_[80, 80, 80, math.radians(8), math.radians(8), math.radians(8)]
        ct._have_prev = 0
        assert ct.command(*X) == T.OK
        phys = np.array(ct.phys_mm)
        # the physical length is geometric - sag - thermal; the command maps to it exactly
        assert np.allclose(phys, np.array(ct.length_mm) - np.array(ct.sag_mm) - np.array(ct.thermal_mm), atol=1e-12)
        assert np.max(np.abs(sm.strut_from_drive(np.array(ct.cmd_mm)) - phys)) < 1e-9
        assert np.max(np.abs(np.array(ct.cmd_mm) - phys)) > 1e-3          # calibration does act
        ct.reset_pose(home)
        assert ct.feedback(list(ct.cmd_mm)) == T.OK
        e = np.array(ct.pose_act) - X
        worst_mm = max(worst_mm, float(np.max(np.abs(e[:3]))))
        worst_deg = max(worst_deg, float(np.degrees(np.max(np.abs(e[3:])))))
    assert worst_mm < 1e-9 and worst_deg < 1e-9


def test_generated_path_equals_general_path_while_tracking():
    cfg = parse_config(calibrated_doc(seed=7, tol_mm=None), "m")
    fast = T.CycleTransform(cfg)
    slow = T.CycleTransform(cfg, fast=False)
    home = home_rad(cfg)
    for k in range(2000):          # a slow circle with a tilt: the warm-started Newton path
        s = k * 5e-4
        X = home + np.r_[40 * math.sin(s), 40 * (1 - math.cos(s)), 5 * math.sin(3 * s),
                         math.radians(2) * math.sin(s), 0.0, 0.0]
        assert fast.command(*X) == T.OK and slow.command(*X) == T.OK
        assert max(abs(a - b) for a, b in zip(fast.cmd_mm, slow.cmd_mm)) < 1e-9
        D = list(fast.cmd_mm)
        assert fast.feedback(D) == T.OK and slow.feedback(D) == T.OK
        assert max(abs(a - b) for a, b in zip(fast.pose_act, slow.pose_act)) < 1e-9
        assert fast.fk_iterations <= 2


@pytest.mark.parametrize("fast", [True, False])
def test_limits_apply_to_physical_length_and_drive_command(fast):
    d = calibrated_doc(seed=3, tol_mm=None)
    d["calibration"]["strut_nonlinearity_mm"] = [[0.0, 0.0, 0.0]] * 6
    d["calibration"]["strut_scale"] = [0.95] + [1.0] * 5    # strut 1 reads 5 % short: its drive travels further
    cfg = parse_config(d, "m")
    ct = T.CycleTransform(cfg, fast=fast)
    hx = ct.hx
    home = home_rad(cfg)
    # find a pose where strut 1's physical length is inside the stroke but its command is not
    lmax = float(cfg.max_length_mm[0])
    found = False
    for dz in np.linspace(0, 600, 1201):
        for sgn in (1, -1):
            X = home + np.r_[0, 0, sgn * dz, 0, 0, 0]
            Xd = X.copy(); Xd[3:] = np.degrees(Xd[3:])
            L = hx.lengths(Xd)
            if np.all(L < np.asarray(cfg.max_length_mm) - 1) and np.all(L > np.asarray(cfg.min_length_mm) + 1):
                ct._have_prev = 0
                code = ct.command(*X)
                if code == T.LIMIT_LENGTH:
                    assert ct.fail_index == 6            # strut 1's drive command
                    assert ct.fail_value > lmax
                    assert "drive command" in ct.describe(code)
                    found = True
                    break
                assert code == T.OK
                assert all(cfg.min_length_mm[i] <= ct.cmd_mm[i] <= cfg.max_length_mm[i] for i in range(6))
        if found:
            break
    assert found


def test_kin_cli_applies_the_calibration(tmp_path):
    import subprocess
    import sys
    from pathlib import Path
    repo = Path(__file__).resolve().parents[1]
    d = calibrated_doc(seed=9, tol_mm=None)
    text = default_config_path().read_text() + "\n[calibration]\n" + "\n".join(
        f"{k} = {v!r}" if not isinstance(v, str) else f'{k} = "{v}"' for k, v in d["calibration"].items()) + "\n"
    cal = tmp_path / "cal.toml"
    cal.write_text(text)
    cfg = parse_config(tomllib.loads(text), str(cal))
    poses = tmp_path / "p.csv"
    rng = np.random.default_rng(2)
    P = np.array(cfg.home_pose) + rng.uniform(-1, 1, (20, 6)) * np.r_[50, 50, 50, 5, 5, 5]
    poses.write_text("x,y,z,a,b,c\n" + "\n".join(",".join(f"{v:.9f}" for v in r) for r in P) + "\n")
    inv, fwd = tmp_path / "inv.csv", tmp_path / "fwd.csv"
    run = lambda *a: subprocess.run([sys.executable, "-m", "hexacnc", "kin", *a], capture_output=True, text=True,
                                    cwd=repo, timeout=120)
    p = run("inverse", "--config", str(cal), "--poses", str(poses), "--out", str(inv))
    assert p.returncode == 0, p.stderr
    out = np.loadtxt(inv, delimiter=",", skiprows=1)
    L, q = out[:, :6], out[:, 6:]
    sm = strut_map_from_config(cfg)
    assert np.max(np.abs(sm.strut_from_drive(q + cfg.strut_offset_mm) - L)) < 1e-6
    assert np.max(np.abs(q - (L - cfg.strut_offset_mm))) > 1e-2        # not the uncalibrated reading
    qf = tmp_path / "q.csv"
    qf.write_text("q1,q2,q3,q4,q5,q6\n" + "\n".join(",".join(f"{v:.9f}" for v in r) for r in q) + "\n")
    p = run("forward", "--config", str(cal), "--readings", str(qf), "--out", str(fwd))
    assert p.returncode == 0, p.stderr
    X = np.loadtxt(fwd, delimiter=",", skiprows=1)[:, :6]
    assert np.max(np.abs(X - P)) < 1e-6


def test_hot_loop_applies_the_calibration_both_ways():
    """The daemon's hot loop (in-process, ideal simulated drives) with a calibrated machine: the drive
    targets are the calibrated commands, and the actual pose from the drive readings is the target."""
    import dataclasses

    from hexacnc.daemon import shm as S
    from hexacnc.daemon.feed import point_to_point
    from hexacnc.daemon.loop import HotLoop
    from hexacnc.daemon.simio import SimIO
    from hexacnc.kinematics import Hexapod
    period = 0.0005
    cfg = parse_config(calibrated_doc(seed=4, tol_mm=None), "calibrated")
    cfg = cfg.replace(cycle=dataclasses.replace(cfg.cycle, max_overruns_in_row=100000))
    hx = Hexapod(cfg)
    sm = strut_map_from_config(cfg)
    # drives at the readings of the home pose under the calibrated map (with the carrier's sag)
    ct0 = T.CycleTransform(cfg, period_s=period)
    assert ct0.command(*home_rad(cfg)) == T.OK
    start = np.array(ct0.cmd_mm) - cfg.strut_offset_mm
    assert np.max(np.abs(sm.strut_from_drive(np.array(ct0.cmd_mm)) - np.array(ct0.phys_mm))) < 1e-9
    sh = S.Shared(create=True)
    try:
        sent = []

        class IO(SimIO):
            def send(self):
                sent.append(list(self.target))
                return super().send()

        io = IO(cfg, period, tau_s=0.0005, start_pos=start)
        lp = HotLoop(cfg, sh, io, period_s=period)
        lp.run(max_cycles=40)
        assert sh.h[S.H_STATE] == S.ST_IDLE and sh.h[S.H_READY] == 1
        h, s = sh.read_status()
        act = np.array(s[S.S_POSE_ACT:S.S_POSE_ACT + 6])
        home = home_rad(cfg)
        assert np.max(np.abs(act[:3] - home[:3])) < 1e-4          # seeded at home through the map
        target = [20.0, -10.0, float(cfg.home_pose[2]) + 15.0, 2.0, -1.0, 3.0]
        rows = point_to_point(cfg, hx, act, target, 300.0, period)
        assert sh.push_rows(rows) == len(rows)
        lp.run(max_cycles=sh.h[S.H_CYCLES] + len(rows) + 100)
        assert sh.h[S.H_FAULT] == 0 and sh.h[S.H_STATE] == S.ST_IDLE
        ct = T.CycleTransform(cfg, period_s=period)
        assert ct.command(*rows[-1, :6]) == T.OK
        k = cfg.bus.increments_per_mm
        want = [round((ct.cmd_mm[i] - cfg.strut_offset_mm[i]) * k) for i in range(6)]
        uncal = [round((ct.phys_mm[i] - cfg.strut_offset_mm[i]) * k) for i in range(6)]
        assert all(abs(a - b) <= 1 for a, b in zip(sent[-1], want))
        assert max(abs(a - b) for a, b in zip(sent[-1], uncal)) > 10        # the map moved the targets
        h, s = sh.read_status()
        assert np.allclose(s[S.S_POSE_ACT:S.S_POSE_ACT + 3], target[:3], atol=0.01)
    finally:
        sh.close()


@pytest.mark.parametrize("fast", [True, False])
def test_a_map_that_cannot_invert_is_a_status_not_a_command(fast):
    cfg = parse_config(calibrated_doc(seed=3, tol_mm=None), "m")
    ct = T.CycleTransform(cfg, fast=fast)
    X = home_rad(cfg)
    assert ct.command(*X) == T.OK
    good = list(ct.cmd_mm)
    # a corrupted warm-start state is recovered: the same exact command
    ct._cal_state[:] = [float("nan")] * len(ct._cal_state)
    ct._have_prev = 0
    assert ct.command(*X) == T.OK and ct.cmd_mm == pytest.approx(good, abs=1e-9)
    # constants corrupted behind the loader's back: no inverse exists; a status, nothing sent
    sm = ct.strut_map
    sm._Al = [[float("nan")] + a[1:] for a in sm._Al]
    sm._Bl = [[0.0] * len(b) for b in sm._Bl]
    ct._cal_state[:] = [float("nan")] * len(ct._cal_state)
    ct._have_prev = 0
    code = ct.command(*X)
    assert code == T.LIMIT_CALIBRATION
    assert ct.cmd_mm == pytest.approx(good, abs=1e-9)
    assert "did not invert" in ct.describe(code)


def test_provenance_accepts_toml_dates():
    text = default_config_path().read_text() + '\n[calibration]\nsource = "lab run 7"\ndate = 2026-11-21T19:27:19Z\n'
    cfg = parse_config(tomllib.loads(text), "m")
    assert cfg.calibration.source == "lab run 7" and cfg.calibration.date.startswith("2026-11-21T19:27:19")
    assert cfg.calibration.identity
