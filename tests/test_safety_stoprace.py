"""A ``stop`` sent right behind a program (``program`` or a chunked upload) aborts that program even
when the stop overtakes it (stop runs on its own worker): the program is refused as stopped and the
daemon ends stopped, never running the program the client stopped."""
from __future__ import annotations

import os
import shutil
import tempfile
import time

import pytest

from hexacnc.config import load_config
from hexacnc.daemon.server import SocketServer

from test_protocol_fake import FakeDaemon
from test_protocol_server import Raw

pytestmark = pytest.mark.e2e

SLOW = "SLOWLOAD\nG1 X1\nG1 X2\n"       # the fake daemon takes 0.5 s to load it


@pytest.fixture
def served():
    d = tempfile.mkdtemp(prefix="hxsr", dir="/tmp")
    fake = FakeDaemon(block_s=5.0)
    srv = SocketServer(fake, load_config(None), os.path.join(d, "s.sock")).start()
    yield srv, fake
    srv.close()
    fake.close()
    shutil.rmtree(d, ignore_errors=True)


def _replies(c, n):
    got = {}
    while len(got) < n:
        m = c.recv(10.0)
        got[m.get("id")] = m
    return got


def _wait_idle(fake, timeout_s=3.0):
    t_end = time.monotonic() + timeout_s
    while fake.state != "idle" and time.monotonic() < t_end:
        time.sleep(0.01)
    return fake.state


@pytest.mark.parametrize("chunked", [False, True])
def test_stop_behind_a_program_aborts_it(served, chunked):
    srv, fake = served
    c = Raw(srv.socket_path)
    if chunked:
        c.send_obj({"id": 1, "op": "program_begin", "name": "slow.ngc", "bytes": len(SLOW)})
        c.send_obj({"id": 2, "op": "program_chunk", "seq": 0, "text": SLOW})
        c.send_obj({"id": 3, "op": "program_end"})
    else:
        c.send_obj({"id": 3, "op": "program", "text": SLOW, "name": "slow.ngc"})
    c.send_obj({"id": 4, "op": "stop"})
    got = _replies(c, 4 if chunked else 2)
    assert got[4]["ok"]
    assert not got[3]["ok"] and "stopped" in got[3]["error"]["message"], got[3]
    assert _wait_idle(fake) == "idle"              # the program does not run


def test_a_program_after_the_stop_runs(served):
    srv, fake = served
    c = Raw(srv.socket_path)
    c.send_obj({"id": 1, "op": "stop"})
    assert _replies(c, 1)[1]["ok"]
    c.send_obj({"id": 2, "op": "program", "text": "G1 X1\n", "name": "ok.ngc"})
    r = _replies(c, 1)[2]
    assert r["ok"], r
    assert fake.state == "running"
