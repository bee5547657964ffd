"""``hexacnc send`` and ``hexacnc status`` against a fake daemon: exit codes and output."""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import threading
import time

import pytest

from hexacnc.cli import main as cli
from hexacnc.config import load_config
from hexacnc.daemon import protocol as P
from hexacnc.daemon.server import SocketServer

from test_protocol_fake import FakeDaemon


pytestmark = pytest.mark.e2e


@pytest.fixture
def env():
    cfg = load_config(None)
    d = tempfile.mkdtemp(prefix="hxc", dir="/tmp")
    daemon = FakeDaemon(block_s=0.01)
    srv = SocketServer(daemon, cfg, os.path.join(d, "s.sock"))
    srv.start()
    yield srv, daemon, d
    srv.close()
    daemon.close()
    shutil.rmtree(d, ignore_errors=True)


def _prog(d, text, name="p.ngc"):
    p = os.path.join(d, name)
    with open(p, "w") as fh:
        fh.write(text)
    return p


def test_send_finishes_with_exit_0(env, capsys):
    srv, daemon, d = env
    rc = cli(["send", _prog(d, "G1 X1\n" * 20), "--socket", srv.socket_path])
    out = capsys.readouterr()
    assert rc == 0, out
    assert "20 blocks" in out.out and "finished" in out.out
    assert "%" in out.out and "line" in out.out          # progress lines (not a TTY: plain lines)
    assert daemon.status()["result"] == "finished"


def test_send_no_wait_returns_once_queued(env, capsys):
    srv, daemon, d = env
    daemon.block_s = 0.05
    rc = cli(["send", _prog(d, "G1 X1\n" * 40), "--socket", srv.socket_path, "--no-wait"])
    assert rc == 0
    assert daemon.status()["state"] == "running"
    daemon.stop()


@pytest.mark.parametrize("text,code,line", [
    ("G1 X1\nG1 X2\nG1 BAD\n", "gcode", 3),
    ("G1 X1\nG1 FAR\n", "limit", 2),
])
def test_send_refused_program_prints_line_and_exits_3(env, capsys, text, code, line):
    srv, daemon, d = env
    path = _prog(d, text)
    rc = cli(["send", path, "--socket", srv.socket_path])
    err = capsys.readouterr().err
    assert rc == 3
    assert f"{path}:{line}" in err and f"[{code}]" in err
    assert daemon.calls == ["load_program"] and daemon.status()["state"] == "idle"


def test_send_fault_exits_4(env, capsys):
    srv, daemon, d = env
    rc = cli(["send", _prog(d, "G1 X1\nG1 X2\nG1 FAULT\nG1 X4\n"), "--socket", srv.socket_path])
    err = capsys.readouterr().err
    assert rc == 4 and "fault" in err and "following error" in err


def test_send_stopped_exits_5(env, capsys):
    srv, daemon, d = env
    daemon.block_s = 0.05
    threading.Timer(0.3, daemon.stop).start()         # e.g. the stop button of the machine
    rc = cli(["send", _prog(d, "G1 X1\n" * 100), "--socket", srv.socket_path])
    err = capsys.readouterr().err
    assert rc == 5 and "stopped" in err


def test_send_connection_error_exits_6(env, capsys):
    srv, daemon, d = env
    rc = cli(["send", _prog(d, "G1 X1\n"), "--socket", os.path.join(d, "none.sock")])
    assert rc == 6 and "cannot connect" in capsys.readouterr().err


def test_send_other_controller_exits_7(env, capsys):
    srv, daemon, d = env
    holder = P.Client.unix(srv.socket_path)
    holder.call("stop")                                # becomes controller
    rc = cli(["send", _prog(d, "G1 X1\n"), "--socket", srv.socket_path])
    assert rc == 7 and "not_controller" in capsys.readouterr().err
    holder.close()


def test_send_unreadable_file_exits_2(env, capsys):
    srv, daemon, d = env
    assert cli(["send", os.path.join(d, "missing.ngc"), "--socket", srv.socket_path]) == 2
    p = os.path.join(d, "bin.ngc")
    with open(p, "wb") as fh:
        fh.write(b"G1 X1\n\xff\xfe\n")
    assert cli(["send", p, "--socket", srv.socket_path]) == 2
    assert "bin.ngc:2" in capsys.readouterr().err


def test_status_json_and_text(env, capsys):
    srv, daemon, d = env
    assert cli(["status", "--socket", srv.socket_path, "--json"]) == 0
    st = json.loads(capsys.readouterr().out)
    assert st["state"] == "idle" and len(st["pose_cmd"]) == 6 and st["cycle"]["lateness_us"]["p99"] is None
    assert "ok" not in st and "id" not in st
    assert cli(["status", "--socket", srv.socket_path]) == 0
    out = capsys.readouterr().out
    assert "state      idle" in out and "struts_cmd" in out


def test_status_watch_json_lines(env, capsys):
    srv, daemon, d = env
    t0 = time.monotonic()
    assert cli(["status", "--socket", srv.socket_path, "--watch", "--json", "--count", "4", "--rate", "20"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4 and all(json.loads(x)["state"] == "idle" for x in lines)
    assert time.monotonic() - t0 > 0.1


def test_status_connection_error_exits_6(env, capsys):
    srv, daemon, d = env
    assert cli(["status", "--socket", os.path.join(d, "none.sock")]) == 6


def test_send_reports_a_pause_and_finishes_after_resume(env, capsys):
    srv, daemon, d = env
    daemon.block_s = 0.03
    threading.Timer(0.2, daemon.pause).start()
    threading.Timer(0.8, daemon.resume).start()
    rc = cli(["send", _prog(d, "G1 X1\n" * 30), "--socket", srv.socket_path])
    out = capsys.readouterr()
    assert rc == 0, out
    assert "paused at line" in out.err and "finished" in out.out
