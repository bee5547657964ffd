"""A fake Daemon with the real Daemon's API, for the socket-protocol tests (and tests of the fake).

Program text: one block per non-empty line; a line containing ``BAD`` is a G-code
error, ``UNSUP`` an unsupported word, ``FAR`` a limit violation, ``FAULT`` drives
the fake into fault when reached, ``SLOWLOAD`` makes loading take 0.5 s.
Each block takes ``block_s`` seconds.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from hexacnc.errors import GcodeError, HexacncError, PlanError


pytestmark = pytest.mark.e2e


class FakeDaemon:
    def __init__(self, block_s: float = 0.02):
        self.block_s = block_s
        self.cv = threading.Condition()
        self.state = "idle"
        self.blocks: list[tuple[int, str]] = []
        self.index = 0
        self.name = None
        self.fault = None
        self.result = None
        self.calls: list[str] = []
        self.t_block = 0.0
        self.stop_at = 0.0
        self.closed = False
        self.load_threads: set[str] = set()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    # -- API --------------------------------------------------------------
    def hello(self) -> dict:
        return {"machine": "fake-hexapod", "versions": {"fake": 1}, "cycle_period_s": 0.0005}

    def load_program(self, text: str, name: str) -> dict:
        self.calls.append("load_program")
        self.load_threads.add(threading.current_thread().name)
        if "SLOWLOAD" in text:
            time.sleep(0.5)
        blocks = []
        for i, line in enumerate(text.splitlines(), 1):
            s = line.strip()
            if not s:
                continue
            if "BAD" in s:
                raise GcodeError("bad word 'Q'", line=i, column=s.index("BAD") + 1, code="gcode")
            if "UNSUP" in s:
                raise GcodeError("G33 is not supported", line=i, column=1, code="unsupported")
            if "FAR" in s:
                raise PlanError("strut 3 length 1400.000 mm above max 1350", line=i, limit="strut_length",
                                code="limit")
            blocks.append((i, s))
        with self.cv:
            if self.state == "fault":
                raise HexacncError("the daemon is in fault: reset first")
            if self.state != "idle":
                raise HexacncError("a program is running")
            self.blocks, self.index, self.name = blocks, 0, name
            self.result = None
            if blocks:
                self.state = "running"
                self.t_block = time.monotonic()
            self.cv.notify_all()
        return {"blocks": len(blocks), "duration_s": len(blocks) * self.block_s}

    def pause(self):
        self.calls.append("pause")
        with self.cv:
            if self.state != "running":
                raise HexacncError("nothing to pause")
            self.state = "paused"
            self.cv.notify_all()

    def resume(self):
        self.calls.append("resume")
        with self.cv:
            if self.state != "paused":
                raise HexacncError("not paused")
            self.state = "running"
            self.t_block = time.monotonic()
            self.cv.notify_all()

    def stop(self):
        self.calls.append("stop")
        with self.cv:
            if self.state in ("running", "paused"):
                self.state = "stopping"
                self.stop_at = time.monotonic() + 0.05
            self.cv.notify_all()

    def reset(self):
        self.calls.append("reset")
        with self.cv:
            if self.state == "fault":
                self.state = "idle"
                self.fault = None
            self.cv.notify_all()

    def status(self) -> dict:
        with self.cv:
            n = len(self.blocks)
            line = self.blocks[min(self.index, n - 1)][0] if n else 0
            pct = 100.0 * self.index / n if n else 0.0
            return {
                "state": self.state,
                "pose_cmd": np.array([0.0, 0.0, -900.0 + self.index, 0.0, 0.0, 0.0]),
                "pose_act": [0.0, 0.0, -900.0 + self.index, 0.0, 0.0, 0.0],
                "struts_cmd_mm": np.full(6, 1000.0 + self.index),
                "struts_act_mm": np.full(6, 1000.0 + self.index),
                "line": line,
                "fault": self.fault,
                "result": self.result,
                "cycle": {"cycles": 1234, "overruns": 0, "lateness_us": {"p50": 3.0, "p99": float("nan")}},
                "progress": {"name": self.name, "line": line, "percent": pct,
                             "time_left_s": (n - self.index) * self.block_s},
            }

    def wait(self, timeout_s: float) -> dict:
        deadline = time.monotonic() + timeout_s
        with self.cv:
            while self.state not in ("idle", "fault"):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self.cv.wait(left)
        return self.status()

    def close(self):
        self.closed = True

    # -- simulation -------------------------------------------------------
    def _run(self):
        while not self.closed:
            time.sleep(0.005)
            with self.cv:
                now = time.monotonic()
                if self.state == "running" and now - self.t_block >= self.block_s:
                    self.t_block = now
                    if "FAULT" in self.blocks[self.index][1]:
                        self.state = "fault"
                        self.fault = f"line {self.blocks[self.index][0]}: following error strut 2"
                        self.result = "fault"
                    else:
                        self.index += 1
                        if self.index >= len(self.blocks):
                            self.state = "idle"
                            self.result = "finished"
                    self.cv.notify_all()
                elif self.state == "stopping" and now >= self.stop_at:
                    self.state = "idle"
                    self.result = "stopped"
                    self.cv.notify_all()


def test_fake_runs_a_program_to_the_end():
    d = FakeDaemon(block_s=0.01)
    try:
        r = d.load_program("G0 X1\nG1 X2\n\nG1 X3\n", "p")
        assert r["blocks"] == 3
        st = d.wait(5.0)
        assert st["state"] == "idle" and st["result"] == "finished"
        assert st["progress"]["percent"] == pytest.approx(100.0)
    finally:
        d.close()


def test_fake_refuses_bad_lines_with_line_numbers():
    d = FakeDaemon()
    try:
        with pytest.raises(GcodeError) as ei:
            d.load_program("G0 X1\nG1 BAD\n", "p")
        assert ei.value.line == 2
        with pytest.raises(PlanError) as pi:
            d.load_program("G0 X1\nG0 X2\nG0 FAR\n", "p")
        assert pi.value.line == 3 and pi.value.limit == "strut_length"
        assert d.status()["state"] == "idle"
    finally:
        d.close()
