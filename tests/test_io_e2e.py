"""M62-M65 end to end: the daemon runs a program on the simulated drives (shared-memory bus, their
own process) and the drives' 0x60FE:1 objects change at the right points along the motion (the drives'
log: SYNC count, one per cycle and row); an unmapped output is refused with its line."""
from __future__ import annotations

import dataclasses
import json
import os
import time

import pytest
from e2e_fixtures import cfg, client, running_machine, wait_standstill  # noqa: F401

from hexacnc.config.iomap import IoConfig
from hexacnc.daemon import protocol as P

pytestmark = [pytest.mark.e2e]


@pytest.fixture(scope="module")
def machine(cfg):  # noqa: F811
    io = IoConfig(digital_out={0: (0, 16), 1: (1, 17)}, digital_in={2: (2, 5)})
    yield from running_machine(dataclasses.replace(cfg, io=io), name="dio")


def _iolog(daemon, tmp_path) -> dict:
    path = str(tmp_path / "iolog.json")
    daemon.sim.iolog(path)
    t_end = time.monotonic() + 10.0
    while not os.path.exists(path):
        assert time.monotonic() < t_end, "the simulated drives wrote no I/O log"
        time.sleep(0.02)
    doc = json.loads(open(path).read())
    return {int(v["strut"]): v for v in doc.values()}


def test_outputs_change_on_the_drives_at_the_right_points(machine, client, tmp_path):
    daemon = machine[0]
    period = daemon.period_s
    text = ("G21 G91 G94\nM64 P0\nG1 X1 F600\nG4 P0.5\nM62 P1\nG1 X4\nM63 P1\nG1 X3\n"
            "M65 P0\nG1 X-8\nM2\n")
    client.call("program", text=text, name="dio.ngc", reply_timeout_s=120.0)
    t_end = time.monotonic() + 30.0
    while daemon.sh.s[95] < 4 and time.monotonic() < t_end:     # S_IO_WRITES: all four acknowledged
        time.sleep(0.05)
    logs = _iolog(daemon, tmp_path)
    d0, d1 = logs[0], logs[1]
    assert [e["outputs"] for e in d0["log"]] == [1 << 16, 0]
    assert [e["outputs"] for e in d1["log"]] == [1 << 17, 0]
    assert d0["outputs"] == 0 and d1["outputs"] == 0 and all(v["log"] == [] for k, v in logs.items() if k > 1)
    on0, off0 = (e["syncs"] for e in d0["log"])
    on1, off1 = (e["syncs"] for e in d1["log"])
    # M62 P1 waits for the G1 X4 after the dwell: at least the 0.5 s dwell (one SYNC per row) after M64
    assert on1 - on0 >= 0.5 / period
    # ... and not much later: the G1 X1 before the dwell is short (< 0.3 s)
    assert on1 - on0 < (0.5 + 0.3) / period
    # M63 P1 at the start of the G1 X3: the whole G1 X4 (>= 0.4 s at 600 mm/min) lies between
    assert off1 - on1 >= 0.4 / period
    # M65 P0 after the G1 X3 (>= 0.3 s), before the G1 X-8 (the strut targets moved between)
    assert off0 - off1 >= 0.3 / period
    assert d1["log"][0]["target_inc"] != d1["log"][1]["target_inc"]


def test_unmapped_output_refused_before_motion(machine, client):
    before = wait_standstill(client, 30.0, polls=3)["pose_cmd"]
    with pytest.raises(P.DaemonError) as ei:
        client.call("program", text="G21 G91 G94\nG1 X1 F600\nM64 P5\nG1 X-1\nM2\n", name="bad.ngc",
                    reply_timeout_s=60.0)
    msg = str(ei.value)
    assert "line 3" in msg and "P5" in msg and "not mapped" in msg
    assert client.call("status")["pose_cmd"] == before


def _node_of(daemon, tmp_path, strut: int) -> int:
    path = str(tmp_path / "nodes.json")
    daemon.sim.iolog(path)
    t_end = time.monotonic() + 10.0
    while not os.path.exists(path):
        assert time.monotonic() < t_end
        time.sleep(0.02)
    return next(int(k) for k, v in json.loads(open(path).read()).items() if v["strut"] == strut)


def test_m66_waits_on_the_drive_input_and_sets_5399(machine, client, tmp_path):
    import threading
    daemon = machine[0]
    node = _node_of(daemon, tmp_path, 2)          # [io] digital_in_2 = drive 3, bit 5
    daemon.sim.inject("dinput", node, 0)
    x0 = wait_standstill(client, 30.0, polls=3)["pose_cmd"][0]
    # L3: wait for high (set 0.4 s after the wait began); L4 Q0.2: low never comes: -1; L0: reads 1
    text = ("G21 G91 G94\nG1 X1 F600\nM66 P2 L3 Q20\nG1 X[#5399 * 2]\nM66 P2 L4 Q0.2\n"
            "G1 X[#5399 + 4]\nM66 P2 L0\nG1 X[#5399 * 0.5]\nG1 X-6.5\nM2\n")
    timer = threading.Timer(1.5, daemon.sim.inject, ("dinput", node, 1 << 5))
    timer.start()
    t0 = time.monotonic()
    try:
        r = client.call("program", text=text, name="m66.ngc", reply_timeout_s=120.0)
    finally:
        timer.cancel()
    assert time.monotonic() - t0 >= 1.5                     # it did wait for the input
    assert [(e["line"], e["mode"], e["value"]) for e in r["inputs"]] == [(3, "high", 1), (5, "low", -1),
                                                                          (7, "immediate", 1)]
    st = wait_standstill(client, 30.0, polls=3)
    # X: +1, +2 (#5399 = 1), +3 (-1 + 4), +0.5, -6.5: back where it started
    assert st["pose_cmd"][0] == pytest.approx(x0, abs=1e-6)
    daemon.sim.inject("dinput", node, 0)


def test_m66_on_an_unmapped_input_refused_before_motion(machine, client):
    before = wait_standstill(client, 30.0, polls=3)["pose_cmd"]
    with pytest.raises(P.DaemonError) as ei:
        client.call("program", text="G21 G91 G94\nM66 P4 L3 Q1\nG1 X1 F600\nM2\n", name="bad66.ngc",
                    reply_timeout_s=60.0)
    assert "line 2" in str(ei.value) and "P4" in str(ei.value)
    assert client.call("status")["pose_cmd"] == before
