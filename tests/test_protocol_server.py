"""Socket server against a fake daemon: every op, errors, controller rules, bad frames, limits, TCP token."""
from __future__ import annotations

import math
import os
import shutil
import socket
import stat
import tempfile
import threading
import time

import msgpack
import pytest

from hexacnc.config import load_config
from hexacnc.daemon import protocol as P
from hexacnc.daemon.server import SocketServer
from hexacnc.errors import HexacncError

from test_protocol_fake import FakeDaemon


pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


@pytest.fixture
def sockdir():
    d = tempfile.mkdtemp(prefix="hxp", dir="/tmp")
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def served(cfg, sockdir):
    d = FakeDaemon()
    srv = SocketServer(d, cfg, os.path.join(sockdir, "s.sock"))
    srv.start()
    yield srv, d
    srv.close()
    d.close()


class Raw:
    """A bare socket client that sends arbitrary objects/bytes and reads replies."""

    def __init__(self, path=None, tcp=None):
        if tcp is not None:
            self.s = socket.create_connection(tcp, timeout=5)
        else:
            self.s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            self.s.settimeout(5)
            self.s.connect(path)
        self.u = msgpack.Unpacker(raw=False)
        self.buf = []
        self.n = 0

    def send_obj(self, obj):
        self.s.sendall(msgpack.packb(obj, use_bin_type=True))

    def send_bytes(self, b):
        self.s.sendall(b)

    def recv(self, timeout=5.0):
        deadline = time.monotonic() + timeout
        while not self.buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no message")
            self.s.settimeout(left)
            data = self.s.recv(65536)
            if not data:
                raise ConnectionError("closed")
            self.u.feed(data)
            self.buf.extend(self.u)
        return self.buf.pop(0)

    def req(self, op, **f):
        self.n += 1
        rid = 1000 + self.n
        msg = {"id": rid, "op": op}
        msg.update(f)
        self.send_obj(msg)
        keep = []
        while True:
            m = self.recv()
            if isinstance(m, dict) and m.get("id") == rid and "stream" not in m:
                self.buf[:0] = [k for k in keep if "stream" not in k]   # other replies stay readable
                return m
            keep.append(m)

    def closed_within(self, timeout=3.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.s.settimeout(max(0.01, deadline - time.monotonic()))
            try:
                data = self.s.recv(65536)
            except socket.timeout:
                return False
            except ConnectionResetError:
                return True
            if not data:
                return True
        return False

    def close(self):
        self.s.close()


def _err(reply):
    assert reply["ok"] is False, reply
    e = reply["error"]
    assert set(e) >= {"code", "message", "line"}
    assert isinstance(e["code"], str) and isinstance(e["message"], str) and e["message"]
    assert e["line"] is None or isinstance(e["line"], int)
    return e


# -- ops ----------------------------------------------------------------------
def test_hello_reports_versions_and_machine(served):
    srv, d = served
    c = Raw(srv.socket_path)
    r = c.req("hello")
    assert r["ok"] is True and r["id"] == 1001
    assert r["protocol"] == P.PROTOCOL_VERSION
    assert r["machine"] == "fake-hexapod"
    assert "hexacnc" in r["versions"] and "msgpack" in r["versions"]
    assert r["role"] == "observer"


def test_status_has_the_contract_fields(served):
    srv, d = served
    r = Raw(srv.socket_path).req("status")
    assert r["ok"] is True
    assert r["state"] in P.STATES
    for k in ("pose_cmd", "pose_act", "struts_cmd_mm", "struts_act_mm"):
        assert isinstance(r[k], list) and len(r[k]) == 6 and all(isinstance(x, float) for x in r[k]), k
    assert "line" in r and "fault" in r and isinstance(r["cycle"], dict)
    assert math.isnan(r["cycle"]["lateness_us"]["p99"])   # numbers pass through, NaN included


def test_program_runs_and_wait_returns_when_idle(served):
    srv, d = served
    c = Raw(srv.socket_path)
    r = c.req("program", text="G0 X1\nG1 X2\nG1 X3\n", name="three")
    assert r["ok"] and r["blocks"] == 3 and r["name"] == "three"
    w = c.req("wait", timeout_s=10.0)
    assert w["ok"] and w["timed_out"] is False and w["state"] == "idle"
    assert w["result"] == "finished"
    assert c.req("status")["struts_cmd_mm"] == [1003.0] * 6


@pytest.mark.parametrize("text,code,line", [
    ("G0 X1\nG1 BAD\nG1 X3\n", "gcode", 2),
    ("G0 X1\n\nG1 X2\nUNSUP\n", "unsupported", 4),
    ("G0 X1\nG0 FAR\n", "limit", 2),
])
def test_refused_program_names_line_and_code_before_motion(served, text, code, line):
    srv, d = served
    c = Raw(srv.socket_path)
    r = c.req("program", text=text, name="bad")
    e = _err(r)
    assert e["code"] == code and e["line"] == line
    assert f"line {line}" in e["message"]
    if code == "limit":
        assert e["limit"] == "strut_length"
    else:
        assert isinstance(e["column"], int)
    st = c.req("status")
    assert st["state"] == "idle" and st["struts_cmd_mm"] == [1000.0] * 6   # nothing moved


def test_pause_resume_stop(served):
    srv, d = served
    d.block_s = 0.05
    c = Raw(srv.socket_path)
    assert c.req("program", text="G1 X1\n" * 100, name="long")["ok"]
    assert c.req("pause")["ok"]
    assert c.req("status")["state"] == "paused"
    assert c.req("resume")["ok"]
    assert c.req("status")["state"] == "running"
    assert c.req("stop")["ok"]
    w = c.req("wait", timeout_s=5.0)
    assert w["state"] == "idle" and w["result"] == "stopped"
    assert d.calls == ["load_program", "pause", "resume", "stop"]


def test_fault_then_reset(served):
    srv, d = served
    c = Raw(srv.socket_path)
    assert c.req("program", text="G1 X1\nG1 FAULT\nG1 X3\n", name="f")["ok"]
    w = c.req("wait", timeout_s=5.0)
    assert w["state"] == "fault" and "following error" in w["fault"]
    e = _err(c.req("program", text="G1 X1\n", name="g"))
    assert e["code"] == "fault"
    assert c.req("reset")["ok"]
    assert c.req("status")["state"] == "idle"
    assert c.req("program", text="G1 X1\n", name="g")["ok"]


def test_program_while_running_is_busy(served):
    srv, d = served
    d.block_s = 0.05
    c = Raw(srv.socket_path)
    assert c.req("program", text="G1 X1\n" * 50, name="a")["ok"]
    assert _err(c.req("program", text="G1 X1\n", name="b"))["code"] == "busy"
    c.req("stop")


def test_wait_does_not_block_other_clients_and_times_out(served):
    srv, d = served
    d.block_s = 0.05
    a, b = Raw(srv.socket_path), Raw(srv.socket_path)
    assert a.req("program", text="G1 X1\n" * 100, name="long")["ok"]
    a.send_obj({"id": 77, "op": "wait", "timeout_s": 30.0})
    t0 = time.monotonic()
    st = b.req("status")
    assert st["state"] == "running" and time.monotonic() - t0 < 0.5
    w = b.req("wait", timeout_s=0.1)
    assert w["ok"] and w["timed_out"] is True and w["state"] == "running"
    # the waiting client itself can still ask for status while its wait is pending
    assert a.req("status")["ok"]
    a.req("stop")
    w = a.recv(5.0)
    assert w["id"] == 77
    assert w["state"] == "idle" and w["timed_out"] is False


def test_slow_program_load_does_not_stall_observers(served):
    srv, d = served
    a, b = Raw(srv.socket_path), Raw(srv.socket_path)
    a.send_obj({"id": 1, "op": "program", "text": "SLOWLOAD\nG1 X1\n", "name": "slow"})
    time.sleep(0.05)
    t0 = time.monotonic()
    assert b.req("status")["ok"]
    assert time.monotonic() - t0 < 0.3
    assert a.recv(5.0)["ok"]
    assert not any("socket" in n for n in d.load_threads)   # parsed off the selector thread


def test_subscribe_streams_until_unsubscribe(served):
    srv, d = served
    c = Raw(srv.socket_path)
    first = c.req("subscribe", rate_hz=50.0)
    assert first["ok"] and first["sub"] == first["id"] and first["rate_hz"] == 50.0 and "state" in first
    t0 = time.monotonic()
    msgs = [c.recv(2.0) for _ in range(10)]
    dt = time.monotonic() - t0
    assert all(m["stream"] == "status" and m["id"] == first["id"] and "pose_cmd" in m for m in msgs)
    assert [m["seq"] for m in msgs] == list(range(1, 11))
    assert 0.1 < dt < 1.0          # 10 samples at 50 Hz ~ 0.2 s
    r = c.req("unsubscribe")
    assert r["cancelled"] == [first["id"]]
    with pytest.raises(TimeoutError):
        c.recv(0.3)


def test_subscribe_default_rate_is_config(served, cfg):
    srv, d = served
    first = Raw(srv.socket_path).req("subscribe")
    assert first["rate_hz"] == cfg.daemon.status_rate_hz


# -- controller / observer ----------------------------------------------------
def test_one_controller_many_observers(served):
    srv, d = served
    d.block_s = 0.05
    a, b, c = Raw(srv.socket_path), Raw(srv.socket_path), Raw(srv.socket_path)
    assert a.req("program", text="G1 X1\n" * 100, name="p")["ok"]
    for op in ("pause", "resume", "stop", "reset"):
        assert _err(b.req(op))["code"] == "not_controller"
    assert _err(c.req("program", text="G1 X1\n", name="q"))["code"] == "not_controller"
    assert b.req("status")["ok"] and c.req("hello")["role"] == "observer"
    assert a.req("hello")["role"] == "controller"
    assert d.calls == ["load_program"]          # refused ops never reached the daemon
    a.close()
    time.sleep(0.1)
    assert b.req("stop")["ok"]                  # control passes on when the controller leaves
    assert _err(c.req("stop"))["code"] == "not_controller"
    assert b.req("release")["released"] is True
    assert c.req("stop")["ok"]


# -- bad input ----------------------------------------------------------------
@pytest.mark.parametrize("msg,code", [
    ([1, 2, 3], "bad_request"),
    (42, "bad_request"),
    ("status", "bad_request"),
    ({"op": "status"}, "missing_field"),
    ({"id": 5}, "missing_field"),
    ({"id": "5", "op": "status"}, "bad_type"),
    ({"id": True, "op": "status"}, "bad_type"),
    ({"id": 1.5, "op": "status"}, "bad_type"),
    ({"id": 5, "op": 3}, "bad_type"),
    ({"id": 5, "op": "fly"}, "unknown_op"),
    ({"id": 5, "op": ""}, "unknown_op"),
    ({"id": 5, "op": "program", "name": "x"}, "missing_field"),
    ({"id": 5, "op": "program", "text": "G0 X1"}, "missing_field"),
    ({"id": 5, "op": "program", "text": b"G0 X1", "name": "x"}, "bad_type"),
    ({"id": 5, "op": "program", "text": 12, "name": "x"}, "bad_type"),
    ({"id": 5, "op": "program", "text": "G0", "name": None}, "bad_type"),
    ({"id": 5, "op": "wait"}, "missing_field"),
    ({"id": 5, "op": "wait", "timeout_s": "1"}, "bad_type"),
    ({"id": 5, "op": "wait", "timeout_s": -1.0}, "bad_value"),
    ({"id": 5, "op": "wait", "timeout_s": float("nan")}, "bad_value"),
    ({"id": 5, "op": "subscribe", "rate_hz": 0.0}, "bad_value"),
    ({"id": 5, "op": "subscribe", "rate_hz": [1]}, "bad_type"),
])
def test_bad_requests_get_error_replies_and_the_connection_lives(served, msg, code):
    srv, d = served
    c = Raw(srv.socket_path)
    c.send_obj(msg)
    r = c.recv()
    e = _err(r)
    assert e["code"] == code, e
    assert r["id"] == (msg["id"] if isinstance(msg, dict) and type(msg.get("id")) is int else None)
    assert c.req("status")["ok"]          # same connection still served
    assert d.calls == []                  # nothing reached the daemon's motion API


def test_extra_fields_are_ignored(served):
    srv, d = served
    c = Raw(srv.socket_path)
    assert c.req("status", future_field=[1, 2])["ok"]
    c.send_obj({"id": 8, "op": "status", 5: "int key", b"k": "bin key"})
    assert c.recv()["ok"] is True


def test_binary_keys_are_not_field_names(served):
    srv, d = served
    c = Raw(srv.socket_path)
    c.send_obj({b"id": 1, b"op": b"status"})
    r = c.recv()
    assert _err(r)["code"] == "missing_field" and r["id"] is None
    c.send_obj({"id": 2, "op": b"status"})
    assert _err(c.recv())["code"] == "bad_type"
    assert c.req("status")["ok"]


def test_undecodable_bytes_close_only_that_connection(served):
    srv, d = served
    good = Raw(srv.socket_path)
    good.req("subscribe", rate_hz=20.0)
    bad = Raw(srv.socket_path)
    bad.send_bytes(b"\x81\xa2id\x01" + b"\xc1garbage")
    assert bad.closed_within(3.0)
    bad2 = Raw(srv.socket_path)
    bad2.send_bytes(b"\xa3\xff\xfe\xfd")            # str with invalid UTF-8
    assert bad2.closed_within(3.0)
    bad3 = Raw(srv.socket_path)
    bad3.send_bytes(b"\x81\x91\x01\x02")            # map with an array as key: no Python map
    assert bad3.closed_within(3.0)
    assert good.req("status")["ok"]
    assert good.recv(1.0)["stream"] == "status"     # its stream keeps flowing
    assert Raw(srv.socket_path).req("hello")["ok"]  # and new clients are accepted


def test_message_size_limit(cfg, sockdir):
    d = FakeDaemon()
    with SocketServer(d, cfg, os.path.join(sockdir, "s.sock"), max_message_bytes=4096) as srv:
        c = Raw(srv.socket_path)
        c.send_obj({"id": 1, "op": "program", "text": "G1 X1\n" * 2000, "name": "big"})
        r = c.recv()
        assert _err(r)["code"] == "too_large"
        assert c.closed_within(3.0)
        assert Raw(srv.socket_path).req("status")["ok"]
        assert d.calls == []
    d.close()


def test_client_count_limit(cfg, sockdir):
    d = FakeDaemon()
    with SocketServer(d, cfg, os.path.join(sockdir, "s.sock"), max_clients=2) as srv:
        a, b = Raw(srv.socket_path), Raw(srv.socket_path)
        assert a.req("status")["ok"] and b.req("status")["ok"]
        c = Raw(srv.socket_path)
        assert _err(c.recv())["code"] == "busy"
        assert c.closed_within(3.0)
        a.close()
        time.sleep(0.1)
        assert Raw(srv.socket_path).req("status")["ok"]
    d.close()


def test_client_leaving_mid_request_is_harmless(served):
    srv, d = served
    d.block_s = 0.05
    a = Raw(srv.socket_path)
    a.req("program", text="G1 X1\n" * 20, name="p")
    a.send_obj({"id": 9, "op": "wait", "timeout_s": 30.0})
    a.send_obj({"id": 10, "op": "subscribe"})
    a.close()
    b = Raw(srv.socket_path)
    w = b.req("wait", timeout_s=10.0)
    assert w["state"] == "idle" and w["result"] == "finished"   # the program was not disturbed
    time.sleep(0.3)
    assert srv.clients == 1


# -- socket file --------------------------------------------------------------
def test_socket_mode_stale_file_and_live_daemon(cfg, sockdir):
    path = os.path.join(sockdir, "s.sock")
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(path)
    stale.close()                                   # leaves a dead socket file
    d = FakeDaemon()
    srv = SocketServer(d, cfg, path).start()
    try:
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o660
        with pytest.raises(HexacncError, match="another daemon"):
            SocketServer(FakeDaemon(), cfg, path).start()
        assert Raw(path).req("status")["ok"]        # the first one is untouched
    finally:
        srv.close()
        d.close()
    assert not os.path.exists(path)


def test_refuses_to_replace_a_regular_file(cfg, sockdir):
    path = os.path.join(sockdir, "notasocket")
    with open(path, "w") as fh:
        fh.write("keep me")
    with pytest.raises(HexacncError, match="not a socket"):
        SocketServer(FakeDaemon(), cfg, path).start()
    assert open(path).read() == "keep me"


# -- TCP ----------------------------------------------------------------------
def _free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    p = s.getsockname()[1]
    s.close()
    return p


def test_no_tcp_unless_configured(served):
    srv, d = served
    assert srv.tcp_address is None


_TOKEN = "9f3c1b7e2a6d4c8b0e5f7a1d3b9c2e4f"  # 128 bits


def test_tcp_needs_token_and_listens_on_loopback_only(cfg, sockdir):
    d = FakeDaemon()
    port = _free_port()
    with SocketServer(d, cfg, os.path.join(sockdir, "s.sock"), tcp_port=port, tcp_token=_TOKEN) as srv:
        assert srv.tcp_address == ("127.0.0.1", port)
        # first message not hello
        c = Raw(tcp=("127.0.0.1", port))
        c.send_obj({"id": 1, "op": "status"})
        assert _err(c.recv())["code"] == "unauthorized"
        assert c.closed_within(3.0)
        # wrong token
        c = Raw(tcp=("127.0.0.1", port))
        c.send_obj({"id": 1, "op": "hello", "token": "guess"})
        assert _err(c.recv())["code"] == "unauthorized"
        assert c.closed_within(3.0)
        time.sleep(0.15)                 # the 0.1 s back-off the wrong token earned this address
        # malformed first message also closes
        c = Raw(tcp=("127.0.0.1", port))
        c.send_obj({"op": "hello"})
        assert _err(c.recv())["code"] == "missing_field"
        assert c.closed_within(3.0)
        # right token
        c = Raw(tcp=("127.0.0.1", port))
        assert c.req("hello", token=_TOKEN)["ok"]
        assert c.req("status")["ok"]
        cl = P.Client.tcp(port, _TOKEN)
        assert cl.call("status")["state"] == "idle"
        cl.close()
        with pytest.raises(P.DaemonError):
            P.Client.tcp(port, "nope")
        # a silent TCP client does not hold a slot for ever
        srv.auth_timeout_s = 0.3
        c = Raw(tcp=("127.0.0.1", port))
        assert _err(c.recv(3.0))["code"] == "unauthorized"
        assert c.closed_within(3.0)
    d.close()


def test_client_class_roundtrip(served):
    srv, d = served
    with P.Client.unix(srv.socket_path) as cl:
        assert cl.call("hello")["ok"]
        r = cl.call("program", text="G1 X1\nG1 X2\n", name="c")
        assert r["blocks"] == 2
        assert cl.call("wait", timeout_s=5.0)["state"] == "idle"
        with pytest.raises(P.DaemonError) as ei:
            cl.call("program", text="BAD\n", name="c")
        assert ei.value.code == "gcode" and ei.value.line == 1
    with pytest.raises(P.ConnectionLost):
        P.Client.unix(os.path.join(os.path.dirname(srv.socket_path), "nothing.sock"))


def test_wait_sent_right_after_program_covers_that_program(served):
    """Pipelined program + wait: the wait must not return 'idle' before the program was even loaded."""
    srv, d = served
    a, b = Raw(srv.socket_path), Raw(srv.socket_path)
    a.send_obj({"id": 1, "op": "program", "text": "SLOWLOAD\n" + "G1 X1\n" * 10, "name": "slow"})
    a.send_obj({"id": 2, "op": "wait", "timeout_s": 20.0})
    time.sleep(0.05)
    b.send_obj({"id": 3, "op": "wait", "timeout_s": 20.0})      # an observer's wait as well
    got = {m["id"]: m for m in (a.recv(10.0), a.recv(10.0))}
    assert got[1]["ok"] and got[1]["blocks"] == 11
    assert got[2]["state"] == "idle" and got[2]["result"] == "finished" and got[2]["timed_out"] is False
    w = b.recv(10.0)
    assert w["result"] == "finished"


def test_per_client_subscription_cap(served):
    srv, d = served
    c = Raw(srv.socket_path)
    for i in range(8):
        assert c.req("subscribe", rate_hz=1.0)["ok"]
    assert _err(c.req("subscribe", rate_hz=1.0))["code"] == "busy"
    assert c.req("unsubscribe")["ok"]
    assert c.req("subscribe", rate_hz=1.0)["ok"]


def test_motion_op_flood_is_bounded(served, monkeypatch):
    srv, d = served
    c = Raw(srv.socket_path)
    reset = d.reset

    def slow_reset():           # each reset takes 20 ms: a flood of them outpaces the (one) control worker
        time.sleep(0.02)        # however fast this machine is (resets do not wait behind the program's load)
        return reset()
    monkeypatch.setattr(d, "reset", slow_reset)
    c.send_obj({"id": 0, "op": "program", "text": "SLOWLOAD\nG1 X1\n", "name": "slow"})
    for i in range(1, 200):
        c.send_obj({"id": i, "op": "reset"})
    replies = [c.recv(10.0) for _ in range(200)]
    codes = [r["error"]["code"] for r in replies if not r["ok"]]
    assert codes and set(codes) == {"busy"}
    assert sum(r["ok"] for r in replies) >= 64
    assert c.req("status")["ok"]


def test_pipelined_flood_is_answered_completely_and_fairly(served):
    srv, d = served
    a, b = Raw(srv.socket_path), Raw(srv.socket_path)
    n = 3000
    a.send_bytes(b"".join(msgpack.packb({"id": i, "op": "status"}) for i in range(n)))
    t0 = time.monotonic()
    assert b.req("status")["ok"] and time.monotonic() - t0 < 1.0
    ids = [a.recv(10.0)["id"] for _ in range(n)]
    assert ids == list(range(n))            # every request answered once, in order
