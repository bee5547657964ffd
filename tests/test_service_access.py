"""Access-control building blocks without sockets: token strength and files, the per-address
back-off, roles from peer credentials, socket-directory checks, default socket paths, config keys."""
from __future__ import annotations

import os
import secrets
import shutil
import stat
import tempfile

import pytest

from hexacnc.config import load_config
from hexacnc.daemon import access as A
from hexacnc.daemon import sockpath, tcpauth
from hexacnc.errors import ConfigError, HexacncError


@pytest.fixture
def tmpdir_():
    d = tempfile.mkdtemp(prefix="hxs", dir="/tmp")
    yield d
    shutil.rmtree(d, ignore_errors=True)


# -- tokens -------------------------------------------------------------------
@pytest.mark.parametrize("token", ["s3cret", "a" * 64, "0123456789abcdef" * 1, "correcthorsebatterystaple",
                                   " " + secrets.token_hex(32), "1234567890" * 3],
                         ids=["short", "one-letter", "hex16", "words", "leading-space", "digits"])
def test_weak_tokens_are_refused_with_a_reason(token):
    why = tcpauth.token_weakness(token)
    assert why and token.strip() not in why          # the reason, never the value


@pytest.mark.parametrize("token", [secrets.token_hex(16), secrets.token_hex(32), secrets.token_urlsafe(22),
                                   secrets.token_urlsafe(32)],
                         ids=["hex16", "hex32", "urlsafe22", "urlsafe32"])   # stable ids: drawn values differ per process
def test_random_tokens_of_128_bits_are_accepted(token):
    assert tcpauth.token_bits(token) >= 128
    assert tcpauth.token_weakness(token) == ""


def test_token_compare_is_by_digest_and_exact():
    tok = secrets.token_hex(16)
    dig = tcpauth.secret_digest(tok)
    assert tcpauth.token_matches(tok, dig)
    assert not tcpauth.token_matches(tok[:-1], dig)
    assert not tcpauth.token_matches(tok + "0", dig)
    assert not tcpauth.token_matches(None, dig) and not tcpauth.token_matches(b"x", dig)


def test_token_file_must_be_private_and_strong(tmpdir_):
    p = os.path.join(tmpdir_, "token")
    tok = secrets.token_hex(32)
    with open(p, "w") as f:
        f.write(tok + "\n")
    os.chmod(p, 0o644)
    with pytest.raises(HexacncError, match=r"mode 0644 .*chmod 600"):
        tcpauth.load_token_file(p)
    os.chmod(p, 0o640)
    with pytest.raises(HexacncError, match="its group"):
        tcpauth.load_token_file(p)
    os.chmod(p, 0o600)
    assert tcpauth.load_token_file(p) == tok
    with open(p, "w") as f:
        f.write("hunter2hunter2")
    with pytest.raises(HexacncError, match="too weak"):
        tcpauth.load_token_file(p)
    link = os.path.join(tmpdir_, "link")
    os.symlink(p, link)
    with pytest.raises(HexacncError, match="cannot open"):
        tcpauth.load_token_file(link)
    with pytest.raises(HexacncError, match="cannot open"):
        tcpauth.load_token_file(os.path.join(tmpdir_, "absent"))


def test_a_weak_tcp_token_is_refused_before_the_drives_boot(tmpdir_):
    from hexacnc.daemon.admission import preflight
    base = open(os.path.join(os.path.dirname(__file__), "..", "config", "default.toml")).read()
    p = os.path.join(tmpdir_, "m.toml")
    with open(p, "w") as f:
        f.write(base.replace("[daemon]\n", '[daemon]\ntcp_port = 7777\ntcp_token = "s3cret"\n'))
    os.chmod(p, 0o600)
    cfg = load_config(p)
    sock = os.path.join(tmpdir_, "s.sock")
    with pytest.raises(HexacncError, match=r"\[daemon\] tcp_token: the token is too weak") as e:
        preflight(cfg, sock)
    assert "s3cret" not in str(e.value)
    os.chmod(p, 0o644)
    with pytest.raises(HexacncError, match=r"holds \[daemon\] tcp_token but has mode 0644"):
        preflight(cfg, sock)
    assert preflight(load_config(None), sock) == sock


def test_config_refuses_a_tcp_port_without_token_and_bad_daemon_keys(tmpdir_):
    base = open(os.path.join(os.path.dirname(__file__), "..", "config", "default.toml")).read()
    p = os.path.join(tmpdir_, "m.toml")
    for extra, msg in (('tcp_port = 7777\n', r"\[daemon\] token_file: a token is required"),
                       ('idle_timeout_s = 0.5\n', r"\[daemon\] idle_timeout_s: value 0.5 is below"),
                       ('tcp_role = "root"\n', r"\[daemon\] tcp_role"),
                       ('max_unauthenticated = 0\n', r"\[daemon\] max_unauthenticated")):
        with open(p, "w") as f:
            f.write(base.replace("[daemon]\n", "[daemon]\n" + extra))
        with pytest.raises(ConfigError, match=msg):
            load_config(p)


def test_enable_at_start_defaults_to_the_bus_being_simulated(tmpdir_):
    assert load_config(None).daemon.enable_at_start is True
    base = open(os.path.join(os.path.dirname(__file__), "..", "config", "default.toml")).read()
    assert "simulate = true" in base
    p = os.path.join(tmpdir_, "real.toml")
    with open(p, "w") as f:
        f.write(base.replace("simulate = true", "simulate = false"))
    assert load_config(p).daemon.enable_at_start is False
    with open(p, "w") as f:
        f.write(base.replace("simulate = true", "simulate = false").replace("[daemon]\n", "[daemon]\nenable_at_start = true\n"))
    assert load_config(p).daemon.enable_at_start is True


# -- back-off ---------------------------------------------------------------------
def test_failed_attempts_back_off_per_address():
    lim = tcpauth.FailureLimiter()
    t = 100.0
    assert lim.retry_after("10.0.0.1", t) == 0.0
    delays = [lim.failed("10.0.0.1", t + i * 100) for i in range(12)]
    assert delays[:5] == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.6])
    assert max(delays) == tcpauth.MAX_DELAY_S and delays == sorted(delays)
    now = t + 11 * 100
    assert lim.retry_after("10.0.0.1", now + 1) == pytest.approx(29.0)
    assert lim.retry_after("10.0.0.2", now) == 0.0          # another address is not affected
    lim.succeeded("10.0.0.1")
    assert lim.retry_after("10.0.0.1", now + 1) == 0.0
    # guesses an address can get evaluated in 60 s when it always tries as soon as allowed
    lim2, t, n = tcpauth.FailureLimiter(), 0.0, 0
    while t < 60.0:
        t += lim2.retry_after("a", t)
        lim2.failed("a", t)
        n += 1
    assert n / 60.0 <= 10.0 and n <= 12


def test_limiter_memory_is_bounded():
    lim = tcpauth.FailureLimiter(max_addresses=100)
    for i in range(1000):
        lim.failed(f"10.0.{i // 256}.{i % 256}", 0.0)
    assert len(lim._s) == 100


# -- roles --------------------------------------------------------------------------
def test_roles_from_peer_credentials():
    import grp
    g = grp.getgrgid(0).gr_name
    pol = A.AccessPolicy(controller_group="", observer_group=g, owner_uid=1234)
    assert pol.role_for(A.Peer("unix", uid=1234, gid=99, pid=1, groups=(99,)))[0] == A.CONTROLLER
    assert pol.role_for(A.Peer("unix", uid=0, gid=0, pid=1, groups=(0,)))[0] == A.CONTROLLER
    assert pol.role_for(A.Peer("unix", uid=4321, gid=5, pid=7, groups=(5, 0)))[0] == A.OBSERVER
    role, why = pol.role_for(A.Peer("unix", uid=4321, gid=5, pid=7, groups=(5,)))
    assert role is None and "uid 4321" in why and "pid 7" in why and f"observer_group {g!r}" in why
    pol = A.AccessPolicy(controller_group=g, sensor_group=g, owner_uid=1234)
    assert pol.role_for(A.Peer("unix", uid=4321, gid=0, pid=7, groups=(0,)))[0] == A.CONTROLLER
    with pytest.raises(HexacncError, match="no such group"):
        A.AccessPolicy(controller_group="no-such-group-hx")


def test_ops_by_role_default_deny():
    for op in ("status", "hello", "wait", "subscribe", "unsubscribe", "release"):
        assert all(A.allowed(r, op) for r in A.ROLES)
    assert A.allowed(A.SENSOR, "temperatures") and A.allowed(A.CONTROLLER, "temperatures")
    assert not A.allowed(A.OBSERVER, "temperatures")
    for op in ("program", "pause", "resume", "stop", "reset", "enable", "some_future_op"):
        assert A.allowed(A.CONTROLLER, op)
        assert not A.allowed(A.SENSOR, op) and not A.allowed(A.OBSERVER, op) and not A.allowed(None, op)
    assert "controller or sensor" in A.refusal(A.OBSERVER, "temperatures")


# -- socket placement -------------------------------------------------------------
def test_default_socket_paths():
    assert sockpath.default_socket_path({"RUNTIME_DIRECTORY": "/run/hexacnc"}) == "/run/hexacnc/hexacnc.sock"
    d = tempfile.mkdtemp(prefix="hxx", dir="/tmp")
    try:
        assert sockpath.default_socket_path({"XDG_RUNTIME_DIR": d}) == os.path.join(d, "hexacnc", "hexacnc.sock")
    finally:
        os.rmdir(d)
    p = sockpath.default_socket_path({})
    assert p == os.path.join(tempfile.gettempdir(), f"hexacnc-{os.geteuid()}", "hexacnc.sock")
    assert "/run/hexacnc/hexacnc.sock" in sockpath.client_socket_candidates({})


def test_directory_checks(tmpdir_):
    me = {os.geteuid()}
    sockpath.check_dir(tmpdir_, me)
    os.chmod(tmpdir_, 0o777)
    with pytest.raises(sockpath.SocketTrustError, match=r"writable by others \(mode 0777\)"):
        sockpath.check_dir(tmpdir_, me)
    os.chmod(tmpdir_, 0o770)
    with pytest.raises(sockpath.SocketTrustError, match="writable by its group"):
        sockpath.check_dir(tmpdir_, me)
    os.chmod(tmpdir_, 0o700)
    sub = os.path.join(tmpdir_, "a")
    os.mkdir(sub, 0o700)
    os.chmod(tmpdir_, 0o777)                            # a parent others can write (not sticky)
    with pytest.raises(sockpath.SocketTrustError, match="parent"):
        sockpath.check_dir(sub, me)
    os.chmod(tmpdir_, 0o1777)                           # sticky like /tmp: fine
    sockpath.check_dir(sub, me)
    with pytest.raises(sockpath.SocketTrustError, match="belongs to"):
        sockpath.check_dir(sub, {os.geteuid() + 12345})


def test_prepare_server_dir_creates_the_default_place_0700(tmpdir_, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", tmpdir_)
    path = sockpath.default_socket_path()
    d = sockpath.prepare_server_dir(path)
    assert d == os.path.join(tmpdir_, "hexacnc")
    assert stat.S_IMODE(os.stat(d).st_mode) == 0o700
    with pytest.raises(sockpath.SocketTrustError, match="does not exist"):
        sockpath.prepare_server_dir(os.path.join(tmpdir_, "nowhere", "x.sock"))   # not a default: not made


def test_a_client_refused_at_connect_reports_the_daemons_reason():
    import socket

    from hexacnc.daemon import protocol as P
    a, b = socket.socketpair()
    b.sendall(P.encode(P.error_reply(None, P.UNAUTHORIZED, "uid 65534 (nobody) pid 7 is not the daemon's user")))
    b.close()                                         # what the daemon does to a peer without a role
    c = P.Client(a)
    with pytest.raises(P.ConnectionLost, match=r"not the daemon's user \[unauthorized\]"):
        for _ in range(50):                           # the first sends may still be buffered
            c.send("hello", client="x" * 60000)
    c.close()
