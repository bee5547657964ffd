"""A captured session against the ``strict`` simulated drives, judged from the capture taken on the drives'
side of the buses (``hexacnc run --capture``: FILE-drives.pcap, what a bus monitor records), which outlives
the master: boot, a program, a stop, a drive fault (EMCY) and its reset, a normal disable (0x605C walk) and
re-enable, then the master falls silent mid-move (the hot process is killed) and the drives react on their
own within ``[bus] comm_loss_timeout_s``: EMCY 0x8250 / 0x8700, quick stop, Switch on disabled, their
heartbeats going on. Decoded by drivers.pcap.read_pcap, and by tshark's CANopen dissector when installed."""
from __future__ import annotations

import dataclasses
import os
import signal
import time

import pytest

from drivers import cia402, pcap, pcapcheck
from hexacnc.daemon import protocol as P

from e2e_fixtures import cfg as base_cfg, machine_running, wait_state  # noqa: F401  (shared fixtures)
from test_e2e_socket import work

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


def _u16(data: bytes) -> int:
    return int.from_bytes(data[:2], "little")


def _session(c, cfg, daemon):
    """boot (done), program to its end, program stopped, EMCY + reset, disable + enable, a moving program."""
    prog = ("G21 G90 G17\n" f"G0 {work(cfg, 10, -5, -1140)}\n" f"G1 {work(cfg, 20, 5, -1130)} F3000\nM2\n")
    c.call("program", text=prog, name="cap-1", reply_timeout_s=120.0)
    assert c.call("wait", timeout_s=60.0)["fault"] is None
    slow = "G21 G90\n" + f"G1 {work(cfg, 10, -5, -1140)} F3000\n" + f"G1 {work(cfg, 10, -5, -1100)} F300\nM2\n"
    c.call("program", text=slow, name="cap-stop", reply_timeout_s=120.0)
    wait_state(c, "running")
    time.sleep(0.3)
    c.call("stop")
    assert c.call("wait", timeout_s=30.0)["state"] == "idle"
    daemon.inject_drive("emcy", 3, 0x2310)
    wait_state(c, "fault", 5.0)
    c.call("reset", reply_timeout_s=30.0)
    assert c.call("wait", timeout_s=30.0)["state"] == "idle"
    c.call("disable", reply_timeout_s=30.0)                     # normal disable: 0x0007, then 0x0000
    c.call("enable", reply_timeout_s=30.0)
    assert c.call("wait", timeout_s=30.0)["state"] == "idle"
    c.call("program", text=slow, name="cap-silent", reply_timeout_s=120.0)
    wait_state(c, "running")
    time.sleep(0.5)                                             # on the F300 line: the struts move


def _check_bus(frames, nodes, comm_loss_s):
    """One bus's drive-side capture: the session's frames and the reaction to the silent master."""
    sync_t = [t for t, cid, _, _ in frames if cid == 0x080]
    assert len(sync_t) > 1000
    t_silent = sync_t[-1]                                       # the master's last SYNC on this bus
    for node in nodes:
        cw = [(t, _u16(d)) for t, cid, d, _ in frames if cid == 0x300 + node]
        sw = [(t, cia402.state_from_status(_u16(d))) for t, cid, d, _ in frames if cid == 0x280 + node]
        emcy = [(t, _u16(d)) for t, cid, d, _ in frames if cid == 0x80 + node and len(d) == 8]
        vals = [v for _, v in cw]
        t_r = 0.0
        if node == 3:                                           # the injected fault and its reset (edge of bit 7)
            t_f = next(t for t, code in emcy if code == 0x2310)
            t_r = next(t for t, v in cw if t > t_f and v == cia402.CW_FAULT_RESET)
            assert any(s == cia402.FAULT for t, s in sw if t_f <= t <= t_r)
            assert any(s == cia402.SWITCH_ON_DISABLED for t, s in sw if t > t_r)
        # the normal disable walk per 0x605C: 0x0007, Switched on reported, then 0x0000 (the faulted drive: the
        # walk after its reset; the stop that followed its fault walked it too, while it was still in Fault)
        k = next(i for i in range(len(vals) - 1) if cw[i][0] > t_r and vals[i:i + 2] == [
            cia402.CW_DISABLE_OPERATION, cia402.CW_DISABLE_VOLTAGE])
        assert any(cw[k][0] <= t <= cw[k + 1][0] and s == cia402.SWITCHED_ON for t, s in sw), (node, cw[k:k + 2])
        # the master fell silent: the drive's own reaction, within the configured time
        late = [(t, code) for t, code in emcy if t > t_silent - 0.01]
        assert late and late[0][1] in (cia402.EMCY_RPDO_TIMEOUT, cia402.EMCY_SYNC_LOSS), (node, late)
        dt = late[0][0] - t_silent
        # after comm_loss_timeout_s (the RPDO before the SYNC may start the deadline a cycle earlier; the
        # simulated drive's 2 ms tick), before it + 0.5 s (its own stalls on this loaded machine postpone it)
        assert comm_loss_s - 0.005 <= dt < comm_loss_s + 0.5, (node, dt)
        after = [s for t, s in sw if t >= late[0][0] - 0.001]
        assert cia402.QUICK_STOP_ACTIVE in after and after[-1] == cia402.SWITCH_ON_DISABLED, (node, after)
        assert cia402.OPERATION_ENABLED not in after[after.index(cia402.QUICK_STOP_ACTIVE):], (node, after)
        hb = [t for t, cid, _, _ in frames if cid == 0x700 + node and t > late[0][0]]
        assert hb, f"node {node}: no heartbeat after the reaction"
    return t_silent


def test_captured_session_shows_the_drives_reaction_to_a_silent_master(base_cfg, tmp_path, monkeypatch):
    # the drives' watchdog of the master's heartbeat (0x1016, heartbeat_timeout_ms) set past the RPDO deadline
    # (comm_loss_timeout_s) by more than one heartbeat period, so the deadline is the reaction seen first
    # (with this test's tolerant comm_loss_timeout_s the heartbeat watchdog could otherwise come first: 0x8130)
    b = base_cfg.bus
    hb_timeout_ms = max(b.heartbeat_timeout_ms, int(b.comm_loss_timeout_s * 1000) + b.heartbeat_ms + 300)
    cfg = base_cfg.replace(bus=dataclasses.replace(b, simulate_profile="strict", heartbeat_timeout_ms=hb_timeout_ms))
    cap = str(tmp_path / "session.pcap")
    monkeypatch.setenv(pcap.ENV_CAPTURE, cap)                  # as hexacnc run --capture sets it
    comm_loss_s = cfg.bus.comm_loss_timeout_s
    with machine_running(cfg, name="cap") as (daemon, srv):
        c = P.Client.unix(srv.socket_path)
        try:
            _session(c, cfg, daemon)
            os.kill(daemon.hot.pid, signal.SIGKILL)             # the master falls silent mid-move
            time.sleep(comm_loss_s + 1.5)
        finally:
            c.close()
    drives = pcap.drives_capture_path(cap)
    files = [drives, pcap.capture_path(drives, 1)]
    for f, nodes in zip(files, ((1, 2, 3), (4, 5, 6))):
        _check_bus(pcap.read_pcap(f), nodes, comm_loss_s)
    assert os.path.getsize(cap) > 0                             # the master's own capture, up to its end
    if not pcapcheck.tshark_available():
        pytest.skip("tshark is not installed: the capture was decoded by drivers.pcap only")
    for f, nodes in zip(files, ((1, 2, 3), (4, 5, 6))):
        res = pcapcheck.check(f)
        assert res["malformed"] == 0 and res["sdo_aborts"] == [], res
        for node in nodes:
            codes = [int(k.split(",")[0], 16) for k in res["emcy"].get(node, {})]
            assert {0x8250, 0x8700} & set(codes), (f, node, res["emcy"])
