"""Shared fixtures for the end-to-end tests: the real daemon (hot-loop process, simulated
drives) behind its socket server, and a controlling client that starts each test from idle.

Import them into a test module with ``from e2e_fixtures import cfg, machine, client``.
"""
from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
import tempfile
import time

import pytest

from hexacnc.config import load_config
from hexacnc.daemon import protocol as P
from hexacnc.daemon.server import SocketServer

from hexacnc.daemon import core


@pytest.fixture(scope="module")
def cfg():
    base = load_config(None)
    # Test machine: shared 2 cores, no SCHED_FIFO, other suites running. Measured there: bursts
    # of 300 overrun cycles (150 ms stalls of the hot process), after which the simulated drives
    # (another process) trail the catching-up command by > 1 mm. Tolerate those stalls (burst
    # count, following error); strut length/joint/velocity limits stay exactly as configured.
    cycle = dataclasses.replace(base.cycle, max_overruns_in_row=1000, following_error_mm=25.0)
    # the same stalls would trip the drives' own master supervision (RPDO deadline, [bus]
    # comm_loss_timeout_s, default 20 ms: a quick stop by the drives); tolerate them here too
    base = base.replace(bus=dataclasses.replace(base.bus, comm_loss_timeout_s=0.5))
    # the shipped [thermal] source ("socket", no readings pushed here) applies no offsets, so these
    # suites check the commands against the plain IK + sag; tests/test_e2e_thermal_*.py cover the
    # compensation (the simulated plant's probe noise alone would move them by ~0.2 um)
    assert base.thermal.source == "socket"
    # persistent offsets / tool table (hexacnc/state) in a private directory, never the user's
    state = tempfile.mkdtemp(prefix="hxstate", dir="/tmp")
    yield base.replace(cycle=cycle, operator=dataclasses.replace(base.operator, state_dir=state))
    shutil.rmtree(state, ignore_errors=True)


def running_machine(cfg, realtime: bool = False, name: str = "e2e"):
    """Generator for a module fixture: yields (daemon, server) on a fresh socket; tears both down
    (drives disabled, processes joined) after it."""
    d = tempfile.mkdtemp(prefix="hx" + name[:3], dir="/tmp")
    daemon = core.Daemon(cfg, realtime=realtime)
    try:
        srv = SocketServer(daemon, cfg, os.path.join(d, name + ".sock")).start()
    except BaseException:
        daemon.close()
        raise
    try:
        yield daemon, srv
    finally:        # also on gen.close(): never a daemon left running behind a test
        srv.close()
        daemon.close()
        shutil.rmtree(d, ignore_errors=True)


#: ``with machine_running(cfg, name=...) as (daemon, server):`` -- the same, for one test
machine_running = contextlib.contextmanager(running_machine)


@pytest.fixture(scope="module")
def machine(cfg):
    """(daemon, server) for the module; torn down (drives disabled, processes joined) after it."""
    yield from running_machine(cfg)


def wait_state(c, state: str, timeout_s: float = 10.0) -> dict:
    """Poll status until its ``state`` is ``state``; returns that status. Fails the test after ``timeout_s``."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        st = c.call("status")
        if st["state"] == state:
            return st
        time.sleep(0.02)
    raise AssertionError(f"not {state}: {c.call('status')}")


def wait_standstill(client, timeout_s: float, interval_s: float = 0.1, polls: int = 1) -> dict:
    """Poll status until the commanded pose is the same ``polls`` polls in a row (``interval_s``
    apart); returns that status.  Fails the test if it still moves after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    last, still = client.call("status")["pose_cmd"], 0
    while True:
        time.sleep(interval_s)
        st = client.call("status")
        still = still + 1 if st["pose_cmd"] == last else 0
        if still >= polls:
            return st
        assert time.monotonic() < deadline, f"still moving {timeout_s} s after the command"
        last = st["pose_cmd"]


@pytest.fixture
def client(machine):
    """A client that holds control, handed over with the machine idle (faults reset, leftovers stopped)."""
    daemon, srv = machine
    c = P.Client.unix(srv.socket_path)
    st = c.call("status")
    if st["state"] == "fault":
        c.call("reset", reply_timeout_s=30.0)
    elif st["state"] in ("running", "paused"):          # left over by a failed test
        c.call("stop")
    assert c.call("wait", timeout_s=30.0)["state"] == "idle"
    yield c
    c.close()
    time.sleep(0.05)        # let the server notice, so the next test's client can take control
