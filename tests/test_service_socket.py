"""Access control on the real socket server (fake daemon): squatting, world-writable directories,
wrong-owner sockets, observers, pre-auth floods, token brute force, oversized pre-auth input,
idle connections.  Each shows the refusal, its log line, and a legitimate controller still working.

Other users are real processes (``nobody``) started as root; without root those tests skip.
Everything listens on 127.0.0.1 or in a temporary directory.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os
import pwd
import resource
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import textwrap
import time

import msgpack
import pytest

from hexacnc.config import load_config
from hexacnc.daemon import protocol as P
from hexacnc.daemon import sockpath
from hexacnc.daemon.server import SocketServer

from test_protocol_fake import FakeDaemon

pytestmark = pytest.mark.e2e

ROOT = os.geteuid() == 0
needs_root = pytest.mark.skipif(not ROOT, reason="needs root to run a second user's process (nobody)")
TOKEN = secrets.token_hex(32)


def _nobody() -> tuple[int, int]:
    try:
        pw = pwd.getpwnam("nobody")
    except KeyError:
        pytest.skip("no user 'nobody' on this host")
    return pw.pw_uid, pw.pw_gid


class SensorFake(FakeDaemon):
    """The fake daemon plus a recorder of accepted temperature readings."""

    def __init__(self):
        super().__init__()
        self.readings = []

    def push_temperatures(self, fields):
        self.readings.append(fields)
        return {"accepted": True}


@pytest.fixture
def base_cfg():
    return load_config(None)


def cfg_with(cfg, **daemon):
    return cfg.replace(daemon=dataclasses.replace(cfg.daemon, **daemon))


@pytest.fixture
def sockdir():
    d = tempfile.mkdtemp(prefix="hxq", dir="/tmp")
    os.chmod(d, 0o755)                 # others may traverse (peer credentials decide), not write
    yield d
    shutil.rmtree(d, ignore_errors=True)


def _free_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


_CLIENT = textwrap.dedent(r'''
    import json, socket, sys, time
    path, reqs = sys.argv[1], json.loads(sys.argv[2])
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.connect(path)
    except OSError as e:
        print(json.dumps({"connect_error": str(e)})); sys.exit(0)
    out = []
    for req in reqs:                       # msgpack bytes (hex) made by the test; replies back as hex
        got = b""
        try:
            s.sendall(bytes.fromhex(req))
        except OSError:
            pass                           # refused at connect: the reason is still there to read
        try:
            s.settimeout(5)
            got = s.recv(65536)
            s.settimeout(0.2)
            while True:
                more = s.recv(65536)
                if not more:
                    break
                got += more
        except socket.timeout:
            pass
        except OSError:
            pass
        out.append(got.hex())
        if not got:
            break
    print(json.dumps(out))
''')


def _child_python() -> str:
    """An interpreter another user may run (the test's own may sit in a private home)."""
    uid, gid = _nobody()
    for exe in (sys.executable, "/usr/bin/python3", "/usr/local/bin/python3"):
        try:
            if subprocess.run([exe, "-c", ""], user=uid, group=gid, extra_groups=[], cwd="/",
                              capture_output=True, timeout=30).returncode == 0:
                return exe
        except OSError:
            continue
    pytest.skip("no Python interpreter that user nobody may run")


def _spawn_as_nobody(args: list, groups: tuple[int, ...] = (), **kw):
    uid, gid = _nobody()
    return subprocess.Popen([_child_python(), *args], user=uid, group=gid, extra_groups=list(groups),
                            env={"PATH": "/usr/bin:/bin"}, cwd="/", text=True, **kw)


def as_nobody(path: str, ops: list, groups: tuple[int, ...] = ()) -> list[dict]:
    """Run a client as user nobody: the replies to ``ops`` [(op, fields), ...]."""
    reqs = [msgpack.packb(dict(fields, id=i + 1, op=op), use_bin_type=True).hex() for i, (op, fields) in enumerate(ops)]
    p = _spawn_as_nobody(["-c", _CLIENT, path, json.dumps(reqs)], groups, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 0, err
    res = json.loads(out)
    assert isinstance(res, list), res
    replies = []
    for h in res:
        u = msgpack.Unpacker(raw=False)
        u.feed(bytes.fromhex(h))
        replies.extend(u)
    return replies


def _controller_works(path: str, daemon: FakeDaemon | None = None) -> None:
    with P.Client(sockpath.connect_checked(path, "hexacnc")) as c:
        h = c.call("hello", client="operator")
        assert h["access"] == "controller"
        assert c.call("status")["state"] in ("idle", "running")
        c.call("program", text="G1 X1\n", name="ok.ngc")
        assert c.call("wait", timeout_s=10)["state"] == "idle"


def _refusals(caplog, needle: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if needle in r.getMessage()]


# -- socket placement ---------------------------------------------------------------
_SQUATTER = textwrap.dedent(r'''
    import os, socket, sys, time
    d = sys.argv[1]
    os.mkdir(d, 0o755)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(os.path.join(d, "hexacnc.sock"))
    os.chmod(os.path.join(d, "hexacnc.sock"), 0o666)
    s.listen(4)
    print("ready", flush=True)
    s.settimeout(float(sys.argv[2]))
    got = 0
    try:
        while True:
            c, _ = s.accept()
            got += len(c.recv(65536))
    except socket.timeout:
        pass
    print("captured", got, flush=True)
''')


@needs_root
def test_a_second_user_squatting_the_default_path_is_refused(base_cfg, monkeypatch, caplog):
    uid, gid = _nobody()
    tmp = tempfile.mkdtemp(prefix="hxt", dir="/tmp")
    os.chmod(tmp, 0o1777)                  # a world-writable sticky temporary directory, like /tmp
    monkeypatch.setattr(tempfile, "tempdir", tmp)
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    path = sockpath.default_socket_path()
    assert path == os.path.join(tmp, f"hexacnc-{os.geteuid()}", "hexacnc.sock")
    squat = _spawn_as_nobody(["-c", _SQUATTER, os.path.dirname(path), "1"], stdout=subprocess.PIPE)
    try:
        assert squat.stdout.readline().strip() == "ready"
        assert os.stat(os.path.dirname(path)).st_uid == uid
        # the daemon refuses to serve in the squatted directory, and says so in its log
        d = FakeDaemon()
        caplog.set_level(logging.ERROR, logger="hexacnc.daemon.sockpath")
        with pytest.raises(sockpath.SocketTrustError, match=r"belongs to nobody .*someone else created it"):
            SocketServer(d, base_cfg, path).start()
        assert _refusals(caplog, f"refused socket path {path}")
        # the client refuses the impostor's socket before sending anything
        with pytest.raises(sockpath.SocketTrustError, match="belongs to nobody"):
            sockpath.connect_checked(path, "hexacnc")
        out, _ = squat.communicate(timeout=10)
        assert "captured 0" in out
        # a legitimate daemon elsewhere (here: $XDG_RUNTIME_DIR) serves its controller
        xdg = tempfile.mkdtemp(prefix="hxr", dir="/tmp")
        monkeypatch.setenv("XDG_RUNTIME_DIR", xdg)
        good = sockpath.default_socket_path()
        with SocketServer(d, base_cfg, good):
            _controller_works(good, d)
        d.close()
        shutil.rmtree(xdg, ignore_errors=True)
    finally:
        if squat.poll() is None:
            squat.kill()
            squat.wait()
        shutil.rmtree(tmp, ignore_errors=True)


def test_a_socket_in_a_world_writable_directory_is_refused(base_cfg, sockdir, caplog):
    bad = os.path.join(sockdir, "open")
    os.mkdir(bad)
    os.chmod(bad, 0o777)
    d = FakeDaemon()
    caplog.set_level(logging.ERROR, logger="hexacnc.daemon.sockpath")
    with pytest.raises(sockpath.SocketTrustError, match=r"writable by others \(mode 0777\)"):
        SocketServer(d, base_cfg, os.path.join(bad, "s.sock")).start()
    assert not os.path.exists(os.path.join(bad, "s.sock"))
    assert _refusals(caplog, "refused socket path")
    good = os.path.join(sockdir, "s.sock")
    with SocketServer(d, base_cfg, good):
        _controller_works(good, d)
    d.close()


@needs_root
def test_the_client_refuses_a_socket_owned_by_another_user(base_cfg, sockdir, capsys):
    from hexacnc.cli import main as cli_main
    uid, gid = _nobody()
    d = FakeDaemon()
    path = os.path.join(sockdir, "s.sock")
    with SocketServer(d, base_cfg, path) as srv:
        os.chown(path, uid, gid)                  # as if nobody had put it there
        with pytest.raises(sockpath.SocketTrustError, match=r"belongs to nobody .*impostor"):
            sockpath.connect_checked(path, "hexacnc")
        accepted = srv.stats["accepted"]
        rc = cli_main(["status", "--socket", path])
        err = capsys.readouterr().err
        assert rc == 6 and "belongs to nobody" in err, err
        assert srv.stats["accepted"] == accepted      # nothing was sent to it
        # the serving process is checked too: a client trusting only nobody refuses root's daemon
        os.chown(path, 0, 0)
        s = socket.socket(socket.AF_UNIX)
        s.connect(path)
        with pytest.raises(sockpath.SocketTrustError, match="runs as root"):
            sockpath.check_server_peer(s, {uid})
        s.close()
        assert cli_main(["status", "--socket", path]) == 0
        _controller_works(path, d)
    d.close()


# -- roles ---------------------------------------------------------------------------
@needs_root
def test_an_observer_may_read_but_not_send_temperatures(base_cfg, sockdir, caplog):
    uid, gid = _nobody()
    import grp
    gname = grp.getgrgid(gid).gr_name
    d = SensorFake()
    path = os.path.join(sockdir, "s.sock")
    caplog.set_level(logging.INFO, logger="hexacnc.daemon.access")
    reading = {"probes_C": [20.0] * 12}
    with SocketServer(d, cfg_with(base_cfg, observer_group=gname), path):
        out = as_nobody(path, [("hello", {}), ("status", {}), ("temperatures", reading),
                               ("program", {"text": "G1 X1\n", "name": "x"}), ("enable", {}), ("status", {})])
        assert out[0]["ok"] and out[0]["access"] == "observer"
        assert out[1]["ok"] and out[1]["access"] == "observer"
        for r in out[2:5]:
            assert r["ok"] is False and r["error"]["code"] == "unauthorized", r
        assert "controller or sensor" in out[2]["error"]["message"]
        assert out[5]["ok"]                        # refused ops do not cost the connection
        assert d.readings == [] and "load_program" not in d.calls
        lines = _refusals(caplog, "op temperatures")
        assert lines and f"uid {uid} (nobody) pid" in lines[0] and "observer" in lines[0]
        # the controller (the daemon's own user) still sends temperatures and runs programs
        with P.Client.unix(path) as c:
            assert c.call("temperatures", **reading)["ok"]
        assert len(d.readings) == 1
        _controller_works(path, d)
    # the same peer named as a sensor may send temperatures, still not motion
    with SocketServer(d, cfg_with(base_cfg, sensor_group=gname), path):
        out = as_nobody(path, [("hello", {}), ("temperatures", reading), ("reset", {})])
        assert out[0]["access"] == "sensor" and out[1]["ok"], out
        assert out[2]["error"]["code"] == "unauthorized"
        assert len(d.readings) == 2
    d.close()


@needs_root
def test_a_peer_in_no_configured_group_is_refused_at_connect(base_cfg, sockdir, caplog):
    uid, gid = _nobody()
    d = FakeDaemon()
    path = os.path.join(sockdir, "s.sock")
    caplog.set_level(logging.INFO, logger="hexacnc.daemon.access")
    with SocketServer(d, cfg_with(base_cfg, observer_group="root"), path) as srv:
        out = as_nobody(path, [("hello", {}), ("status", {})])
        assert out[0]["ok"] is False and out[0]["error"]["code"] == "unauthorized"
        assert "is not the daemon's user" in out[0]["error"]["message"]
        assert srv.stats["refused_peer"] == 1
        lines = _refusals(caplog, "op connect")
        assert lines and f"uid {uid} (nobody)" in lines[0] and "observer_group 'root'" in lines[0]
        _controller_works(path, d)
    d.close()


# -- TCP -------------------------------------------------------------------------------
@pytest.fixture
def tcp_served(base_cfg, sockdir):
    d = FakeDaemon()
    port = _free_port()
    srv = SocketServer(d, base_cfg, os.path.join(sockdir, "s.sock"), tcp_port=port, tcp_token=TOKEN).start()
    yield srv, d, port
    srv.close()
    d.close()


def _tcp_operator(port: int, source: str = "127.0.0.1") -> P.Client:
    s = socket.create_connection(("127.0.0.1", port), timeout=10, source_address=(source, 0))
    s.settimeout(None)
    c = P.Client(s)
    c.call("hello", token=TOKEN, client="operator", reply_timeout_s=10)
    return c


def test_weak_or_leaky_tokens_refuse_the_start(base_cfg, sockdir):
    d = FakeDaemon()
    with pytest.raises(Exception, match="too weak"):
        SocketServer(d, base_cfg, os.path.join(sockdir, "a.sock"), tcp_port=_free_port(), tcp_token="s3cret")
    tok = os.path.join(sockdir, "token")
    with open(tok, "w") as f:
        f.write(TOKEN)
    os.chmod(tok, 0o644)
    with pytest.raises(Exception, match="mode 0644"):
        SocketServer(d, cfg_with(base_cfg, token_file=tok), os.path.join(sockdir, "a.sock"), tcp_port=_free_port())
    os.chmod(tok, 0o600)
    port = _free_port()
    with SocketServer(d, cfg_with(base_cfg, token_file=tok), os.path.join(sockdir, "a.sock"), tcp_port=port):
        with _tcp_operator(port) as c:
            assert c.call("status")["access"] == "controller"
    d.close()


@pytest.mark.slow
def test_1000_idle_unauthenticated_connections_do_not_lock_the_operator_out(tcp_served, caplog):
    srv, d, port = tcp_served
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < 1200:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, 4096), hard))
    if resource.getrlimit(resource.RLIMIT_NOFILE)[0] < 1200:
        pytest.skip("cannot raise RLIMIT_NOFILE to 1200 for 1000 connections")
    caplog.set_level(logging.INFO, logger="hexacnc.daemon.access")
    idle = []
    try:
        for _ in range(1000):
            s = socket.socket()
            s.setblocking(False)
            s.connect_ex(("127.0.0.1", port))
            idle.append(s)
        time.sleep(0.5)
        t0 = time.monotonic()
        op = _tcp_operator(port)                    # the operator connects while they sit there
        took = time.monotonic() - t0
        assert op.call("status")["access"] == "controller"
        print(f"operator authenticated {took:.2f} s after 1000 idle connections")
        for _ in range(300):                        # more keep coming: the operator keeps its slot
            s = socket.socket()
            s.setblocking(False)
            s.connect_ex(("127.0.0.1", port))
            idle.append(s)
        time.sleep(0.5)
        assert op.call("status")["ok"]
        assert len(srv._preauth) <= srv.max_unauthenticated
        assert srv.stats["preauth_closed"] > 0 and srv.clients - len(srv._preauth) <= 2
        assert _refusals(caplog, "connections are waiting to authenticate")
        with P.Client.unix(srv.socket_path) as c:   # the Unix controller was never affected
            assert c.call("status")["ok"]
        op.close()
    finally:
        for s in idle:
            s.close()


@pytest.mark.slow
def test_token_brute_force_is_held_to_10_guesses_per_second(tcp_served, caplog):
    srv, d, port = tcp_served
    caplog.set_level(logging.INFO, logger="hexacnc.daemon.access")
    evaluated = throttled = attempts = 0
    t0 = time.monotonic()
    duration = 3.0
    while time.monotonic() - t0 < duration:
        attempts += 1
        try:
            s = socket.create_connection(("127.0.0.1", port), timeout=5)
            s.sendall(msgpack.packb({"id": 1, "op": "hello", "token": secrets.token_hex(32)}))
            reply = next(iter(_read_all(s)), None)
            s.close()
        except OSError:
            continue
        msg = (reply or {}).get("error", {}).get("message", "")
        if msg.startswith("wrong token"):
            evaluated += 1
        elif "too many failed authentications" in msg:
            throttled += 1
    rate = evaluated / duration
    print(f"brute force: {attempts} attempts in {duration:.0f} s, {evaluated} tokens compared "
          f"({rate:.1f}/s), {throttled} throttled")
    assert srv.stats["auth_failed"] == evaluated
    assert 1 <= evaluated and rate <= 10.0
    assert throttled > evaluated                  # the rest never reached a comparison
    assert _refusals(caplog, "op hello: wrong token") and _refusals(caplog, "too many failed")
    # the controller still works: on the Unix socket, and over TCP from another address
    with P.Client.unix(srv.socket_path) as c:
        assert c.call("status")["ok"]
    with _tcp_operator(port, source="127.0.0.2") as c:
        assert c.call("status")["access"] == "controller"


def _read_all(s: socket.socket, timeout: float = 5.0):
    u = msgpack.Unpacker(raw=False)
    s.settimeout(timeout)
    while True:
        try:
            data = s.recv(65536)
        except (socket.timeout, ConnectionResetError):
            break
        if not data:
            break
        u.feed(data)
    return list(u)


def test_an_oversized_pre_auth_message_is_refused_after_1_kib(tcp_served, caplog):
    srv, d, port = tcp_served
    caplog.set_level(logging.INFO, logger="hexacnc.daemon.access")
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    big = msgpack.packb({"id": 1, "op": "hello", "client": "x" * 200_000, "token": TOKEN})
    try:
        s.sendall(big)
    except OSError:
        pass                                       # the daemon may close before all is sent
    replies = _read_all(s)
    s.close()
    assert replies and replies[0]["error"]["code"] == "too_large"
    assert "more than 1024 bytes before authentication" in replies[0]["error"]["message"]
    assert srv.stats["preauth_closed"] == 1 and srv.stats["auth_failed"] == 0
    assert _refusals(caplog, "op hello: more than 1024 bytes")
    with _tcp_operator(port) as c:                 # a controller with the token gets in right after
        assert c.call("status")["ok"]


# -- idle connections ------------------------------------------------------------------------
@pytest.mark.slow
def test_idle_connections_are_closed_but_not_while_subscribed(base_cfg, sockdir, caplog):
    d = FakeDaemon()
    path = os.path.join(sockdir, "s.sock")
    caplog.set_level(logging.INFO, logger="hexacnc.daemon.server")
    with SocketServer(d, cfg_with(base_cfg, idle_timeout_s=1.0), path) as srv:
        idle = P.Client.unix(path)
        idle.call("hello")
        sub = P.Client.unix(path)
        sub.call("subscribe", rate_hz=2.0)
        time.sleep(2.5)
        msg = idle.next_message(timeout_s=1.0)
        assert msg is not None and msg["ok"] is False and "idle_timeout_s" in msg["error"]["message"]
        with pytest.raises(P.ConnectionLost):
            idle.call("status", reply_timeout_s=2.0)
        assert sub.call("status")["ok"]            # its stream kept it open
        assert srv.stats["idle_closed"] == 1
        assert _refusals(caplog, "([daemon] idle_timeout_s 1); closing")
        _controller_works(path, d)
        sub.close()
    d.close()


def test_a_legacy_tcp_token_in_a_readable_config_file_refuses_the_start(sockdir):
    base = open(os.path.join(os.path.dirname(__file__), "..", "config", "default.toml")).read()
    p = os.path.join(sockdir, "m.toml")
    port = _free_port()
    with open(p, "w") as f:
        f.write(base.replace("[daemon]\n", f'[daemon]\ntcp_port = {port}\ntcp_token = "{TOKEN}"\n'))
    os.chmod(p, 0o644)
    cfg = load_config(p)
    d = FakeDaemon()
    with pytest.raises(Exception, match=r"holds \[daemon\] tcp_token but has mode 0644"):
        SocketServer(d, cfg, os.path.join(sockdir, "a.sock"))
    os.chmod(p, 0o600)
    with SocketServer(d, cfg, os.path.join(sockdir, "a.sock")):
        with _tcp_operator(port) as c:
            assert c.call("status")["ok"]
    d.close()


def test_hexacnc_run_refuses_a_world_writable_socket_directory_before_booting(sockdir):
    bad = os.path.join(sockdir, "open")
    os.mkdir(bad)
    os.chmod(bad, 0o777)
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    r = subprocess.run([sys.executable, "-m", "hexacnc", "run", "--socket", os.path.join(bad, "s.sock"),
                        "--no-realtime", "--duration", "1"], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode != 0
    assert "refused socket path" in r.stderr and "writable by others (mode 0777)" in r.stderr
    assert "hot loop" not in r.stderr and "daemon ready" not in r.stderr     # no drive was booted
