"""End to end through the real daemon (simulated drives): a program larger than the planning window with
``[planner] start_before_validated`` starts moving before its validation is done; the validation finds a bad
line far past the start; the motion stops with a controlled stop before it, and the status names the line
and the reason."""
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
    bad = 58_000
    try:
        r = client.call("program", text=cam_program(60_000, bad_line=bad), name="bad-ahead.ngc",
                        reply_timeout_s=600.0)
        assert r["ok"] and r["validated"] is False
        st = client.call("wait", timeout_s=600.0)
    finally:
        daemon.cfg = keep
    assert st["state"] == "idle" and st["fault"] is None
    prog = st["program"]
    assert prog["name"] == "bad-ahead.ngc" and prog["stopped"] is True
    assert prog["error"]["line"] == bad and "max_length_mm" in prog["error"]["message"]
    assert 0 < prog["line"] < bad
    st = wait_standstill(client, 10.0)
    assert st["state"] == "idle"
