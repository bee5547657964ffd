"""End to end: the real daemon (hot loop process, simulated drives) fed G-code over its socket.

* a program sent over the socket runs to its end; the final strut commands (status
  ``struts_cmd_mm``) equal the inverse kinematics of the programmed end pose (tool tip ->
  platform pose, plus the sag compensation the cycle applies) within one drive increment;
* seeded random small programs never command a strut outside its limits (every status
  sample while they run, and the daemon never faults) and end where they were programmed;
* a program leaving the workspace is refused with its line before any motion.
"""
from __future__ import annotations

import os
import random
import time

import numpy as np
import pytest

from hexacnc.daemon import protocol as P
from hexacnc.kinematics import Hexapod
from hexacnc.pose import matrix_from_euler

from hexacnc.daemon import core  # noqa: F401  (a broken import fails the suite, never skips it)

from hexacnc.gcode import program_from_config  # noqa: E402
from hexacnc import sag as sagmod              # noqa: E402


from e2e_fixtures import cfg, machine, client  # noqa: E402,F401  (shared fixtures)
from e2e_fixtures import wait_standstill  # noqa: E402


pytestmark = pytest.mark.e2e


def programmed_end_platform_pose(cfg, text: str) -> np.ndarray:
    """Platform pose (mm, deg) at the end of ``text``: the interpreter's last tool-tip pose
    through the planner's conversion (``hexacnc.planner.path.tip_to_platform``), checked
    against the formula t = tip - R (tip_platform + L axis_platform) written out here."""
    from hexacnc.planner.path import tip_to_platform
    prog = program_from_config(text, "expected", cfg)
    last = [b for b in prog.blocks if b.end is not None][-1]
    tip = np.asarray(last.end, dtype=float)
    q = np.asarray(cfg.tool.tip_platform_mm) + last.tool_length_mm * np.asarray(cfg.tool.axis_platform)
    tip_rad = np.concatenate([tip[:3], np.radians(tip[3:])])
    X = np.asarray(tip_to_platform(tip_rad[None, :], q[None, :]), dtype=float)[0]
    pose = np.concatenate([X[:3], np.degrees(X[3:])])
    R = matrix_from_euler(*np.radians(tip[3:]))
    np.testing.assert_allclose(pose, np.concatenate([tip[:3] - R @ q, tip[3:]]), atol=1e-9)
    return pose


def work(cfg, x: float, y: float, z: float, a: float = 0.0, b: float = 0.0, c: float = 0.0) -> str:
    """Axis words in G54 coordinates for a tool-tip pose given in machine coordinates
    (the G54 origin is the interpreter's default for this machine)."""
    from hexacnc.gcode.factory import machine_defaults
    o = np.asarray(machine_defaults(cfg)["work_offsets"][1], dtype=float)
    v = np.array([x, y, z, a, b, c]) - o
    return " ".join(f"{k}{val:.4f}" for k, val in zip("XYZABC", v))


def expected_struts_cmd_mm(cfg, hx: Hexapod, pose_deg: np.ndarray) -> np.ndarray:
    """What the cycle must command at rest at ``pose_deg``: geometric length minus sag elongation."""
    return hx.lengths(pose_deg) + sagmod.sag_compensation_mm(hx, pose_deg)


def _run(client: P.Client, text: str, name: str, watch_limits=None) -> dict:
    r = client.call("program", text=text, name=name, reply_timeout_s=120.0)
    assert r["blocks"] >= 1
    if watch_limits is None:
        return client.call("wait", timeout_s=60.0)
    lo, hi = watch_limits
    sub = client.send("subscribe", rate_hz=200.0)
    wid = client.send("wait", timeout_s=60.0)
    samples = 0
    while True:
        m = client.next_message(70.0)
        assert m is not None, "no reply to wait"
        if m.get("id") == sub and m.get("ok"):
            s = np.asarray(m["struts_cmd_mm"])
            assert np.all(s >= lo - 1e-9) and np.all(s <= hi + 1e-9), (name, s.tolist())
            assert m["state"] != "fault", m["fault"]
            samples += 1
        elif m.get("id") == wid:
            client.call("unsubscribe", sub=sub)
            m["samples"] = samples
            return m


def test_program_over_socket_ends_on_the_inverse_kinematics_of_its_end_pose(cfg, client):
    hx = Hexapod(cfg)
    text = ("(e2e: lines with rotations, an arc, a dwell)\n"
            "G21 G90 G17\n"
            f"G0 {work(cfg, 10, -5, -1140)}\n"
            f"G1 {work(cfg, 20, 5, -1130, 2, -1, 3)} F3000\n"
            f"G2 {work(cfg, 30, 15, -1130, 2, -1, 3)} I5 J5 F2000\n"
            "G4 P0.05\n"
            f"G1 {work(cfg, 25, 12, -1125, -1.5, 2, -2)} F2500\n"
            "M2\n")
    st = _run(client, text, "e2e-end-pose")
    assert st["state"] == "idle" and st["fault"] is None
    assert st["timed_out"] is False
    want_pose = programmed_end_platform_pose(cfg, text)
    want = expected_struts_cmd_mm(cfg, hx, want_pose)
    got = np.asarray(st["struts_cmd_mm"])
    incr_mm = 1.0 / cfg.bus.increments_per_mm
    assert np.max(np.abs(got - want)) <= incr_mm, (got - want).tolist()
    # the commanded pose reported is the programmed one too
    np.testing.assert_allclose(st["pose_cmd"], want_pose, atol=1e-6)
    # and the program is reported finished at 100 %
    prog = st.get("program") or st.get("progress")
    assert prog["name"] == "e2e-end-pose" and prog["percent"] == pytest.approx(100.0)


def test_out_of_workspace_program_is_refused_with_its_line_before_motion(cfg, client):
    before = client.call("status")
    text = f"G21 G90\nG0 {work(cfg, 10, 0, -1140)}\nG1 X15 F3000\nG1 X900 F3000\nG1 X0\nM2\n"
    with pytest.raises(P.DaemonError) as ei:
        client.call("program", text=text, name="too-far", reply_timeout_s=60.0)
    e = ei.value
    assert e.code == "limit", e.reply
    assert e.line == 4, e.reply
    time.sleep(0.1)
    after = client.call("status")
    assert after["state"] == "idle"
    assert after["struts_cmd_mm"] == before["struts_cmd_mm"]     # not one increment moved
    assert after["pose_cmd"] == before["pose_cmd"]


def test_unsupported_gcode_is_refused_with_line_and_column(cfg, client):
    before = client.call("status")
    with pytest.raises(P.DaemonError) as ei:
        client.call("program", text=f"G21 G90\nG0 {work(cfg, 1, 1, -1140)}\nG33 Z-10 K1\nM2\n", name="g33",
                    reply_timeout_s=60.0)
    assert ei.value.code in ("unsupported", "gcode") and ei.value.line == 3
    assert ei.value.error.get("column") is not None
    assert client.call("status")["struts_cmd_mm"] == before["struts_cmd_mm"]


@pytest.mark.slow
def test_random_small_programs_stay_within_limits_and_end_where_programmed(cfg, client):
    hx = Hexapod(cfg)
    lo = float(np.min(cfg.min_length_mm))
    hi = float(np.max(cfg.max_length_mm))
    rng = random.Random(20261121)
    ran = refused = 0
    for k in range(4):
        lines = ["G21 G90"]
        for _ in range(rng.randrange(2, 5)):
            x, y = rng.uniform(-40, 40), rng.uniform(-40, 40)
            z = rng.uniform(-1190, -1110)
            a, b, c = (rng.uniform(-5, 5) for _ in range(3))
            if rng.random() < 0.4:
                lines.append(f"G0 {work(cfg, x, y, z, a, b, c)}")
            else:
                lines.append(f"G1 {work(cfg, x, y, z, a, b, c)} F{rng.uniform(3000, 9000):.0f}")
        lines.append("M2")
        text = "\n".join(lines) + "\n"
        try:
            st = _run(client, text, f"random-{k}", watch_limits=(lo, hi))
        except P.DaemonError as exc:
            # a refusal is allowed only for a named limit on a named line, and nothing moved
            assert exc.code == "limit" and isinstance(exc.line, int), exc.reply
            refused += 1
            continue
        ran += 1
        assert st["state"] == "idle" and st["fault"] is None, st
        assert st["samples"] > 0
        want = expected_struts_cmd_mm(cfg, hx, programmed_end_platform_pose(cfg, text))
        assert np.max(np.abs(np.asarray(st["struts_cmd_mm"]) - want)) <= 1.0 / cfg.bus.increments_per_mm
        assert np.all(np.asarray(st["struts_cmd_mm"]) >= cfg.min_length_mm - 1e-9)
        assert np.all(np.asarray(st["struts_cmd_mm"]) <= cfg.max_length_mm + 1e-9)
    assert ran >= 2, (ran, refused)


def test_send_command_against_the_real_daemon(cfg, machine, tmp_path, capsys):
    from hexacnc.cli import main as cli
    daemon, srv = machine
    p = tmp_path / "small.ngc"
    p.write_text(f"G21 G90\nG1 {work(cfg, 5, 5, -1140)} F3000\nG1 {work(cfg, 0, 0, -1150)}\nM2\n")
    rc = cli(["send", str(p), "--socket", srv.socket_path])
    out = capsys.readouterr()
    assert rc == 0, out
    assert "finished" in out.out
    bad = tmp_path / "bad.ngc"
    bad.write_text("G21 G90\nG1 X5 F3000\nG1 X2000\nM2\n")
    assert cli(["send", str(bad), "--socket", srv.socket_path]) == 3
    assert f"{bad}:3" in capsys.readouterr().err
    assert cli(["status", "--socket", srv.socket_path, "--json"]) == 0


def test_send_ctrl_c_stops_the_program_under_control(cfg, machine, tmp_path):
    """``hexacnc send`` as a separate process; SIGINT asks for a controlled stop; exit code 5."""
    import signal
    import subprocess
    import sys
    daemon, srv = machine
    p = tmp_path / "long.ngc"
    p.write_text(f"G21 G90\nG1 {work(cfg, 40, 0, -1150)} F600\nG1 {work(cfg, -40, 0, -1150)}\nM2\n")
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    proc = subprocess.Popen([sys.executable, "-m", "hexacnc", "send", str(p), "--socket", srv.socket_path],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with P.Client.unix(srv.socket_path) as obs:
            deadline = time.monotonic() + 20.0
            while obs.call("status")["state"] != "running":
                assert proc.poll() is None, proc.communicate()
                assert time.monotonic() < deadline
                time.sleep(0.05)
            time.sleep(0.5)
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=30)
            assert proc.returncode == 5, (out, err)
            assert "stopping" in err and "stopped" in err
            st = obs.call("status")
            assert st["state"] == "idle" and st["fault"] is None
            assert st["program"]["stopped"] is True and st["program"]["percent"] < 100.0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.mark.slow
def test_pause_and_resume_a_program_over_the_socket_still_ends_on_its_end_pose(cfg, client):
    hx = Hexapod(cfg)
    text = (f"G21 G90\nG1 {work(cfg, 30, 0, -1150)} F1500\nG1 {work(cfg, 30, 30, -1140, 2, 0, 0)}\n"
            f"G1 {work(cfg, 0, 0, -1150)}\nM2\n")
    assert client.call("program", text=text, name="pausable")["blocks"] >= 3
    time.sleep(0.4)
    client.call("pause")
    deadline = time.monotonic() + 10.0
    while client.call("status")["state"] != "paused":
        assert time.monotonic() < deadline
        time.sleep(0.02)
    # the pause decelerates along the path to rest (after the rows already queued to the loop)
    p1 = wait_standstill(client, timeout_s=3.0)["pose_cmd"]
    time.sleep(0.3)
    st = client.call("status")
    assert st["pose_cmd"] == p1 and st["state"] == "paused"
    assert 0.0 < st["program"]["percent"] < 100.0
    client.call("resume")
    st = client.call("wait", timeout_s=60.0)
    assert st["state"] == "idle" and st["fault"] is None and st["program"]["percent"] == pytest.approx(100.0)
    want = expected_struts_cmd_mm(cfg, hx, programmed_end_platform_pose(cfg, text))
    assert np.max(np.abs(np.asarray(st["struts_cmd_mm"]) - want)) <= 1.0 / cfg.bus.increments_per_mm


@pytest.mark.slow
def test_feed_hold_acts_on_the_rows_the_drives_get_next_not_after_the_queue(cfg, client):
    """Pause at 200 mm/s: the daemon takes back the rows queued beyond its short lead
    (core.REWIND_LEAD_S) and re-plans them as the deceleration, so the tool comes to rest within
    lead + one feeder chunk + the deceleration - not after the whole queue (FEED_AHEAD_S).
    Resume continues on the path and the program ends where it was programmed."""
    hx = Hexapod(cfg)
    v_mm_s = 200.0
    text = ("G21 G90 G64 P0.1\n"
            f"G0 {work(cfg, -120, 0, -1140)}\n"
            f"G1 {work(cfg, 120, 0, -1140)} F{60 * v_mm_s:.0f}\n"
            f"G1 {work(cfg, -120, 0, -1140)}\n"
            "M2\n")
    client.call("program", text=text, name="feed-hold", reply_timeout_s=120.0)
    t0 = time.monotonic()
    for side in (-1.0, 1.0):        # the G0 to the start (x < -100), then the middle of the first G1
        while side * client.call("status")["pose_cmd"][0] < 100.0 * (side < 0):
            assert time.monotonic() - t0 < 20.0
            time.sleep(0.005)
    at_pause = np.asarray(client.call("pause")["pose_cmd"])
    # standstill: the same commanded pose 5 polls in a row, within 30 s of the program's start
    st = wait_standstill(client, timeout_s=30.0 - (time.monotonic() - t0), interval_s=0.01, polls=5)
    assert st["state"] == "paused"
    travel_mm = abs(st["pose_cmd"][0] - at_pause[0])
    lead_s = core.REWIND_LEAD_S + core.FEED_CHUNK_ROWS * cfg.cycle.period_s
    # lead at full speed, plus a deceleration of at most 0.15 s at full speed (measured 0.06-0.1 s)
    assert travel_mm <= v_mm_s * (lead_s + 0.15), travel_mm
    assert travel_mm < v_mm_s * cfg.daemon.feed_ahead_s * 0.75       # well short of the queue
    assert np.all(np.abs(np.asarray(st["pose_cmd"][1:3]) - at_pause[1:3]) < 1e-6)   # on the line
    client.call("resume")
    st = client.call("wait", timeout_s=30.0)
    assert st["state"] == "idle" and st["fault"] is None
    want = expected_struts_cmd_mm(cfg, hx, programmed_end_platform_pose(cfg, text))
    assert np.max(np.abs(np.asarray(st["struts_cmd_mm"]) - want)) <= 1.0 / cfg.bus.increments_per_mm
