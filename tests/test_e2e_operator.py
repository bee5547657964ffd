"""Operator control end to end: the CLI against the real daemon and simulated drives.

The machine here has Cartesian soft limits close around the home tool tip (x, y +-5 mm, z -1190 ..
-1140, a b c +-2 deg) so that limits are reached in a fraction of a second of jogging, and
``[planner] max_feed_override`` 1.5.
"""
from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import time

import numpy as np
import pytest

from hexacnc.cli import main as cli
from hexacnc.daemon import protocol as P
from hexacnc.daemon.server import SocketServer

from e2e_fixtures import cfg, core, running_machine  # noqa: F401

pytestmark = pytest.mark.e2e

TIP_MIN = [-5.0, -5.0, -1190.0, -2.0, -2.0, -2.0]
TIP_MAX = [5.0, 5.0, -1140.0, 2.0, 2.0, 2.0]


@pytest.fixture(scope="module")
def state_dir():
    d = tempfile.mkdtemp(prefix="hxopst", dir="/tmp")
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(scope="module")
def opcfg(cfg, state_dir):  # noqa: F811
    # deadman 0.1 s (the largest allowed): a loaded test machine must not stop the jogs early
    jog = dataclasses.replace(cfg.operator.jog, deadman_s=0.1)
    op = dataclasses.replace(cfg.operator, state_dir=state_dir, max_feed_override=1.5, jog=jog,
                             tip_min=np.array(TIP_MIN), tip_max=np.array(TIP_MAX))
    return cfg.replace(operator=op)


@pytest.fixture(scope="module")
def machine(opcfg):
    yield from running_machine(opcfg, name="op")


@pytest.fixture
def sock(machine):
    daemon, srv = machine
    with P.Client.unix(srv.socket_path) as c:
        st = c.call("status")
        if st["state"] == "fault" or not st["drives_enabled"]:
            c.call("reset", reply_timeout_s=30.0)
        elif st["state"] in ("running", "paused"):
            c.call("stop")
        c.call("wait", timeout_s=30.0)
        c.call("override", feed=1.0, rapid=1.0, optional_stop=False, block_delete=True)
        work = c.call("status")["tool_tip"]["work"]
        if max(abs(work[0]), abs(work[1]), abs(work[2] - 30.0)) > 0.01:     # a test left it elsewhere
            c.call("mdi", text="G90 G0 X0 Y0 Z30")
            c.call("wait", timeout_s=30.0)
    time.sleep(0.05)
    return srv.socket_path


def run(capsys, *argv) -> tuple[int, str, str]:
    rc = cli(list(argv))
    out = capsys.readouterr()
    return rc, out.out, out.err


def status(sock_path: str) -> dict:
    with P.Client.unix(sock_path) as c:
        return c.call("status")


def tip(sock_path: str) -> np.ndarray:
    return np.array(status(sock_path)["tool_tip"]["machine"])


def long_program(client, name: str = "long") -> None:
    """A program that runs for several seconds inside the soft limits."""
    lines = ["G21 G90 G64 P0.05", "G0 X-4 Y0 Z30"]
    for k in range(12):
        lines.append(f"G1 X{4 if k % 2 == 0 else -4} F120")
    lines.append("M2")
    client.call("program", text="\n".join(lines) + "\n", name=name, reply_timeout_s=120.0)


def test_jog_incremental_moves_and_refuses_past_the_limit(sock, capsys):
    t0 = tip(sock)
    rc, out, err = run(capsys, "jog", "z", "+0.1", "--socket", sock)
    assert rc == 0, err
    t1 = tip(sock)
    assert t1[2] - t0[2] == pytest.approx(0.1, abs=1e-6)
    assert np.allclose(t1[[0, 1, 3, 4, 5]], t0[[0, 1, 3, 4, 5]], atol=1e-6)
    rc, out, err = run(capsys, "jog", "x", "+20", "--socket", sock)
    assert rc == 3
    assert "soft limit" in err and "refused" in err and len(err.strip().splitlines()) == 1
    assert np.allclose(tip(sock), t1, atol=1e-9)            # nothing moved
    rc, out, err = run(capsys, "jog", "z", "-0.1", "--socket", sock)
    assert rc == 0


def test_jog_rotation_about_the_tool_tip(sock, capsys):
    t0 = tip(sock)
    rc, _, err = run(capsys, "jog", "a", "+0.5", "--socket", sock)
    assert rc == 0, err
    t1 = tip(sock)
    assert t1[3] - t0[3] == pytest.approx(0.5, abs=1e-6)
    assert np.allclose(t1[:3], t0[:3], atol=1e-6)           # pivot: the tool tip stays
    assert run(capsys, "jog", "a", "-0.5", "--socket", sock)[0] == 0


def test_continuous_jog_comes_to_rest_at_the_limit(sock, capsys):
    for _ in range(4):      # a confirmation late by over deadman_s (loaded machine) stops it early: go on
        rc, out, err = run(capsys, "jog", "--continuous", "x", "+", "--for", "20", "--socket", sock)
        assert rc == 0, err
        t = tip(sock)
        if t[0] >= TIP_MAX[0] - 0.05:
            break
    assert TIP_MAX[0] - 0.05 <= t[0] <= TIP_MAX[0]
    rc, out, err = run(capsys, "jog", "x", "+0.5", "--socket", sock)
    assert rc == 3 and "soft limit" in err
    rc, out, err = run(capsys, "jog", "x", f"{-t[0]:.6f}", "--socket", sock)
    assert rc == 0, err


def test_continuous_jog_stops_when_confirmations_stop(sock):
    with P.Client.unix(sock) as c:
        r = c.call("jog", axis="y", direction=1)
        assert r["continuous"] and r["deadman_s"] <= 0.1
        for _ in range(4):                 # ~0.1 s of confirmations: the jog would reach the limit in ~0.5 s
            try:
                c.call("jog", action="confirm")
            except P.DaemonError as exc:          # a confirmation later than deadman_s (loaded machine)
                assert exc.code == "invalid_state"
                break
            time.sleep(0.02)
        st = c.call("wait", timeout_s=5.0)               # no more confirmations: the deadman stops it
        assert st["state"] == "idle" and not st.get("timeout")
        y = c.call("status")["tool_tip"]["machine"][1]
        assert 0.0 < y < 4.0                                   # moved, and stopped well before the limit
        with pytest.raises(P.DaemonError) as ei:
            c.call("jog", action="confirm")
        assert ei.value.code == "invalid_state"
        c.call("jog", axis="y", distance=-y)
        c.call("wait", timeout_s=10.0)


def test_mdi_keeps_the_modal_state_and_checks_limits(sock, capsys):
    rc, out, err = run(capsys, "mdi", "G21 G90 G1 X1 Y1 Z32 F600", "--socket", sock)
    assert rc == 0, err
    rc, out, err = run(capsys, "mdi", "X2", "--socket", sock)        # G1 F600 from the line before
    assert rc == 0, err
    t = tip(sock)
    assert t[0] == pytest.approx(2.0, abs=1e-6) and t[1] == pytest.approx(1.0, abs=1e-6)
    st = status(sock)
    assert st["modal"].startswith("G1 ") and "F600" in st["modal"] and "G54" in st["modal"]
    rc, out, err = run(capsys, "mdi", "G1 X40", "--socket", sock)
    assert rc == 3 and "soft limit" in err and err.count("line 1") == 1, err       # once, not three times
    assert np.allclose(tip(sock), t, atol=1e-9)
    assert run(capsys, "mdi", "G0 X0 Y0 Z30", "--socket", sock)[0] == 0


def test_a_dwell_or_m0_without_motion_takes_its_time(sock, capsys):
    """As in LinuxCNC, ``G4 P0.8`` alone (MDI or a program) stands still for 0.8 s and M0 alone pauses until
    resumed; before, a program without motion queued nothing and returned at once."""
    t0 = tip(sock)
    started = time.monotonic()
    rc, out, err = run(capsys, "mdi", "G4 P0.8", "--socket", sock)
    assert rc == 0, err
    assert time.monotonic() - started >= 0.8 and "0.80 s" in out, out
    with P.Client.unix(sock) as c:
        r = c.call("program", text="G4 P0.8\nM2\n", name="dwell", reply_timeout_s=60.0)
        assert r["duration_s"] == pytest.approx(0.8, abs=0.01), r
        assert c.call("status")["state"] == "running"          # the dwell runs as a job
        c.call("wait", timeout_s=30.0)
        c.call("program", text="M0\nM2\n", name="m0", reply_timeout_s=60.0)
        deadline = time.monotonic() + 10.0
        while c.call("status")["state"] != "paused" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert c.call("status")["state"] == "paused"
        c.call("resume")
        assert c.call("wait", timeout_s=30.0)["state"] == "idle"
        # a zero dwell and settings alone still queue nothing
        r = c.call("program", text="G4 P0\nG55\nG54\nM2\n", name="nothing", reply_timeout_s=60.0)
        assert r.get("moved") is False and c.call("status")["state"] == "idle", r
    assert np.allclose(tip(sock), t0, atol=1e-9)


def _states_until_idle(c, timeout_s: float = 30.0, resume_paused: bool = False) -> list[str]:
    seen, t_end = [], time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        st = c.call("status")["state"]
        if not seen or seen[-1] != st:
            seen.append(st)
        if st == "idle" and len(seen) > 1:
            break
        if st == "paused" and resume_paused:
            c.call("resume")
        time.sleep(0.02)
    return seen


def test_m1_pauses_only_with_the_optional_stop_switch_on(sock, capsys):
    """LinuxCNC's optional stop: M1 pauses as M0 with the switch on (at start: ``[planner] optional_stop``,
    default on as LinuxCNC's canon) and is skipped with it off; switched while a program runs, it acts on
    an M1 still ahead.  (The fixture switches it off before each test.)"""
    from hexacnc.config import load_config
    assert load_config(None).operator.optional_stop is True
    prog = "G21 G90 G1 X2 F600\nM1\nG1 X0\nM2\n"
    rc, out, err = run(capsys, "optional-stop", "--socket", sock)
    assert rc == 0 and out.strip() == "optional stop off", (out, err)
    with P.Client.unix(sock) as c:
        c.call("program", text=prog, name="m1-off", reply_timeout_s=60.0)
        assert "paused" not in _states_until_idle(c)
    rc, out, err = run(capsys, "optional-stop", "on", "--socket", sock)
    assert rc == 0 and out.strip() == "optional stop on", (out, err)
    with P.Client.unix(sock) as c:
        assert c.call("status")["overrides"]["optional_stop"] is True
        c.call("program", text=prog, name="m1-on", reply_timeout_s=60.0)
        assert "paused" in _states_until_idle(c, resume_paused=True)
        # switched on while the program runs: 2 s of motion before the M1
        c.call("override", optional_stop=False)
        c.call("program", text="G21 G90 G1 X2 F60\nM1\nG1 X0 F600\nM2\n", name="m1-live", reply_timeout_s=60.0)
        t_end = time.monotonic() + 10.0
        while c.call("status")["state"] != "running" and time.monotonic() < t_end:
            time.sleep(0.02)
        assert c.call("override", optional_stop=True)["optional_stop"] is True
        assert c.call("status")["program"]["line"] == 1              # before the M1
        assert "paused" in _states_until_idle(c, resume_paused=True)
        with pytest.raises(P.DaemonError, match="optional_stop"):
            c.call("override", optional_stop="yes")
    assert np.allclose(tip(sock)[:3], [0.0, 0.0, tip(sock)[2]], atol=1e-6)


def test_block_delete_switch_skips_or_runs_the_slash_lines(sock, capsys):
    """LinuxCNC's block delete: on (the default, ``[planner] block_delete``) a line starting with '/' is
    skipped, off it runs; the switch acts on programs and MDI sent after it."""
    from hexacnc.config import load_config
    assert load_config(None).operator.block_delete is True
    prog = "G21 G90 G1 X1 F600\n/G1 X3\nM2\n"
    t0 = tip(sock)
    with P.Client.unix(sock) as c:
        c.call("program", text=prog, name="bd-on", reply_timeout_s=60.0)
        c.call("wait", timeout_s=30.0)
        assert tip(sock)[0] == pytest.approx(t0[0] + 1.0, abs=1e-6)
    rc, out, err = run(capsys, "block-delete", "off", "--socket", sock)
    assert rc == 0 and out.strip() == "block delete off", (out, err)
    with P.Client.unix(sock) as c:
        assert c.call("status")["overrides"]["block_delete"] is False
        c.call("program", text=prog, name="bd-off", reply_timeout_s=60.0)
        c.call("wait", timeout_s=30.0)
        assert tip(sock)[0] == pytest.approx(t0[0] + 3.0, abs=1e-6)
        c.call("mdi", text="/G1 X0")                      # MDI too
        c.call("wait", timeout_s=30.0)
        assert tip(sock)[0] == pytest.approx(t0[0], abs=1e-6)
        assert c.call("override", block_delete=True)["block_delete"] is True
        c.call("mdi", text="/G1 X2")
        c.call("wait", timeout_s=30.0)
        assert tip(sock)[0] == pytest.approx(t0[0], abs=1e-6)
    rc, out, err = run(capsys, "block-delete", "--socket", sock)
    assert rc == 0 and out.strip() == "block delete on", (out, err)


def test_mdi_refused_during_a_program_and_non_controller_refused(sock, capsys):
    with P.Client.unix(sock) as a:
        long_program(a)
        rc, out, err = run(capsys, "mdi", "G1 X1", "--socket", sock)
        assert rc == 7 and "controls the machine" in err and "hexacnc" in err       # names the holder
        rc, out, err = run(capsys, "jog", "z", "+0.1", "--socket", sock)
        assert rc == 7 and "not_controller" in err
        rc, out, err = run(capsys, "mdi", "G1 X1", "--take", "--socket", sock)
        assert rc == 7 and "running" in err and "[busy]" in err
        ev = a.next_message(2.0)                          # the previous controller is told
        assert ev and ev.get("event") == "control_taken"
        assert run(capsys, "stop", "--socket", sock)[0] == 0
    assert status(sock)["state"] == "idle"


def test_hold_resume_override_and_stop_from_the_cli(sock, capsys):
    with P.Client.unix(sock) as a:
        long_program(a, "hold")
        a.call("release")
        time.sleep(0.5)
        assert run(capsys, "pause", "--socket", sock)[0] == 0
        time.sleep(0.5)
        st = status(sock)
        assert st["state"] == "paused" and "paused" in st["why_idle"]
        assert run(capsys, "resume", "--socket", sock)[0] == 0
        rc, out, err = run(capsys, "feed", "50", "--socket", sock)
        assert rc == 0 and "feed 50 %" in out
        st = status(sock)
        assert st["overrides"]["feed"] == 0.5 and st["state"] == "running"
        assert st["progress"] == st["program"] and st["progress"]["name"] == "hold"
        assert st["block"].startswith("G1") and st["feed"]["programmed_mm_min"] == pytest.approx(120.0)
        rc, out, err = run(capsys, "feed", "180", "--socket", sock)   # over [planner] max_feed_override
        assert rc == 3 and "max_feed_override" in err
        rc, out, err = run(capsys, "feed", "250", "--socket", sock)
        assert rc == 3
        rc, out, err = run(capsys, "rapid", "150", "--socket", sock)
        assert rc == 3
        with pytest.raises(P.DaemonError) as ei:
            a.call("override", feed=2.5)
        assert ei.value.code == "bad_value"
        assert run(capsys, "stop", "--socket", sock)[0] == 0
        st = status(sock)
        assert st["state"] == "idle" and st["program"]["stopped"]
    run(capsys, "mdi", "G0 X0 Y0 Z30", "--socket", sock)


def test_disable_enable_and_home(sock, capsys):
    assert run(capsys, "disable", "--socket", sock)[0] == 0
    st = status(sock)
    assert not st["drives_enabled"] and "disabled" in st["why_idle"]
    rc, out, err = run(capsys, "jog", "z", "+0.1", "--socket", sock)
    assert rc == 7 and "disabled" in err
    assert run(capsys, "enable", "--socket", sock)[0] == 0
    assert status(sock)["drives_enabled"]
    rc, out, err = run(capsys, "home", "--socket", sock)
    assert rc == 0 and "referenced" in out
    assert status(sock)["referenced"] is True


def test_status_view_fits_80x24(sock, capsys):
    rc, out, err = run(capsys, "status", "--watch", "--count", "2", "--rate", "20", "--socket", sock)
    assert rc == 0
    frames = [f for f in out.split("\n\n") if f.strip()]
    assert len(frames) == 2
    for f in frames:
        lines = f.splitlines()
        assert len(lines) <= 24 and max(len(x) for x in lines) <= 80
        assert any(x.startswith("machine") for x in lines) and any("override" in x for x in lines)
    st = status(sock)
    for key in ("tool_tip", "work_offset", "tool", "feed", "overrides", "modal", "why_idle", "elapsed_s",
                "remaining_s", "message", "block", "progress", "controller"):
        assert key in st, key


def test_offsets_and_tools_survive_programs_and_a_restart(opcfg, sock, capsys):
    rc, out, err = run(capsys, "offsets", "G56", "x=1.5", "y=-2", "z=-1175", "--socket", sock)
    assert rc == 0 and "G56" in out
    rc, out, err = run(capsys, "tools", "7", "z=33.5", "d=6", "comment=6 mm drill", "--socket", sock)
    assert rc == 0 and "6 mm drill" in out
    assert run(capsys, "mdi", "G10 L2 P2 X0.5 Y0.5 Z-1180", "--socket", sock)[0] == 0
    with P.Client.unix(sock) as c:                 # G10 of one program is there for the next one
        c.call("program", text="G55 G0 X0 Y0 Z40\nM2\n", name="g55", reply_timeout_s=60.0)
        c.call("wait", timeout_s=30.0)
        st = c.call("status")
    assert st["work_offset"]["name"] == "G55"
    assert np.allclose(st["tool_tip"]["work"][:3], [0.0, 0.0, 40.0], atol=1e-6)
    with open(os.path.join(opcfg.operator.state_dir, "tool.tbl")) as fh:
        assert "T7 P7 Z33.500000 D6.000000 ;6 mm drill" in fh.read()
    # a second daemon on the same state directory starts from what the first one left (drives simulated in its
    # hot loop: a second simulated drives' process, SCHED_FIFO beside the first one's on the supervisor's
    # CPU, starved that one of its heartbeats in a CI run)
    d = tempfile.mkdtemp(prefix="hxop2", dir="/tmp")
    daemon = core.Daemon(opcfg, realtime=False, io_mode="inproc")
    try:
        srv = SocketServer(daemon, opcfg, os.path.join(d, "op2.sock")).start()
        try:
            rc, out, err = run(capsys, "offsets", "--json", "--socket", srv.socket_path)
            assert rc == 0
            import json
            r = json.loads(out)
            assert r["G56"][:3] == [1.5, -2.0, -1175.0] and r["G55"][:3] == [0.5, 0.5, -1180.0]
            assert r["active"] == "G55"
            rc, out, err = run(capsys, "tools", "--json", "--socket", srv.socket_path)
            assert any(t["tool"] == 7 and t["z_mm"] == 33.5 for t in json.loads(out)["tools"])
            rc, out, err = run(capsys, "tools", "7", "--delete", "--json", "--socket", srv.socket_path)
            assert rc == 0, err
            assert not any(t["tool"] == 7 for t in json.loads(out)["tools"])
        finally:
            srv.close()
    finally:
        daemon.close()
        shutil.rmtree(d, ignore_errors=True)
    assert run(capsys, "offsets", "--select", "G54", "--socket", sock)[0] == 0
    assert run(capsys, "mdi", "G0 X0 Y0 Z30", "--socket", sock)[0] == 0


def test_interactive_jog_in_a_terminal(sock):
    """``hexacnc jog --interactive`` in a pseudo-terminal: axis z, one step up, one down, quit."""
    import pty
    import subprocess
    import sys
    t0 = tip(sock)
    master, slave = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-m", "hexacnc.cli", "jog", "--interactive", "--step", "0.2",
                             "--socket", sock], stdin=slave, stdout=slave, stderr=slave, close_fds=True)
    os.close(slave)
    out = b""

    def read_for(s: float, until: bytes | None = None) -> None:
        nonlocal out
        end = time.monotonic() + s
        while time.monotonic() < end and not (until is not None and until in out):
            import select
            if select.select([master], [], [], 0.05)[0]:
                try:
                    out += os.read(master, 4096)
                except OSError:
                    return
    try:
        read_for(60.0, until=b"step 0.2")          # started and in cbreak mode (a loaded machine: slow)
        os.write(master, b"z")
        read_for(10.0, until=b"z base")
        os.write(master, b"+")
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            read_for(0.3)
            t1 = tip(sock)
            if abs(t1[2] - t0[2] - 0.2) < 1e-6:
                break
        os.write(master, b"q")
        assert proc.wait(20) == 0, out.decode(errors="replace")
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
    assert t1[2] - t0[2] == pytest.approx(0.2, abs=1e-6), out.decode(errors="replace")
    assert b"step 0.2" in out and b"tip" in out
    assert cli(["jog", "z", f"{t0[2] - t1[2]:+.6f}", "--socket", sock]) == 0
