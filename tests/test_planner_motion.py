"""Planner: dynamic limits on random programs, blending vs exact stop, feed, override, pause/resume, stop, sampler.

Utilisation is measured independently here: the sampler's platform rows go through
``Hexapod.inverse_batch`` and finite differences at the cycle period.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.gcode.blocks import Block
from hexacnc.kinematics import Hexapod
from hexacnc.pose import matrix_from_euler
from hexacnc.planner import FLAG_PROGRAM_PAUSE, plan_program


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def rapid_lifted(cfg):
    """``cfg`` with ``[planner] rapid_feed_mm_min`` far above what the struts allow: the rapid feed caps every
    feed (as LinuxCNC's maximum velocity), so a plan at the strut limits needs it lifted."""
    return cfg.replace(planner=dataclasses.replace(cfg.planner, rapid_feed_mm_min=1e9))


def tip_of(cfg, P):
    P = np.asarray(P, dtype=float)
    R = matrix_from_euler(*np.radians(P[3:]))
    out = P.copy()
    out[:3] = P[:3] + R @ np.asarray(cfg.tool.tip_platform_mm)
    return out


def run(sampler, chunk=500, hook=None, limit=2_000_000):
    out = np.empty((chunk, 8))
    rows = []
    n = 0
    while n < limit:
        if hook is not None:
            hook(sampler, n)
        c = sampler.next_rows(out)
        if c == 0:
            break
        rows.append(out[:c].copy())
        n += c
    return np.vstack(rows)


def utilisation(cfg, rows, dt):
    hx = Hexapod(cfg)
    P = rows[:, :6].copy()
    P[:, 3:] = np.degrees(P[:, 3:])
    L = hx.inverse_batch(P)
    v = np.diff(L, axis=0) / dt
    a = np.diff(v, axis=0) / dt
    j = np.diff(a, axis=0) / dt
    return (float(np.max(np.abs(v) / cfg.max_velocity_mm_s)), float(np.max(np.abs(a) / cfg.max_acceleration_mm_s2)),
            float(np.max(np.abs(j) / cfg.max_jerk_mm_s3)))


def random_program(cfg, seed, n=8):
    rng = np.random.default_rng(seed)
    home = np.array(cfg.home_pose, dtype=float)
    P = [home]
    blocks = []
    line = 1
    for _ in range(n):
        nxt = home + np.concatenate([rng.uniform(-60, 60, 3), rng.uniform(-8, 8, 3)])
        a, b = tip_of(cfg, P[-1]), tip_of(cfg, nxt)
        kind = rng.choice(["line", "rapid", "arc"])
        feed = float(rng.uniform(5, 200))
        tol = float(rng.choice([0.01, 0.1, 0.5]))
        if kind == "arc":
            # helical arc in a random plane through a, ending at b's height along the normal
            nrm = rng.normal(size=3)
            nrm /= np.linalg.norm(nrm)
            chord = b[:3] - a[:3]
            inplane = chord - (chord @ nrm) * nrm
            if np.linalg.norm(inplane) < 5:
                kind = "line"
            else:
                ctr = a[:3] + 0.5 * inplane + np.cross(nrm, inplane) * rng.uniform(-0.5, 0.5)
                # same radius at both ends: move b radially onto the circle
                r0 = a[:3] - ctr - ((a[:3] - ctr) @ nrm) * nrm
                rb = b[:3] - ctr - ((b[:3] - ctr) @ nrm) * nrm
                b[:3] = ctr + ((b[:3] - ctr) @ nrm) * nrm + rb / np.linalg.norm(rb) * np.linalg.norm(r0)
                blocks.append(Block("arc", line, a, b, feed_mm_s=feed, center=ctr, normal=nrm,
                                    clockwise=bool(rng.integers(2)), blend_tolerance_mm=tol))
        if kind != "arc":
            blocks.append(Block(kind, line, a, b, feed_mm_s=None if kind == "rapid" else feed,
                                blend_tolerance_mm=tol))
        # platform pose at the end (for the next start)
        R = matrix_from_euler(*np.radians(b[3:]))
        nx = b.copy()
        nx[:3] = b[:3] - R @ np.asarray(cfg.tool.tip_platform_mm)
        P.append(nx)
        line += 1
    return blocks


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_random_programs_stay_within_strut_limits(cfg, seed):
    blocks = random_program(cfg, seed)
    plan = plan_program(blocks, cfg)
    assert all(v <= 1.0 for v in plan.utilisation.values())
    rows = run(plan.sampler())
    uv, ua, uj = utilisation(cfg, rows, plan.dt)
    assert uv <= 1.0 and ua <= 1.0 and uj <= 1.0, (uv, ua, uj)
    # the planner's own figures are measurements of the same table
    assert uv == pytest.approx(plan.utilisation["velocity"], rel=1e-3, abs=1e-6)
    # ends on the programmed end pose
    last = blocks[-1].end
    R = matrix_from_euler(*np.radians(last[3:]))
    end_platform = last[:3] - R @ np.asarray(cfg.tool.tip_platform_mm)
    assert np.allclose(rows[-1, :3], end_platform, atol=1e-6)
    assert np.allclose(rows[-1, 3:6], np.radians(last[3:]), atol=1e-9)


def corner_program(cfg, exact, rotate=False):
    home = np.array(cfg.home_pose, dtype=float)
    p1 = home + [60, 0, 0, 0, 0, 0]
    p2 = home + [120, 8, 0, 3 if rotate else 0, 2 if rotate else 0, 0]      # a 4 degree corner
    t0, t1, t2 = tip_of(cfg, home), tip_of(cfg, p1), tip_of(cfg, p2)
    return [Block("line", 2, t0, t1, feed_mm_s=250.0, exact_stop=exact, blend_tolerance_mm=0.2),
            Block("line", 3, t1, t2, feed_mm_s=250.0, exact_stop=exact, blend_tolerance_mm=0.2)], t1, t2


def tips_of_rows(cfg, rows):
    q = np.asarray(cfg.tool.tip_platform_mm)
    out = np.empty((rows.shape[0], 3))
    for i, r in enumerate(rows):
        out[i] = r[:3] + matrix_from_euler(*r[3:6]) @ q
    return out


@pytest.mark.parametrize("rotate", [False, True])
def test_exact_stop_versus_blending(cfg, rotate):
    be, corner, t2 = corner_program(cfg, exact=True, rotate=rotate)
    bb, _, _ = corner_program(cfg, exact=False, rotate=rotate)
    pe = plan_program(be, cfg)
    pb = plan_program(bb, cfg)
    assert pe.n_blends == 0 and pb.n_blends == 1          # rotary moves are blended too
    re = run(pe.sampler())
    rb = run(pb.sampler())
    te = tips_of_rows(cfg, re)
    tb = tips_of_rows(cfg, rb)
    # exact stop: passes through the corner at standstill
    k = int(np.argmin(np.linalg.norm(te - corner[:3], axis=1)))
    assert np.linalg.norm(te[k] - corner[:3]) < 1e-6
    assert np.linalg.norm(te[k + 1] - te[k - 1]) / (2 * pe.dt) < 1e-2      # mm/s, vs 250 mm/s feed
    # blending: never closer than a bit to the corner, within the 0.2 mm tolerance of the corner lines,
    # and keeps moving
    d_corner = np.linalg.norm(tb - corner[:3], axis=1)
    k = int(np.argmin(d_corner))
    assert 1e-3 < d_corner[k] <= 0.2 + 1e-9
    def dist_to_line(p, a, b):
        e = (b - a) / np.linalg.norm(b - a)
        rel = p - a
        return np.linalg.norm(rel - np.outer(rel @ e, e), axis=1)
    d1 = dist_to_line(tb, be[0].start[:3], corner[:3])
    d2 = dist_to_line(tb, corner[:3], t2[:3])
    assert np.max(np.minimum(d1, d2)) <= 0.2 + 1e-9
    speed = np.linalg.norm(np.diff(tb, axis=0), axis=1) / pb.dt
    assert speed[k] > 10.0
    if not rotate:
        # (with rotation the short blend is jerk-bound at 250 mm/s and about as slow as a stop: see docs)
        assert pb.duration_s < pe.duration_s
    for rows, p in ((re, pe), (rb, pb)):
        assert max(utilisation(cfg, rows, p.dt)) <= 1.0


def test_feed_is_the_tool_tip_speed(cfg):
    home = np.array(cfg.home_pose, dtype=float)
    a, b = tip_of(cfg, home), tip_of(cfg, home + [100, 0, 0, 0, 0, 0])
    plan = plan_program([Block("line", 1, a, b, feed_mm_s=10.0)], cfg)
    rows = run(plan.sampler())
    speed = np.linalg.norm(np.diff(tips_of_rows(cfg, rows), axis=0), axis=1) / plan.dt
    assert speed.max() <= 10.0 * (1 + 1e-6)
    assert speed.max() >= 10.0 * (1 - 1e-3)
    assert plan.duration_s == pytest.approx(10.0, abs=0.3)
    # G93: the move takes the programmed time
    p93 = plan_program([Block("line", 1, a, b, inverse_time_s=20.0)], cfg)
    assert p93.duration_s == pytest.approx(20.0, abs=0.3)


def test_dwell_and_program_pause(cfg):
    home = np.array(cfg.home_pose, dtype=float)
    t0, t1, t2 = (tip_of(cfg, home + d) for d in ([0] * 6, [30, 0, 0, 0, 0, 0], [30, 30, 0, 0, 0, 0]))
    blocks = [Block("line", 1, t0, t1, feed_mm_s=50.0), Block("dwell", 2, seconds=0.7),
              Block("line", 3, t1, t2, feed_mm_s=50.0), Block("pause", 4), Block("line", 5, t2, t0, feed_mm_s=50.0),
              Block("end", 6)]
    plan = plan_program(blocks, cfg)
    # dwell: standing still for at least 0.7 s on line 2
    rows = plan.rows()
    on2 = rows[rows[:, 6] == 2]
    assert on2.shape[0] * plan.dt >= 0.7
    assert np.ptp(on2[:, :3], axis=0).max() < 1e-9
    s = plan.sampler()
    paused_rows = []

    def hook(smp, n):
        if smp.state == "program_paused":
            paused_rows.append(n)
            if len(paused_rows) > 5:
                smp.resume()
    rows = run(s, chunk=100, hook=hook)
    assert len(paused_rows) > 5
    assert np.any(rows[:, 7].astype(int) & FLAG_PROGRAM_PAUSE) or s.done
    assert max(utilisation(cfg, rows, plan.dt)) <= 1.0


def long_program(cfg):
    home = np.array(cfg.home_pose, dtype=float)
    pts = [home, home + [80, 0, 0, 0, 0, 0], home + [80, 80, 0, 5, 0, 0], home + [-80, 80, 0, 5, 5, 0],
           home + [-80, -80, 20, 0, 5, 10], home]
    tips = [tip_of(cfg, p) for p in pts]
    blocks = [Block("rapid", 1, tips[0], tips[1])]
    blocks += [Block("line", i + 1, tips[i], tips[i + 1], feed_mm_s=120.0, blend_tolerance_mm=0.05)
               for i in range(1, len(tips) - 1)]
    return blocks


def on_path_distance(cfg, plan, rows):
    """Distance of each row's platform pose from the plan's path (nearest of dense path samples)."""
    from scipy.spatial import cKDTree
    s = np.linspace(0, plan.path.total, 400_001)
    X = plan.platform_at(s)
    tree = cKDTree(np.hstack([X[:, :3], 100 * X[:, 3:]]))
    d, _ = tree.query(np.hstack([rows[:, :3], 100 * rows[:, 3:6]]))
    return d


def test_override_pause_resume_stop_are_jerk_limited_and_on_path(cfg):
    plan = plan_program(long_program(cfg), cfg)
    events = {}

    def hook(smp, n):
        t = n * plan.dt
        if t > 0.4 and "o1" not in events:
            events["o1"] = smp.set_override(0.4)
        if t > 1.2 and "o2" not in events:
            events["o2"] = smp.set_override(1.2)
        if t > 2.0 and "pause" not in events:
            events["pause"] = smp.pause()
        if smp.state == "paused" and "paused_at" not in events:
            events["paused_at"] = n
        if "paused_at" in events and n > events["paused_at"] + 400 and "resume" not in events:
            events["resume"] = smp.resume()
        if t > 4.0 and "stop" not in events:
            events["stop"] = smp.stop()
    s = plan.sampler()
    rows = run(s, chunk=50, hook=hook)
    assert "paused_at" in events and s.done and s.state == "done"
    uv, ua, uj = utilisation(cfg, rows, plan.dt)
    assert uv <= 1.0 and ua <= 1.0 and uj <= 1.0, (uv, ua, uj)
    # at standstill while paused, and at the end of the stop
    k = events["paused_at"]
    assert np.abs(rows[k + 1:k + 300, :6] - rows[k, :6]).max() < 1e-9
    # the stop ends at rest: the last cycle moves less than 0.05 mm/s (the feed was 120 mm/s)
    assert np.linalg.norm(rows[-1, :3] - rows[-2, :3]) / plan.dt < 0.05
    assert s.progress[0] < 100.0                    # stopped before the end
    # every row on the planned path
    assert on_path_distance(cfg, plan, rows).max() < 0.01


def test_sampler_is_continuous_across_chunks_and_periods(cfg):
    plan = plan_program(long_program(cfg), cfg)
    big = run(plan.sampler(), chunk=100_000)
    small = run(plan.sampler(), chunk=7)
    assert big.shape == small.shape
    assert np.array_equal(big, small)
    assert big.shape[0] == pytest.approx(plan.duration_s / plan.dt + 1, abs=2)
    step = np.abs(np.diff(big[:, :3], axis=0)).max()
    assert step <= 250.0 * plan.dt * 1.5            # no jumps: at most rapid speed per cycle
    # another period: same path and duration
    half = run(plan.sampler(period_s=plan.dt / 2), chunk=999)
    assert half.shape[0] == pytest.approx(2 * (big.shape[0] - 1) + 1, abs=3)
    # rows are one period ahead of the start: half-period rows 1, 3, 5, ... are the full-period rows
    n2 = min(half[1::2].shape[0], big.shape[0])
    assert np.allclose(half[1::2][:n2, :7], big[:n2, :7], atol=1e-6)
    # progress reaches 100 %
    s = plan.sampler()
    run(s)
    assert s.progress == (100.0, 0.0) and s.done
    assert math.isfinite(plan.min_joint_margin_deg)


@pytest.mark.parametrize("seed", [0, 1])
def test_pause_on_a_plan_at_the_strut_limits(cfg, seed):
    """Pause while the nominal plan uses ~99 % velocity / ~93 % acceleration: still within limits, on
    the path, and at rest within half a second."""
    from hexacnc.bench.toppra_peer import topp_path_blocks
    cfg = rapid_lifted(cfg)
    plan = plan_program(topp_path_blocks(cfg), cfg)
    assert plan.utilisation["velocity"] > 0.9
    tp = np.random.default_rng(seed).uniform(0.3, plan.duration_s - 0.5)
    assert _pause_and_resume(cfg, plan, tp, 200, chunk=20) < 0.5


def _pause_and_resume(cfg, plan, at_s: float, rest_rows: int, chunk: int) -> float:
    """Runs the plan's sampler, pauses at plan time ``at_s`` and resumes ``rest_rows`` rows after the
    standstill; checks the rows within the limits by independent differences and on the path.  Returns the
    seconds from the pause to the standstill."""
    ev = {}

    def hook(s, n):
        if n * plan.dt > at_s and "p" not in ev:
            ev["p"] = n
            s.pause()
        if s.state == "paused" and "at" not in ev:
            ev["at"] = n
        if "at" in ev and n > ev["at"] + rest_rows and "r" not in ev:
            ev["r"] = n
            s.resume()
    s = plan.sampler()
    rows = run(s, chunk=chunk, hook=hook)
    assert s.done and "r" in ev
    assert max(utilisation(cfg, rows, plan.dt)) <= 1.0
    assert on_path_distance(cfg, plan, rows).max() < 0.01
    return (ev["at"] - ev["p"]) * plan.dt


def test_a_pause_in_a_cruise_takes_the_headroom_of_the_rows_it_runs_through(cfg):
    """Pause at 200 mm/s in the middle of a 240 mm line: the rate's limits come from the rows the
    deceleration runs through, not from the deceleration at the line's end 0.6 s ahead (a window of
    1.2 s of table time took that in, left 2-14 % of the jerk limit for the rate and the pause took
    0.2-0.3 s, 29-51 mm).  At rest within 0.1 s (measured 44 ms), within the limits, on the path."""
    home = np.array(cfg.home_pose, dtype=float)
    tips = [tip_of(cfg, home + [x, 0, 0, 0, 0, 0]) for x in (-120.0, 120.0, -120.0)]
    blocks = [Block("line", 1 + i, tips[i], tips[i + 1], feed_mm_s=200.0, blend_tolerance_mm=0.1)
              for i in range(2)]
    plan = plan_program(blocks, cfg)
    mid = float(np.interp(0.0, [-120.0, 120.0], [0.0, plan.line_times[1][1]]))      # about x = 0
    t_rest = _pause_and_resume(cfg, plan, mid, 50, chunk=10)
    assert t_rest < 0.1, t_rest


def test_snapshot_restore_replays_exactly_and_a_rewound_pause_stays_within_limits(cfg):
    """The daemon takes back queued rows by restoring a sampler snapshot: what follows a restore is
    bit-identical to the first run, and a pause applied after the rewind (rows already run
    followed by the new deceleration) keeps strut velocity/acceleration/jerk within limits."""
    plan = plan_program(long_program(cfg), cfg)
    s = plan.sampler()
    out = np.empty((37, 8))
    head = []
    for _ in range(40):                                  # well into the program
        n = s.next_rows(out)
        head.append(out[:n].copy())
    snap = s.snapshot()
    first = run(s, chunk=53, limit=3000)
    s.restore(snap)
    again = run(s, chunk=11, limit=3000)
    m = min(len(first), len(again))
    assert m >= 3000 and np.array_equal(first[:m], again[:m])
    # rewind to the snapshot and pause there: the ring would hold head + the pause rows
    s.restore(snap)
    s.pause()
    tail = run(s, chunk=64, limit=2000)
    rows = np.vstack(head + [tail])
    assert s.state == "paused"
    uv, ua, uj = utilisation(cfg, rows, plan.dt)
    assert uv <= 1.0 and ua <= 1.0 and uj <= 1.0, (uv, ua, uj)
    assert np.abs(rows[-100:, :6] - rows[-1, :6]).max() < 1e-12        # at rest, paused
    assert on_path_distance(cfg, plan, rows).max() < 0.01
