"""The operator's fields of the status reply (added by :class:`~.operator.Operator.status`).

``tool_tip`` {``machine``, ``work``} (x y z mm, a b c deg: the tool tip of the tool in the
spindle; ``work`` relative to the active work origin = offset + G92), ``work_offset`` (name and
origin), ``tool`` (number, length), ``feed`` (``programmed_mm_min`` of the line being executed,
``actual_mm_s`` of the tool tip from successive status reads), ``overrides`` (feed, rapid,
max_feed), ``block`` (source text of the line), ``modal`` (G/M/F/S words the interpreter was left
in), ``message`` (last (MSG,...) passed), ``elapsed_s`` / ``remaining_s``, ``why_idle`` (why the
machine is not moving, null when it moves), ``referenced``, ``jog``, and ``progress`` (the same
map as ``program``, the name docs/protocol.md used).
"""
from __future__ import annotations

import math
import threading
import time

import numpy as np

from ..state.machine import SYSTEMS
from .progtext import TextLines


def modal_text(st, modal: dict) -> str:
    """Modal state as G-code words (``G1 G17 G21 G90 G94 G54 G64 T1 M5 M9 F600``)."""
    if not modal:
        return f"{SYSTEMS[st.system - 1]} T{st.tool}"
    mot = modal.get("motion", 800)
    words = [f"G{mot // 10}" if mot % 10 == 0 else f"G{mot / 10:g}",
             {170: "G17", 180: "G18", 190: "G19"}.get(modal.get("plane", 170), "G17"),
             "G21" if modal.get("u", 1.0) == 1.0 else "G20",
             "G90" if modal.get("absolute", True) else "G91",
             "G93" if modal.get("inverse_time") else "G94",
             SYSTEMS[st.system - 1],
             "G61" if modal.get("exact_stop") else "G64",
             f"T{st.tool}",
             {1: "M3", -1: "M4"}.get(modal.get("spindle_dir", 0), "M5"),
             "M8" if modal.get("flood") else ("M7" if modal.get("mist") else "M9"),
             f"F{modal.get('feed', 0.0):g}", f"S{modal.get('rpm', 0.0):g}"]
    return " ".join(words)


class OperatorStatus:
    def __init__(self, op):
        self.op = op
        self.lock = threading.Lock()
        self.name = None
        self.lines = TextLines("")
        self.feeds = {}.get             #: line -> programmed feed (mm/min) or None
        self.messages = list     #: () -> [(line, text)] of the program's (MSG, ...) comments
        self.duration_s = 0.0
        self.started = None
        self.ended = None
        self._last_tip = None
        self._speed = 0.0

    def program_loaded(self, name: str, text: str, prog, duration_s: float) -> None:
        """``prog``: the interpreted program (its blocks), or a streamed one (a
        :class:`~hexacnc.daemon.planstream.StreamPlan`: the feeds come from its windows as they run)."""
        feeds = getattr(prog, "feed_at", None)
        if feeds is None:
            feeds = {}
            for b in prog.motion_blocks:
                f = b.feed_mm_s
                feeds[b.line] = 60.0 * f if f is not None and b.kind != "rapid" else None
            feeds = feeds.get
        with self.lock:
            self.name = name
            self.lines = TextLines(text)
            self.feeds = feeds
            self.messages = (lambda: prog.messages) if hasattr(prog, "feed_at") else list(prog.messages).copy
            self.duration_s = duration_s
            self.started = None
            self.ended = None

    def _times(self, st: dict, running: bool, name) -> tuple:
        now = time.monotonic()
        prog = st.get("program") or {}
        if running and name == self.name and self.started is None:
            # first seen running: back-date by the planned time done (exact when seen at the start)
            done = self.duration_s * float(prog.get("percent") or 0.0) / 100.0
            self.started, self.ended = now - done, None
        if not running and self.started is not None and self.ended is None:
            self.ended = now
        elapsed = None if self.started is None else (self.ended or now) - self.started
        remaining = prog.get("time_left_s") if running else (0.0 if prog else None)
        if st.get("state") == "stopping":
            remaining = 0.0
        return elapsed, remaining

    def add(self, st: dict) -> dict:
        op = self.op
        ms = op.store.state
        pc = st.get("pose_cmd")
        prog = st.get("program")
        st["progress"] = prog
        if pc is not None:
            X = np.r_[pc[:3], np.radians(pc[3:6])]
            tip = op.tip_pose_deg(X)
            origin = ms.work_origin()
            work = [float(tip[i] - origin[i]) for i in range(6)]
            now = time.monotonic()
            if self._last_tip is not None and 1e-3 < now - self._last_tip[0] < 2.0:
                self._speed = float(np.linalg.norm(tip[:3] - self._last_tip[1][:3])) / (now - self._last_tip[0])
            if self._last_tip is None or now - self._last_tip[0] > 0.02:
                self._last_tip = (now, tip)
            st["tool_tip"] = {"machine": [float(v) for v in tip], "work": work}
        st["work_offset"] = {"name": SYSTEMS[ms.system - 1], "origin": ms.work_origin()}
        st["tool"] = {"number": ms.tool, "length_mm": ms.tool_length_mm}
        line = st.get("line") or (prog or {}).get("line") or 0
        running = st.get("state") in ("running", "paused", "stopping")
        with self.lock:
            name = (prog or {}).get("name")
            ours = name is not None and name == self.name
            block = self.lines[line - 1] if ours and 0 < line <= len(self.lines) else None
            fprog = self.feeds(line) if ours else None
            msg = None
            if ours:
                for ln, text in self.messages():
                    if ln <= line or not running:
                        msg = text
            elapsed, remaining = self._times(st, running, name)
        st["block"] = block
        st["feed"] = {"programmed_mm_min": fprog, "actual_mm_s": round(self._speed, 3) if running else 0.0}
        st["overrides"] = {"feed": op.feed, "rapid": op.rapid, "max_feed": op.max_feed,
                           "optional_stop": op.optional_stop, "block_delete": op.block_delete}
        st["modal"] = modal_text(ms, ms.modal)
        st["message"] = msg
        st["elapsed_s"] = None if elapsed is None else round(elapsed, 3)
        st["remaining_s"] = None if remaining is None else round(float(remaining), 3)
        st["referenced"] = op.referenced
        st["reference_lost"] = None if st["referenced"] else op.ref.lost
        ji = op.jog_info
        src = op.active_jog()
        st["jog"] = None if ji is None or src is None else dict(ji, stopping=src.stopping)
        st["why_idle"] = self.why_idle(st)
        return st

    def why_idle(self, st: dict) -> str | None:
        op = self.op
        state = st.get("state")
        f = st.get("fault")
        if state == "fault":
            return "fault: " + (f.get("message", "") if isinstance(f, dict) else str(f)) + " (hexacnc reset)"
        if not st.get("drives_enabled", True):
            return "drives disabled (hexacnc enable)"
        if state == "paused":
            return "paused (hexacnc resume)"
        if state == "stopping":
            return "stopping"
        if state == "running":
            if op.feed == 0.0:
                return "feed override 0 % (hexacnc feed)"
            return None
        if op.cfg.operator.homing.required and not op.referenced:
            lost = op.ref.lost
            return "not referenced" + (f": {lost['reason']}" if lost else "") + " (hexacnc home)"
        return "idle: no program or jog"


def fmt_num(v, digits: int = 3) -> str:
    return f"{v:.{digits}f}" if isinstance(v, (int, float)) and math.isfinite(v) else "-"
