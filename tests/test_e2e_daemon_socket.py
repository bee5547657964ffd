"""The socket server in front of the real daemon (hot loop process, simulated drives).

Needs only the daemon (not the G-code/planner path): motion comes from
``Daemon.move_to``, everything else goes over the socket.
"""
from __future__ import annotations

import math
import os
import random
import socket
import tempfile
import time

import numpy as np
import pytest

from hexacnc.daemon import protocol as P
from hexacnc.kinematics import Hexapod
from hexacnc import sag as sagmod

from hexacnc.daemon import core  # noqa: E402,F401  (a broken import fails the suite, never skips it)


from e2e_fixtures import cfg, machine, client  # noqa: E402,F401  (shared fixtures)
from e2e_fixtures import wait_standstill  # noqa: E402


pytestmark = pytest.mark.e2e


def _finite6(v):
    return isinstance(v, list) and len(v) == 6 and all(isinstance(x, float) and math.isfinite(x) for x in v)


def test_hello_and_status_contract_from_the_real_daemon(cfg, client):
    h = client.call("hello")
    assert h["machine"] == cfg.name and h["protocol"] == P.PROTOCOL_VERSION
    assert h["versions"]["hexacnc"] and h["versions"]["msgpack"]
    st = client.call("status")
    assert st["state"] == "idle" and st["fault"] is None
    for k in ("pose_cmd", "pose_act", "struts_cmd_mm", "struts_act_mm"):
        assert _finite6(st[k]), (k, st[k])
    assert isinstance(st["line"], int)
    cy = st["cycle"]
    assert cy["cycles"] > 0 and "p99" in cy["lateness_us"] and "overruns" in cy


def test_move_streamed_and_awaited_over_the_socket_ends_on_ik(cfg, machine, client):
    daemon, srv = machine
    hx = Hexapod(cfg)
    target = np.array([15.0, -10.0, -880.0, 3.0, -2.0, 4.0])
    sub = client.send("subscribe", rate_hz=100.0)
    daemon.move_to(target, 80.0, name="move")
    wid = client.send("wait", timeout_s=30.0)
    states, n = set(), 0
    lo, hi = cfg.min_length_mm, cfg.max_length_mm
    while True:
        m = client.next_message(40.0)
        assert m is not None
        if m.get("id") == sub and m.get("ok"):
            states.add(m["state"])
            s = np.asarray(m["struts_cmd_mm"])
            assert np.all(s >= lo) and np.all(s <= hi)
            n += 1
        elif m.get("id") == wid:
            break
    assert m["state"] == "idle" and m["timed_out"] is False
    assert "running" in states and n >= 3
    want = hx.lengths(target) + sagmod.sag_compensation_mm(hx, target)
    got = np.asarray(m["struts_cmd_mm"])
    assert np.max(np.abs(got - want)) <= 1.0 / cfg.bus.increments_per_mm, (got - want).tolist()
    np.testing.assert_allclose(m["pose_cmd"], target, atol=1e-6)
    # feedback follows: actual within the following-error limit of the command at rest
    time.sleep(0.1)
    st = client.call("status")
    assert np.max(np.abs(np.asarray(st["struts_act_mm"]) - np.asarray(st["struts_cmd_mm"]))) < 0.01
    # back home for the next test
    daemon.move_to(cfg.home_pose, 80.0, name="home")
    assert client.call("wait", timeout_s=30.0)["state"] == "idle"


def test_pause_resume_stop_over_the_socket(cfg, machine, client):
    daemon, srv = machine
    e = pytest.raises(P.DaemonError, client.call, "pause").value
    assert e.code in ("invalid_state", "refused")
    daemon.move_to([0.0, 0.0, -820.0, 0.0, 0.0, 0.0], 40.0, name="slow")
    time.sleep(0.2)
    client.call("pause")
    # decelerates along the path to rest (after the rows already queued to the loop)
    p1 = wait_standstill(client, timeout_s=3.0, polls=3)["pose_cmd"]   # still over 0.3 s, not one stalled poll
    time.sleep(0.2)
    st = client.call("status")
    assert st["state"] == "paused"
    assert st["pose_cmd"] == p1                               # held still while paused
    client.call("resume")
    assert client.call("status")["state"] in ("running", "idle")
    client.call("stop")
    st = client.call("wait", timeout_s=20.0)
    assert st["state"] == "idle" and st["fault"] is None
    assert st["pose_cmd"][2] > -900.0 and st["pose_cmd"][2] < -820.0 + 1e-6   # stopped on the path
    daemon.move_to(cfg.home_pose, 80.0, name="home")
    assert client.call("wait", timeout_s=30.0)["state"] == "idle"


def test_garbage_on_the_socket_does_not_disturb_a_running_move(cfg, machine, client):
    daemon, srv = machine
    hx = Hexapod(cfg)
    target = np.array([-20.0, 10.0, -930.0, -2.0, 3.0, -4.0])
    client.call("reset")          # a motion op (a no-op when idle): this client now controls motion
    daemon.move_to(target, 60.0, name="under-fire")
    rng = random.Random(7)
    for _ in range(40):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.connect(srv.socket_path)
        try:
            if rng.random() < 0.5:
                s.sendall(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 600))))
            else:
                s.sendall(P.encode({"id": rng.randrange(9), "op": rng.choice(["stop", "program", "reset", "x"]),
                                    "text": 5}))
                s.settimeout(2.0)
                dec = P.Decoder()
                dec.feed(s.recv(4096))
                r = next(dec.messages())
                assert r["ok"] is False
                assert r["error"]["code"] in ("not_controller", "bad_type", "unknown_op"), r
        except OSError:
            pass
        s.close()
    st = client.call("wait", timeout_s=30.0)
    assert st["state"] == "idle" and st["fault"] is None
    want = hx.lengths(target) + sagmod.sag_compensation_mm(hx, target)
    assert np.max(np.abs(np.asarray(st["struts_cmd_mm"]) - want)) <= 1.0 / cfg.bus.increments_per_mm
    daemon.move_to(cfg.home_pose, 80.0, name="home")
    assert client.call("wait", timeout_s=30.0)["state"] == "idle"


@pytest.mark.slow
def test_hexacnc_run_serves_status_to_hexacnc_status_processes(tmp_path):
    """Separate processes, as a user runs them: ``hexacnc run`` then ``hexacnc status``."""
    import json
    import signal
    import subprocess
    import sys
    sock = os.path.join(tempfile.mkdtemp(prefix="hxr", dir="/tmp"), "run.sock")   # a directory only we can write
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    run = subprocess.Popen([sys.executable, "-m", "hexacnc", "run", "--socket", sock, "--no-realtime",
                            "--duration", "60"], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 30.0
        while not os.path.exists(sock):
            assert run.poll() is None, run.stdout.read().decode(errors="replace")
            assert time.monotonic() < deadline, "hexacnc run did not open its socket"
            time.sleep(0.05)
        assert oct(os.stat(sock).st_mode & 0o777) == oct(0o660)
        r = subprocess.run([sys.executable, "-m", "hexacnc", "status", "--socket", sock, "--json"],
                           env=env, capture_output=True, text=True, timeout=30)
        assert r.returncode == 0, r.stderr
        st = json.loads(r.stdout)
        assert st["state"] in ("idle", "fault") and len(st["struts_cmd_mm"]) == 6
        r = subprocess.run([sys.executable, "-m", "hexacnc", "status", "--socket", sock + ".none"],
                           env=env, capture_output=True, text=True, timeout=30)
        assert r.returncode == 6
    finally:
        run.send_signal(signal.SIGTERM)
        try:
            out, _ = run.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            run.kill()
            out, _ = run.communicate()
    assert run.returncode == 0, out.decode(errors="replace")[-2000:]
    assert not os.path.exists(sock)          # removed on shutdown
