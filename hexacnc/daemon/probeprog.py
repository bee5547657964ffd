"""Programs and MDI with G38.2-G38.5: run up to a probe, probe, set #5061-#5070, go on.

LinuxCNC synchronises read-ahead at a probe: the interpreter stops there, the probe move runs until
the probe input changes, the result parameters are set, and only then are the following lines
interpreted (a program may branch on, or move to, #5061..).  A program whose text has a G38 word
takes this path (:func:`has_probe_words`; ``Daemon.load_program`` and the operator's
``load_program`` hand it over):

1. interpret from the start in the bounded planning child (:mod:`.planproc`) with the results of
   the probes done so far (:class:`hexacnc.gcode.probesync.SyncInterpreter`) up to the next probe;
   plan and run the blocks after the last probe (one job; pause, resume, stop and feed override
   work on it as on any program), wait until it has ended;
2. run the probe move (:func:`hexacnc.daemon.calibprobe.probe_move`: a G53 G1 move of the tool
   reference point toward the target at the programmed feed; at the probe edge the daemon's
   controlled stop decelerates along the path within the strut limits; the edge goes to the probe
   log);  no edge: G38.2/G38.4 abort the program with the reason naming the line (``status``
   ``program.aborted``), G38.3/G38.5 set #5070 = 0 and go on;
3. back to 1 with one more result; the interpreter continues from where the machine stopped.

The ``program`` (or ``mdi``) reply comes when the program has ended: ``blocks``, ``duration_s``
(planned motion, probe moves excluded), ``probes`` (one entry per probe: ``line``, ``code``,
``contact``, ``tip_mm`` the controlled point at the edge in the machine frame, ``log_index``).
"""
from __future__ import annotations

import logging
import re
import time
from typing import Any

import numpy as np

from ..errors import HexacncError, PlanError

log = logging.getLogger("hexacnc.probeprog")

_G38 = re.compile(r"g\s*0*38\s*\.\s*[2-5]|m\s*0*66(?![\d.])", re.IGNORECASE)
MAX_PROBES = 10_000


#: the pattern of :func:`has_probe_words` for :func:`.progtext.scan`: where neither "38" nor "66" occurs, none
PROBE_WORDS = (lambda s: "38" in s or "66" in s, _G38)


def has_probe_words(text) -> bool:
    """Does the program text (str or pieces) contain a G38.2..G38.5 or an M66 word (it then runs
    synchronised)?  Scanned in pieces: a stop never waits behind a scan of a large program."""
    from .progtext import scan
    return bool(scan({"probe": PROBE_WORDS}, text))


def plan_segment(cfg, text: str, name: str, start_rad, period_s: float, tip0, state, known, tip_check):
    """Planning child: interpret with the ``known`` probe results up to the next probe, plan what
    comes after the last known one (``tip_check(cfg, program)``: MDI's tool-tip limits, or None).
    Returns ``(plan or None, blocks, probe dict or None, state after the program or None, messages)``."""
    from ..gcode import blocks as B
    from ..gcode.probesync import ProbeSync, make_sync_interpreter, segment_after
    from ..kinematics import Hexapod
    from ..planner import plan_program as planner_plan
    cls = make_sync_interpreter(known)
    new_state, messages = None, []
    try:
        if state is None:
            from ..gcode.factory import machine_defaults
            kw = machine_defaults(cfg)
            kw["start_pose"] = [float(v) for v in tip0]
            prog = cls(text, name, **kw).run()
        else:
            from ..state.machine import interpret
            prog, new_state = interpret(text, name, cfg, tip0, state, interpreter=cls)
        blocks, messages = prog.blocks, list(prog.messages)
    except ProbeSync as exc:
        blocks, new_state = exc.interpreter.blocks, None
    seg, probe = segment_after(blocks, len(known))
    if tip_check is not None:
        tip_check(cfg, type("Segment", (), {"motion_blocks": [b for b in seg if b.kind in B.MOTION_KINDS]}))
    from .ioprog import check_io, plan_with_io
    from .program import tool_tip_pose_deg
    check_io(cfg, seg)
    plan = None
    if any(b.kind in B.MOTION_KINDS or b.kind == B.IO for b in seg):   # outputs alone: a standstill plan
        plan = plan_with_io(seg, cfg, planner_plan, hexapod=Hexapod(cfg), period_s=period_s,
                            start_pose=tool_tip_pose_deg(cfg, start_rad))
    info = None
    if probe is not None and probe.kind == B.IO:             # M66: wait on a digital input
        check_io(cfg, [probe], waits=True)
        ex = probe.extra
        drive, bit = cfg.io.digital_in[int(ex["index"])]
        info = {"line": int(probe.line), "code": "M66", "wait": True, "input": int(ex["index"]),
                "drive": drive, "bit": bit, "mode": ex["mode"], "timeout_s": float(ex["timeout_s"])}
    elif probe is not None:
        ex = probe.extra
        info = {"line": int(probe.line), "code": ex["code"], "toward": bool(ex["toward"]),
                "must": bool(ex["error_if_no_contact"]), "start": [float(v) for v in probe.start],
                "end": [float(v) for v in probe.end], "feed_mm_s": float(probe.feed_mm_s),
                "tool_length_mm": float(probe.tool_length_mm or 0.0)}
    return plan, len(seg), info, new_state, messages


def _tool_vector(cfg, abc_deg, tool_length_mm: float) -> np.ndarray:
    from ..pose import matrix_from_euler
    R = matrix_from_euler(*np.radians(np.asarray(abc_deg, dtype=float)))
    return R @ (float(tool_length_mm) * np.asarray(cfg.tool.axis_platform, dtype=float))


def _tip_deg(cfg, platform_rad, tool_length_mm: float) -> np.ndarray:
    from .jog import tip_poses
    X = np.asarray(platform_rad, dtype=float)
    return tip_poses(cfg, np.r_[X[:3], np.degrees(X[3:6])][None, :], tool_length_mm)[0]


class _Run:
    """One probe-synchronised program run on a daemon (see the module text)."""

    def __init__(self, daemon: Any, text: str, name: str, operator: Any, tip_check):
        self.d, self.text, self.name, self.op, self.tip_check = daemon, text, name, operator, tip_check
        with daemon.lock:
            daemon._require_motion_ok()
            self.start = daemon._planned_start()
            self.stops = daemon._stops
        self.state = operator.store.snapshot() if operator is not None else None
        self.tip0 = (operator.tip_pose_deg(self.start) if operator is not None
                     else _tip_deg(daemon.cfg, self.start, 0.0))
        self.known: list = []
        self.probes: list = []
        self.inputs: list = []          #: M66: one entry per wait (line, input, mode, value = #5399)
        self.blocks = 0
        self.duration_s = 0.0

    def _check_stop(self) -> None:
        if self.d._stops != self.stops or self.d.closed:
            raise HexacncError(f"{self.name}: stopped")

    def _plan(self):
        from .planproc import PlanJob
        d = self.d
        cfg = self.op.run_cfg() if self.op is not None else d.cfg
        pj = PlanJob(cfg, self.text, self.name, self.start, d.period_s, work=plan_segment,
                     work_args=(self.tip0, self.state, tuple(self.known), self.tip_check))
        with d.lock:
            d._planning.add(pj)
            if d._stops != self.stops:
                pj.cancel()
        try:
            return pj.result()
        finally:
            with d.lock:
                d._planning.discard(pj)

    def _run_plan(self, plan, nblocks: int) -> None:
        from .feeding import Job
        from .program import ProgramSource
        d = self.d
        p0 = np.asarray(plan.start_pose_platform, dtype=float)
        if float(np.max(np.abs(p0 - np.asarray(self.start, dtype=float)))) > 1e-6:
            raise PlanError(f"{self.name} does not continue where the machine is", limit="start")
        src = ProgramSource(plan, d.period_s, self.name)
        if self.op is not None:
            self.op.carry_overrides(src)
        job = Job(name=self.name, source=src, start_rad=self.start,
                  end_rad=np.asarray(plan.end_pose_platform, dtype=float), blocks=nblocks,
                  duration_s=float(plan.duration_s))
        with d.lock:
            self._check_stop()
            if float(np.max(np.abs(d._planned_start() - self.start))) > 1e-9:
                raise HexacncError("another motion was queued while this program was planned; send it again")
            d._queue(job)
        self.blocks += nblocks
        self.duration_s += float(plan.duration_s)
        self._wait_done()

    def _wait_done(self) -> None:
        while True:
            st = self.d.wait(1.0)
            self._check_stop()
            if st.get("state") == "fault":
                raise HexacncError(f"{self.name}: aborted: {(st.get('fault') or {}).get('message', 'fault')}")
            if st.get("state") == "idle" and self.d.current is None and not self.d.queue:
                return

    def _probe(self, info: dict) -> None:
        from ..gcode.probesync import ProbeResult
        from .calibprobe import probe_move
        cfg, L = self.d.cfg, info["tool_length_mm"]
        end = np.asarray(info["end"], dtype=float)
        tv = _tool_vector(cfg, end[3:], L)
        ref = np.r_[end[:3] - tv, end[3:]]
        mode = info["code"][1:]
        try:
            r = probe_move(self.d, ref, info["feed_mm_s"] * 60.0, mode)
        except HexacncError as exc:
            self._check_stop()
            raise HexacncError(f"{self.name}: line {info['line']}: {exc}") from None
        with self.d.lock:
            self.stops = self.d._stops          # the probe's own stop at the edge
            self.start = self.d._planned_start()
        stop_tip = _tip_deg(cfg, self.start, L)
        if r.get("contact"):
            p = r["params"]
            contact = np.array([p[str(5061 + i)] for i in range(6)], dtype=float)
            contact[:3] += tv
        else:
            contact = stop_tip.copy()
        self.known.append(ProbeResult(bool(r.get("contact")), tuple(map(float, contact)), tuple(map(float, stop_tip))))
        self.probes.append({"line": info["line"], "code": info["code"], "contact": bool(r.get("contact")),
                            "tip_mm": contact.tolist(), "log_index": r.get("log_index")})

    def _wait_input(self, info: dict) -> None:
        from ..gcode.probesync import InputResult
        from .dioread import wait_input
        with self.d.lock:
            self.start = self.d._planned_start()      # the next segment starts where the last one ended
        try:
            v = wait_input(self.d, info["drive"], info["bit"], info["mode"], info["timeout_s"], self._check_stop)
        except HexacncError as exc:
            self._check_stop()
            raise HexacncError(f"{self.name}: line {info['line']}: M66 P{info['input']}: {exc}") from None
        self.known.append(InputResult(float(v)))
        self.inputs.append({"line": info["line"], "input": info["input"], "mode": info["mode"], "value": v})

    def run(self) -> dict:
        while True:
            self._check_stop()
            plan, nblocks, info, new_state, messages = self._plan()
            if plan is not None:
                self._run_plan(plan, nblocks)
            if info is None:
                break
            if len(self.known) >= MAX_PROBES:
                raise HexacncError(f"{self.name}: more than {MAX_PROBES} probes (endless loop?)")
            if info.get("wait"):
                self._wait_input(info)
            else:
                self._probe(info)
        if self.op is not None and new_state is not None:
            self.op.store.commit(new_state)
        return {"blocks": self.blocks, "duration_s": self.duration_s, "probes": self.probes, "messages": messages,
                "inputs": self.inputs}


def run_probe_program(daemon: Any, text: str, name: str, operator: Any = None, tip_check=None) -> dict:
    """Run a program (or MDI) with G38.x probe-synchronised; returns when it has ended.  A failure
    (no contact for G38.2/G38.4, a fault, a stop) is recorded as the program's abort reason.
    ``operator``: interpret from its persistent state and commit the state after the program;
    ``tip_check``: a module-level ``f(cfg, program)`` run on each segment (MDI's tool-tip limits)."""
    run = _Run(daemon, text, name, operator, tip_check)
    try:
        return run.run()
    except HexacncError as exc:
        line = run.probes[-1]["line"] if run.probes else 0
        m = re.search(r"line (\d+)", str(exc))
        with daemon.lock:
            daemon.last_program = {"name": name, "line": int(m.group(1)) if m else line, "percent": None,
                                   "time_left_s": None, "aborted": str(exc), "t": time.time()}
        log.warning("%s aborted: %s", name, exc)
        raise


__all__ = ["has_probe_words", "run_probe_program", "plan_segment"]
