"""Property tests: seeded random bytes and random maps on the socket never crash the server.

Every decodable request gets exactly one well-formed reply carrying its id (or
null when the id is unreadable); undecodable streams only lose their own
connection; afterwards the server still serves a well-behaved client, the fake
daemon's program was never disturbed, and no unvalidated call reached it.
"""
from __future__ import annotations

import os
import random
import shutil
import socket
import tempfile
import time

import msgpack
import pytest

from hexacnc.config import load_config
from hexacnc.daemon import protocol as P
from hexacnc.daemon.server import SocketServer

from test_protocol_fake import FakeDaemon

pytestmark = pytest.mark.e2e


KEYS = ["id", "op", "text", "name", "timeout_s", "rate_hz", "token", "sub", "x", ""]
OPS = list(P.OPS) + ["", "fly", "PROGRAM", "status ", "\u00e9"]


def rand_value(rng: random.Random, depth: int = 0):
    k = rng.randrange(11 if depth < 2 else 8)
    if k == 0:
        return None
    if k == 1:
        return rng.choice([True, False])
    if k == 2:
        return rng.choice([0, 1, -1, 2 ** 31, -(2 ** 63), 2 ** 64 - 1, rng.randrange(-1000, 1000)])
    if k == 3:
        return rng.choice([0.0, -1.0, 0.01, 1e308, float("inf"), float("nan"), rng.uniform(-10, 10)])
    if k == 4:
        return "".join(chr(rng.randrange(1, 0x2FF)) for _ in range(rng.randrange(12)))
    if k == 5:
        return bytes(rng.randrange(256) for _ in range(rng.randrange(12)))
    if k == 6:
        return rng.choice(OPS)
    if k == 7:
        return "G1 X1\n" * rng.randrange(3)
    if k == 8:
        return [rand_value(rng, depth + 1) for _ in range(rng.randrange(4))]
    if k == 9:
        return {rng.choice(KEYS): rand_value(rng, depth + 1) for _ in range(rng.randrange(4))}
    return msgpack.ExtType(rng.randrange(128), b"\x00\x01")


def rand_map(rng: random.Random) -> dict:
    m = {}
    if rng.random() < 0.8:
        m["id"] = rng.randrange(1, 10 ** 6) if rng.random() < 0.85 else rand_value(rng)
    if rng.random() < 0.85:
        m["op"] = rng.choice(OPS) if rng.random() < 0.85 else rand_value(rng)
    for _ in range(rng.randrange(4)):
        m[rng.choice(KEYS)] = rand_value(rng)
    if m.get("op") == "wait" and isinstance(m.get("timeout_s"), (int, float)):
        m["timeout_s"] = 0.0 if rng.random() < 0.5 else m["timeout_s"]
    return m


def _check_reply(r):
    assert isinstance(r, dict) and isinstance(r.get("ok"), bool), r
    assert "id" in r
    if not r["ok"]:
        e = r["error"]
        assert e["code"] in P.ERROR_CODES, e
        assert isinstance(e["message"], str) and e["message"]
        assert e["line"] is None or isinstance(e["line"], int)


@pytest.fixture
def served():
    cfg = load_config(None)
    d = tempfile.mkdtemp(prefix="hxf", dir="/tmp")
    daemon = FakeDaemon(block_s=0.01)
    srv = SocketServer(daemon, cfg, os.path.join(d, "s.sock"), max_clients=64)
    srv.start()
    yield srv, daemon
    srv.close()
    daemon.close()
    shutil.rmtree(d, ignore_errors=True)


def _recv_all(sock, unpacker, until_ids, timeout):
    got = []
    deadline = time.monotonic() + timeout
    pending = set(until_ids)
    while pending and time.monotonic() < deadline:
        sock.settimeout(max(0.01, deadline - time.monotonic()))
        try:
            data = sock.recv(65536)
        except socket.timeout:
            break
        if not data:
            break
        unpacker.feed(data)
        for m in unpacker:
            got.append(m)
            if isinstance(m, dict) and "stream" not in m:
                pending.discard(m.get("id"))
    return got, pending


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_random_maps_always_get_one_wellformed_reply(served, seed):
    srv, daemon = served
    rng = random.Random(seed)
    observer = P.Client.unix(srv.socket_path)
    observer.call("subscribe", rate_hz=50.0)
    for conn_no in range(6):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.connect(srv.socket_path)
        u = msgpack.Unpacker(raw=False, strict_map_key=False)
        msgs = [rand_map(rng) for _ in range(60)]
        # never ask the fake to wait long: the test is about the protocol, not about time
        for m in msgs:
            if m.get("op") == "wait" and isinstance(m.get("timeout_s"), (int, float)) \
                    and not isinstance(m.get("timeout_s"), bool):
                m["timeout_s"] = 0.0
        s.sendall(b"".join(msgpack.packb(m, use_bin_type=True) for m in msgs))
        n_expected = len(msgs)
        got, _ = _recv_all(s, u, [], 0.0)
        deadline = time.monotonic() + 10.0
        replies = []
        while len(replies) < n_expected and time.monotonic() < deadline:
            more, _ = _recv_all(s, u, [object()], 0.2)
            got.extend(more)
            replies = [m for m in got if isinstance(m, dict) and "stream" not in m]
        assert len(replies) == n_expected, (seed, conn_no, len(replies))
        for r in replies:
            _check_reply(r)
        # ids: every well-typed id is answered exactly once
        want = sorted(m["id"] for m in msgs if type(m.get("id")) is int)
        have = sorted(r["id"] for r in replies if r["id"] is not None)
        assert have == want
        s.close()
    # the observer's stream and requests still work; the server thread lives
    assert observer.call("status")["ok"]
    assert observer.next_message(1.0)["stream"] == "status"
    assert srv._thread.is_alive()
    observer.close()


@pytest.mark.parametrize("seed", [11, 12, 13, 14])
def test_random_bytes_never_crash_the_server(served, seed):
    srv, daemon = served
    rng = random.Random(seed)
    watcher = P.Client.unix(srv.socket_path)
    assert watcher.call("program", text="G1 X1\n" * 40, name="background")["ok"]
    socks = []
    for _ in range(30):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.connect(srv.socket_path)
        kind = rng.randrange(3)
        if kind == 0:
            data = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 2000)))
        elif kind == 1:      # a valid request followed by garbage
            data = msgpack.packb({"id": 1, "op": "status"}) + bytes(rng.randrange(256) for _ in range(64))
        else:                # a valid request cut short, then garbage
            full = msgpack.packb({"id": 1, "op": "program", "text": "G1 X1\n" * 20, "name": "n"})
            data = full[:rng.randrange(1, len(full))] + bytes(rng.randrange(256) for _ in range(16))
        try:
            s.sendall(data)
        except OSError:
            pass                       # the server may already have closed it
        socks.append(s)
    time.sleep(0.2)
    for s in socks:
        s.close()
    assert srv._thread.is_alive()
    w = watcher.call("wait", timeout_s=10.0)
    assert w["state"] == "idle" and w["result"] == "finished"    # the program ran to its end undisturbed
    assert watcher.call("status")["ok"]
    # the watcher controls motion: nothing the random streams sent reached the daemon's motion API
    assert daemon.calls == ["load_program"]
    watcher.close()
    time.sleep(0.2)
    assert srv.clients == 0
