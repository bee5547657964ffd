"""A stop while a program larger than one planning window is still being interpreted, validated and
planned behind the socket (op ``program`` and the chunked ``program_begin/chunk/end``): the socket path
streams it through the bounded validator and windowed planner (:mod:`hexacnc.daemon.planstream`), the stop
ends the motion on the frames the drives receive and kills the planning children, the program is refused
with the reason, and the daemon takes the next program (nothing accepted is lost)."""
from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import time

import numpy as np
import pytest

from hexacnc.bench.ringtap import RingTap
from hexacnc.config import load_config
from hexacnc.daemon import protocol as P
from hexacnc.daemon.core import Daemon
from hexacnc.daemon.planstream import StreamPlan
from hexacnc.daemon.server import SocketServer

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

#: motion lines of the large program: 40 planning windows of the default 2000 blocks, ~1.5 MB (one message)
LINES = 80_000


def _cfg():
    base = load_config(None)
    return base.replace(daemon=dataclasses.replace(base.daemon, max_plan_s=60.0),
                        cycle=dataclasses.replace(base.cycle, max_overruns_in_row=1000),
                        bus=dataclasses.replace(base.bus, comm_loss_timeout_s=0.5))     # VM stalls: as e2e_fixtures


def _program(lines: int) -> str:
    return "G0 X0 Y0 Z20\n" + "".join(f"G1 X{(i % 100) * 0.5 - 25:.1f} Y{(i % 7) - 3} F3000\n"
                                      for i in range(lines)) + "M2\n"


def _recv(c, ids: set, timeout_s: float = 60.0) -> dict:
    """{id: (arrival order, reply)} of the replies to ``ids``."""
    got = {}
    t_end = time.monotonic() + timeout_s
    while not ids <= set(got) and time.monotonic() < t_end:
        m = c.next_message(max(0.1, t_end - time.monotonic()))
        if m is not None and m.get("id") in ids and "stream" not in m:
            got[m["id"]] = (len(got), m)
    assert ids <= set(got), f"no reply to {ids - set(got)} within {timeout_s} s"
    return got


def _speeds(tap, cfg, t_from: float) -> np.ndarray:
    tap.drain()
    _, L = tap.lengths_mm(t_from)
    return np.max(np.abs(np.diff(L, axis=0)), axis=1) / cfg.cycle.period_s


def _wait_moving(tap, cfg, timeout_s: float = 30.0) -> None:
    """Until the frames show the struts moving (the move's rows reach the hot loop; on a loaded machine that
    can take a while, and a stop that comes first finds nothing to stop)."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        v = _speeds(tap, cfg, time.monotonic() - 0.05)
        if v.size and v.max() > 0.5:
            return
        time.sleep(0.02)
    raise AssertionError(f"the struts did not move within {timeout_s} s of the move")


def _planning(daemon, timeout_s: float = 60.0) -> StreamPlan:
    """The streamed plan of the program once its children run."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        sps = [p for p in list(daemon._planning) if isinstance(p, StreamPlan)]
        if sps and sps[0].alive():
            return sps[0]
        time.sleep(0.01)
    raise AssertionError(f"the program was not streamed to planning children within {timeout_s} s "
                         f"(planning: {daemon._planning})")


@pytest.mark.parametrize("chunked", [False, True])
def test_stop_while_a_large_program_is_planned_ends_motion_and_planning(chunked):
    cfg = _cfg()
    text = _program(LINES)
    data = text.encode()
    assert len(data) < cfg.daemon.max_message_bytes - 4096      # one message fits: both paths comparable
    d = tempfile.mkdtemp(prefix="hxbg", dir="/tmp")
    daemon = Daemon(cfg, realtime=False)
    tap = RingTap(cfg, [seg.name for seg in daemon.sim.segments]).start()
    srv = SocketServer(daemon, cfg, os.path.join(d, "b.sock")).start()
    try:
        with P.Client.unix(srv.socket_path) as c:
            pose = np.array(cfg.home_pose, dtype=float)
            pose[0] += 100.0
            daemon.move_to(pose, 6.0)                       # ~17 s of motion
            _wait_moving(tap, cfg)
            if chunked:
                half = len(text) // 2
                c.call("program_begin", name="big.ngc", bytes=len(data))
                r0 = c.call("program_chunk", seq=0, text=text[:half])
                r1 = c.call("program_chunk", seq=1, text=text[half:])
                assert r0["received_bytes"] + len(text[half:].encode()) == r1["received_bytes"] == len(data)
                rid = c.send("program_end")
            else:
                rid = c.send("program", text=text, name="big.ngc")
            sp = _planning(daemon)
            assert sp.total_lines == LINES + 2 and sp.validation["state"] == "running"
            t0 = time.monotonic()
            sid = c.send("stop")
            got = _recv(c, {rid, sid})
            assert got[sid][1]["ok"]
            prog = got[rid][1]
            assert not prog["ok"] and "stopped" in prog["error"]["message"], prog
            # the planning ended: children killed, nothing left being planned
            t_end = time.monotonic() + 5.0
            while sp.alive() and time.monotonic() < t_end:
                time.sleep(0.02)
            assert sp.cancelled and not sp.alive() and not daemon._planning
            # on the frames: moving when the stop came, at rest afterwards, never the program's motion
            time.sleep(0.5)
            v = _speeds(tap, cfg, t0 - 0.1)
            assert v[:200].max() > 0.5 and v[-1] < 1e-6     # moving in the 0.1 s before the stop, at rest after
            st = c.call("status")
            assert st["state"] == "idle" and st["program"]["name"] == "move_to"
            # nothing accepted is lost: the daemon takes and runs the next program to its end
            t1 = time.monotonic()
            c.call("program", text="G0 X0 Y0 Z20\nG1 X5 F3000\nM2\n", name="next.ngc", reply_timeout_s=60.0)
            c.call("wait", timeout_s=30.0)
            st = c.call("status")
            assert st["state"] == "idle" and st["program"]["name"] == "next.ngc" and st["program"]["percent"] == 100
            v = _speeds(tap, cfg, t1)
            assert v.max() > 1.0 and v[-1] < 1e-6
    finally:
        srv.close()
        daemon.close()
        tap.stop()
        shutil.rmtree(d, ignore_errors=True)
