"""calib run pieces against fake daemons: the probing cycle, far readings, the platform path, resumed verification."""
import re

import numpy as np
import pytest

from hexacnc.calib.probing import probe_sphere
from hexacnc.daemon.protocol import DaemonError

pytestmark = [pytest.mark.unit, pytest.mark.serial]   # starts processes or keeps time: runs alone

R = 13.5


class FakeDaemon:
    """Moves the tip to the last G53 G0 point of a program; ``probe`` runs a straight line to the target
    and stops at the first point within ``R`` of the true centre (G38.2: no contact or already in
    contact is an error, as the daemon's op)."""

    def __init__(self, true_centre):
        self.c = np.asarray(true_centre, dtype=float)
        self.tip = self.c + [0.0, 0.0, 60.0]
        self.touches = 0
        self.path = []

    def call(self, op, **kw):
        if op == "program":
            for m in re.finditer(r"G53 G0 X(\S+) Y(\S+) Z(\S+)", kw["text"]):
                p = np.array([float(v) for v in m.groups()])
                self._check_path(self.tip, p)
                self.tip = p
            return {}
        if op == "wait":
            return {"state": "idle"}
        assert op == "probe"
        self.touches += 1
        a, b = self.tip, np.asarray(kw["tip_mm"][:3], dtype=float)
        if np.linalg.norm(a - self.c) <= R:
            raise DaemonError({"error": {"code": 3, "message": "G38.2: the probe is already tripped at the start"}})
        d = b - a
        # first t in [0, 1] with |a + t d - c| = R
        A, B, C = d @ d, 2 * d @ (a - self.c), (a - self.c) @ (a - self.c) - R * R
        disc = B * B - 4 * A * C
        t = (-B - np.sqrt(disc)) / (2 * A) if disc >= 0 else 2.0
        if not 0.0 <= t <= 1.0:
            raise DaemonError({"error": {"code": 3, "message": "G38.2: move finished without the probe tripping"}})
        p = a + t * d
        self.tip = p
        return {"contact": True, "tip_pose": list(p) + [0.0, 0.0, 0.0], "q_mm": [0.0] * 6, "t_s": 0.0,
                "overtravel_mm": 0.0}

    def _check_path(self, a, b):
        for t in np.linspace(0.0, 1.0, 50):          # a rapid never passes through the sphere
            assert np.linalg.norm(a + t * (b - a) - self.c) > R - 1e-9, "rapid through the artefact"


@pytest.mark.parametrize("error_mm", [[0.0, 0.0, 0.0], [1.9, -1.2, 0.5], [-3.5, 2.0, -2.5], [2.0, 3.8, 3.0]])
def test_the_cycle_finds_a_sphere_millimetres_off_where_the_machine_expects_it(error_mm):
    nominal = np.array([100.0, 0.0, -1150.0])
    fake = FakeDaemon(nominal + error_mm)
    r = probe_sphere(fake, nominal, [0.0, 0.0, 0.0], R)
    assert fake.touches == 5
    assert np.linalg.norm(r["centre_mm"] - fake.c) < 1e-6
    assert r["residual_um"] < 1e-3


def test_a_sphere_beyond_the_search_range_is_an_error_not_a_wrong_centre():
    nominal = np.array([0.0, 0.0, -1150.0])
    fake = FakeDaemon(nominal + [0.0, 0.0, -6.0])        # 6 mm lower: beyond overtravel + search (5 mm)
    with pytest.raises(DaemonError, match="without the probe tripping"):
        probe_sphere(fake, nominal, [0.0, 0.0, 0.0], R)


# -- far readings: the machine really there (confirmed by the next reading) or the instrument's gross error --
class FakeTracker:
    def __init__(self, cfg, offsets_mm):
        from hexacnc.kinematics import Hexapod
        self.cfg, self.hx = cfg, Hexapod(cfg)
        self.offsets = list(offsets_mm)          #: z offset of each successive reading
        self.n = 0

    def call(self, op, **kw):
        if op == "program":
            return {}
        if op == "wait":
            return {"state": "idle"}
        if op == "status":
            return {"struts_act_mm": list(self.hx.lengths(self.X))}
        assert op == "measure"
        dz = self.offsets[min(self.n, len(self.offsets) - 1)]
        self.n += 1
        q = (self.hx.lengths(self.X) - np.asarray(self.cfg.strut_offset_mm)).tolist()
        vals = dict(zip("xyzabc", self.X))
        vals["z"] += dz
        import time
        return {"values": vals, "q_mm": q, "target": "platform", "t_s": time.time() + 1.0, "pair_gap_s": 0.0}


@pytest.mark.parametrize("offsets,kept,flag", [
    ([3.0, 3.01], True, "confirmed"),             # an uncalibrated machine 3 mm off: kept
    ([7.0, 0.001], True, "remeasured"),           # one gross reading, then a good one
    ([7.0, 3.0, 5.0], False, "excluded"),         # far readings that disagree: the instrument
    ([12.0, 12.0, 12.0], False, "excluded"),      # beyond gross_mm: a wrong configuration, not calibration
])
def test_a_far_reading_is_kept_only_when_the_next_reading_confirms_it(offsets, kept, flag):
    from hexacnc.calib.cyclerun import RunOptions, measure_pose
    from hexacnc.config import load_config
    from hexacnc.kinematics import Hexapod
    cfg = load_config(None)
    fake = FakeTracker(cfg, offsets)
    fake.X = np.asarray(cfg.home_pose, dtype=float)
    r = measure_pose(fake, cfg, Hexapod(cfg), fake.X, 0, RunOptions(settle_s=0.0, progress=False))
    assert bool(r.values) == kept
    assert r.flag.startswith(flag), r.flag


def test_the_rapid_between_poses_keeps_the_platform_on_its_straight_line():
    """A straight tool-tip move with the orientation interpolated swings the platform out (it left the
    [workspace] box near its edge): calib run cuts the rapid into short platform steps."""
    import re as _re

    from hexacnc.calib.cyclerun import RunOptions, approach_pose, move_program, platform_of_tip, tip_of
    from hexacnc.config import load_config
    from hexacnc.kinematics import Hexapod
    cfg = load_config(None)
    hx = Hexapod(cfg)
    S = np.array([100.0, -80.0, -700.0, 12.0, -10.0, 8.0])
    X = np.array([-100.0, 90.0, -760.0, -12.0, 11.0, -9.0])
    pre = approach_pose(hx, X, 0.3)

    def swing_mm(text):
        tips = [np.array([float(v) for v in m.groups()]) for m in
                _re.finditer(r"G0 X(\S+) Y(\S+) Z(\S+) A(\S+) B(\S+) C(\S+)", text)]
        pts, prev = [], tip_of(cfg, S)
        for T in tips:                       # the planner: tip straight, orientation interpolated
            for t in np.linspace(0.0, 1.0, 21):
                pts.append(platform_of_tip(cfg, prev + t * (T - prev))[:3])
            prev = T
        P, d = np.array(pts), pre[:3] - S[:3]
        rel = P - S[:3]
        off = rel - np.outer(rel @ d / (d @ d), d)
        return float(np.max(np.linalg.norm(off, axis=1)))
    one = swing_mm(move_program(cfg, hx, X, RunOptions()))           # no start known: one rapid
    steps = swing_mm(move_program(cfg, hx, X, RunOptions(), S))
    assert one > 3.0 and steps < 0.1, (one, steps)


def test_an_interrupted_verification_resumes_after_its_last_row(tmp_path):
    from hexacnc.calib.cyclerun import RunOptions
    from hexacnc.calib.synth import sample_poses
    from hexacnc.calib.verify import verify_poses
    from hexacnc.config import load_config
    cfg = load_config(None)
    poses = sample_poses(cfg, np.random.default_rng(4), 5)
    rows = tmp_path / "after.json.rows.jsonl"

    class Lost(FakeTracker):
        def call(self, op, **kw):
            if op == "program":
                self.X = self.poses[self.k]
                self.k += 1
                if self.k > self.fail_after:
                    raise ConnectionError("the daemon closed the connection")
            return super().call(op, **kw)
    first = Lost(cfg, [0.0])
    first.poses, first.k, first.fail_after, first.X = poses, 0, 3, poses[0]
    opts = RunOptions(settle_s=0.0, progress=False)
    with pytest.raises(ConnectionError):
        verify_poses(first, cfg, poses, opts, rows)
    assert len(rows.read_text().splitlines()) == 1 + 3
    again = Lost(cfg, [0.0])
    again.poses, again.k, again.fail_after, again.X = poses[3:], 0, 99, poses[0]
    rep = verify_poses(again, cfg, poses, opts, rows)
    assert again.k == 2 and rep["measured"] == 5 and [r["pose"] for r in rep["rows"]] == [1, 2, 3, 4, 5]
    # other poses: not a resumption, measured from the start
    other = Lost(cfg, [0.0])
    other.poses, other.k, other.fail_after, other.X = poses[:4], 0, 99, poses[0]
    verify_poses(other, cfg, poses[:4], opts, rows)
    assert other.k == 4


def test_the_last_direction_survives_a_missed_look_across_a_reversal():
    """The simulated backlash follows each strut's last direction of motion; the supervisor looks every
    10 ms but a loaded VM stalls it for longer: the rapid down to the approach pose and the 0.3 mm feed
    back up fall between two looks.  Commanded travel (every cycle) tells the reversal."""
    from hexacnc.daemon.calibops import last_direction
    d = np.ones(3)
    db = 0.0005
    # strut 0: seen at 700.5 moving down (-50 mm/s); then down to 700.0, up to 700.3: travel 0.5 + 0.3
    # strut 1: monotonic down by 0.2 (no reversal): -1;  strut 2: 0.2 um of jitter: unchanged
    c0, T0, v0 = np.array([700.5, 650.0, 600.0]), np.array([10.0, 10.0, 10.0]), np.array([-50.0, -5.0, 0.0])
    c1, T1 = np.array([700.3, 649.8, 600.0002]), np.array([10.8, 10.2, 10.0002])
    out, decided = last_direction(d, c0, T0, v0, c1, T1, db)
    assert out.tolist() == [1.0, -1.0, 1.0] and decided.tolist() == [True, True, False]
    # the net move alone (what a sampler sees) would say 'retracting' for strut 0
    assert np.sign(c1[0] - c0[0]) == -1
    # a reversal whose return leg is within the dead band keeps the first leg's direction
    out, _ = last_direction(np.ones(1), [700.0], [0.0], [-10.0], [699.8002], [0.2004], db)
    assert out.tolist() == [-1.0]


@pytest.mark.parametrize("code,measured", [("busy", True), ("limit", False)])
def test_a_move_refused_while_a_stop_runs_is_sent_again_a_limit_is_not(code, measured):
    from hexacnc.calib.cyclerun import RunOptions, measure_pose
    from hexacnc.config import load_config
    from hexacnc.errors import DataError
    from hexacnc.kinematics import Hexapod
    cfg = load_config(None)

    class Refusing(FakeTracker):
        refused = 0
        state = "stopping"

        def call(self, op, **kw):
            if op == "program" and not self.refused:
                self.refused = 1
                raise DaemonError({"error": {"code": code, "message": "a stop is in progress; wait for idle"}})
            if op == "status":
                return dict(super().call(op), state=self.state)
            if op == "wait":
                self.state = "idle"
            return super().call(op, **kw)
    fake = Refusing(cfg, [0.0])
    fake.X = np.asarray(cfg.home_pose, dtype=float)
    opts = RunOptions(settle_s=0.0, progress=False, reset_faults=3)
    if measured:
        assert measure_pose(fake, cfg, Hexapod(cfg), fake.X, 0, opts).values
        assert opts.faults_reset == 1
    else:
        with pytest.raises(DataError, match="refused the move"):
            measure_pose(fake, cfg, Hexapod(cfg), fake.X, 0, opts)


def test_probe_poses_keep_the_whole_probing_cycle_inside_the_box():
    """A tilted pose puts the platform |tip| sin(angle) beside its sphere and the touches go 18.5 mm
    around it: the nearest sphere can take the platform over the [workspace] box (a bench validation
    pose: platform y 151 > 150); retarget_probe picks one whose cycle fits, check_reachable refuses
    poses whose cycle does not."""
    from hexacnc.calib.cyclerun import check_reachable, platform_of_tip, probe_reach_offsets_mm, retarget_probe
    from hexacnc.config import load_config
    from hexacnc.errors import DataError
    from hexacnc.sim.instruments import TouchProbe
    cfg = load_config(None)
    sp = TouchProbe().spheres
    X = np.array([90.0, 100.0, -800.0, -9.9, -10.0, -2.0])            # tip near the (100, 100) column, tilted
    nearest = platform_of_tip(cfg, np.r_[sp[np.argmin(np.linalg.norm(sp - tip_of_(cfg, X), axis=1))], X[3:]])
    offs = probe_reach_offsets_mm()
    with pytest.raises(DataError, match="cannot reach"):
        check_reachable(cfg, nearest[None], 0.3, "valid.csv", offs)
    R = retarget_probe(cfg, X[None], sp)
    check_reachable(cfg, R, 0.3, "valid.csv", offs)
    assert np.allclose(R[0, 3:], X[3:])                                  # orientation kept


def tip_of_(cfg, X):
    from hexacnc.calib.cyclerun import tip_of
    return tip_of(cfg, X)[:3]


def test_a_move_reported_idle_short_of_its_pose_is_made_again_not_measured():
    """Under load a program that a fault ended was once reported idle: the pose was measured where the
    machine had stopped (52 mm short, with readings and tracker agreeing). The commanded pose is checked."""
    from hexacnc.calib.cyclerun import RunOptions, measure_pose
    from hexacnc.config import load_config
    from hexacnc.kinematics import Hexapod
    cfg = load_config(None)

    class Short(FakeTracker):
        programs = 0

        def call(self, op, **kw):
            if op == "program":
                self.programs += 1
            if op == "status":
                pc = list(self.X) if self.programs >= 2 else list(self.X + [40.0, 30.0, 0, 0, 0, 0])
                return dict(super().call(op), state="idle", pose_cmd=pc)
            return super().call(op, **kw)
    fake = Short(cfg, [0.0])
    fake.X = np.asarray(cfg.home_pose, dtype=float)
    opts = RunOptions(settle_s=0.0, progress=False, reset_faults=3)
    r = measure_pose(fake, cfg, Hexapod(cfg), fake.X, 0, opts)
    assert fake.programs == 2 and opts.faults_reset == 1 and r.values
