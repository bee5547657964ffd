"""End to end through the real daemon (simulated drives, Daemon.load_program: the streamed program path): a
program larger than the planning window with ``[planner] start_before_validated`` starts moving before its
validation is done; the validation finds a bad line far past the start; the motion stops with a controlled
stop before it, and the status names the line and the reason.  (The socket's ``program`` op goes through the
operator's persistent-state path, which still plans a program as a whole: see docs/planner.md.)"""
from __future__ import annotations

import dataclasses

import pytest

from hexacnc.bench.camgen import cam_program
from hexacnc.daemon import core  # noqa: F401  (a broken import fails the suite, never skips it)

from e2e_fixtures import cfg, machine, client, wait_standstill  # noqa: E402,F401  (shared fixtures)


@pytest.mark.e2e
def test_program_found_bad_ahead_stops_before_the_bad_line(machine, client):
    daemon, _srv = machine
    keep = daemon.cfg
    daemon.cfg = keep.replace(planner=dataclasses.replace(keep.planner, window_blocks=60,
                                                          start_before_validated=True))
    bad = 9_000
    try:
        daemon.load_program("M2\n", "warm")                  # the forkserver up before the measured program
        assert client.call("wait", timeout_s=600.0)["state"] == "idle"
        r = daemon.load_program(cam_program(10_000, bad_line=bad), "bad-ahead.ngc")
        assert r["validated"] is False
        st = client.call("wait", timeout_s=600.0)
    finally:
        daemon.cfg = keep
    assert st["state"] == "idle" and st["fault"] is None, (st["fault"], st["program"])
    prog = st["program"]
    assert prog["name"] == "bad-ahead.ngc" and prog["stopped"] is True
    assert prog["error"]["line"] == bad and "max_length_mm" in prog["error"]["message"]
    assert 0 < prog["line"] < bad
    st = wait_standstill(client, 10.0)
    assert st["state"] == "idle"
