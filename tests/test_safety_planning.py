"""Planning off the control path: bounded time and memory, killable by stop; stop acts while a
program is being planned, on the frames the drives receive."""
from __future__ import annotations

import dataclasses
import os
import tempfile
import time

import numpy as np
import pytest

from hexacnc.bench.ringtap import RingTap
from hexacnc.config import load_config
from hexacnc.daemon import protocol as P
from hexacnc.daemon.core import Daemon
from hexacnc.daemon.planproc import PlanJob
from hexacnc.daemon.server import SocketServer
from hexacnc.errors import HexacncError, PlanError

ENDLESS = "#1=0\no100 while [1]\n#1=[#1+1]\no100 endwhile\nM2\n"


def _cfg(**daemon):
    base = load_config(None)
    return base.replace(daemon=dataclasses.replace(base.daemon, **daemon),
                        cycle=dataclasses.replace(base.cycle, max_overruns_in_row=1000))


def _home(cfg):
    return np.array([*cfg.home_pose[:3], *np.radians(cfg.home_pose[3:])])


@pytest.mark.slow
def test_endless_program_is_refused_at_the_time_bound_naming_it_and_the_line():
    cfg = _cfg(max_plan_s=1.0)
    with pytest.raises(PlanError) as e:
        PlanJob(cfg, ENDLESS, "endless.ngc", _home(cfg), cfg.cycle.period_s).result()
    assert e.value.limit == "max_plan_s" and "max_plan_s = 1 s" in str(e.value)
    assert e.value.line in (2, 3, 4)          # inside the loop (o100 while .. endwhile)


@pytest.mark.slow
def test_program_over_the_memory_bound_is_refused_naming_it():
    cfg = _cfg(max_plan_memory_mb=700, max_plan_s=120.0)
    # a 16 h helix of 1500 turns: within [planner] max_block_s raised to its maximum and the check samples' bound,
    # the memory bound is what refuses it
    cfg = cfg.replace(planner=dataclasses.replace(cfg.planner, max_block_s=86400.0))
    text = "G0 X0 Y0 Z20\nG2 X0 Y0 I10 J0 P1500 F100\nM2\n"
    with pytest.raises(PlanError) as e:
        PlanJob(cfg, text, "turns.ngc", _home(cfg), cfg.cycle.period_s).result()
    assert e.value.limit == "max_plan_memory_mb" and "700 MB" in str(e.value)


def test_gcode_errors_come_back_with_line_and_column():
    from hexacnc.errors import GcodeError
    cfg = _cfg()
    with pytest.raises(GcodeError) as e:
        PlanJob(cfg, "G1 X1 F100\nG12\n", "bad.ngc", _home(cfg), cfg.cycle.period_s).result()
    assert e.value.line == 2 and e.value.column == 1


def test_cancel_kills_the_planning_child():
    cfg = _cfg(max_plan_s=60.0)
    pj = PlanJob(cfg, ENDLESS, "endless.ngc", _home(cfg), cfg.cycle.period_s)
    time.sleep(0.2)
    pj.cancel()
    with pytest.raises(HexacncError, match="stopped while"):
        pj.result()
    assert not pj.proc.is_alive()


@pytest.mark.e2e
@pytest.mark.slow
def test_stop_acts_on_the_running_motion_while_a_program_is_planned():
    """One client: a motion runs, then ``program`` (an endless loop: plans until max_plan_s) and
    ``stop`` back to back. The stop is answered at once, the program is refused as stopped (by the stop), and the
    drives' targets decelerate from the moment of the stop."""
    import msgpack
    import socket
    cfg = _cfg(max_plan_s=60.0)
    d = tempfile.mkdtemp(prefix="hxpl", dir="/tmp")
    daemon = Daemon(cfg, realtime=False)
    tap = RingTap(cfg, [seg.name for seg in daemon.sim.segments]).start()
    srv = SocketServer(daemon, cfg, os.path.join(d, "p.sock")).start()
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.connect(srv.socket_path)
        unpacker = msgpack.Unpacker(raw=False)
        pose = np.array(cfg.home_pose, dtype=float)
        pose[0] += 100.0
        daemon.move_to(pose, 100.0)                  # motion under way (about 1 s)
        time.sleep(0.2)
        s.sendall(P.encode({"id": 1, "op": "program", "text": ENDLESS, "name": "endless.ngc"}))
        time.sleep(0.3)                              # the program is being interpreted now
        t0 = time.monotonic()
        s.sendall(P.encode({"id": 2, "op": "stop"}))
        replies = []
        s.settimeout(10.0)
        while len(replies) < 2:
            unpacker.feed(s.recv(65536))
            for m in unpacker:
                replies.append((time.monotonic() - t0, m))
        by_id = {m["id"]: (t, m) for t, m in replies}
        # the stop answered at once; the program refused *because of* the stop (its message says so): the
        # stop acted while the program was being planned.  Which of the two replies is written first is
        # up to the threads that send them (the refusal may leave before the stop's own reply)
        t_stop, stop_reply = by_id[2]
        assert stop_reply["ok"] and t_stop < 2.0, (t_stop, stop_reply)
        prog_reply = by_id[1][1]
        assert not prog_reply["ok"] and "stopped while" in prog_reply["error"]["message"], prog_reply
        # on the frames: moving when the stop came, at rest afterwards
        time.sleep(0.5)
        tap.drain()
        tt, L = tap.lengths_mm(t0 - 0.02)
        v = np.max(np.abs(np.diff(L, axis=0)), axis=1) / cfg.cycle.period_s
        assert v[0] > 10.0 and v[-1] < 1e-6
        assert daemon.status()["state"] == "idle"
    finally:
        s.close()
        srv.close()
        daemon.close()
        tap.stop()
