"""Operator control of a running :class:`hexacnc.daemon.core.Daemon`: overrides, drives on/off,
referencing, jog, MDI, the persistent interpreter state and the operator's status fields.

``Operator(daemon)`` is attached by the socket server (``daemon.operator``); its methods raise
:class:`~hexacnc.errors.HexacncError` with a ``code`` from the protocol's error codes on refusal.

* Programs and MDI lines are interpreted from the persistent state (:mod:`hexacnc.state`: work
  offsets, G92, G28/G30, tool table, tool in the spindle) and, for MDI, the modal state the last
  program or MDI line left.  A program's state changes (G10, G92, G43, T/M6, ...) take effect when
  the daemon accepts it - the whole program is interpreted and checked before it moves - and are
  written to the files at once, so the next program and a restarted daemon start from them.
* Overrides persist: a new program starts at the feed and rapid overrides in force.
* ``[homing] required``: programs, MDI and Cartesian jogs are refused until the machine is
  referenced (absolute encoders: at start; ``cia402``: by ``home``), and again once the reference
  is lost (:mod:`.reference`: a fault, a drive's boot-up, an encoder error, a failed homing run).
"""
from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import replace

import numpy as np

from ..errors import HexacncError, PlanError
from ..config.operator import tip_box, tip_violation
from ..state import MachineState, StateStore, ToolEntry, interpret
from . import shm as S
from .motion import scan_words
from .jog import JogLimitError, JogSource, plan_jog, tip_poses, tool_point_platform
from .opstatus import OperatorStatus
from .reference import ReferenceWatch

log = logging.getLogger("hexacnc.daemon.operator")

#: deadman watchdog period (s)
WATCHDOG_S = 0.002
#: longest MDI text (bytes)
MAX_MDI_BYTES = 4096


class OperatorError(HexacncError):
    def __init__(self, message: str, code: str = "refused", line: int | None = None):
        super().__init__(message)
        self.code = code
        self.line = line


class Operator:
    """Operator functions over ``daemon`` (see module doc)."""

    def __init__(self, daemon, cfg=None, state_dir=None):
        self.daemon = daemon
        self.cfg = cfg if cfg is not None else daemon.cfg
        self.store = StateStore(self.cfg, state_dir)
        self.feed = 1.0
        self.rapid = 1.0
        self.optional_stop = bool(self.cfg.operator.optional_stop)    #: the M1 switch
        self.block_delete = bool(self.cfg.operator.block_delete)      #: skip '/' lines of programs taken
        self.max_feed = float(self.cfg.operator.max_feed_override)
        hm = self.cfg.operator.homing
        self.ref = ReferenceWatch(hm.method, hm.method == "absolute")
        if daemon.sh is not None:
            self.ref.baseline(daemon.sh.h)
        daemon.ref_watch = self.ref       # polled by the feeder thread and before a reset
        self.pivot_mm = (None if self.cfg.operator.pivot_mm is None
                         else np.asarray(self.cfg.operator.pivot_mm, dtype=float))
        self.lock = threading.RLock()
        self.jog_src: JogSource | None = None
        self.jog_job = None
        self.jog_info: dict | None = None
        self._deadline = math.inf
        self._watch: threading.Thread | None = None
        self._closed = False
        self.status_view = OperatorStatus(self)

    # ------------------------------------------------------------------ helpers
    def _motion_checks(self, what: str, cartesian: bool = True) -> None:
        d = self.daemon
        if d.sh is None or not d.alive:
            raise OperatorError("the daemon is not running", "fault")
        st = d.sh.h[S.H_STATE]
        if st == S.ST_FAULT:
            raise OperatorError(f"{what} refused: the daemon is in fault; reset first", "fault")
        if st == S.ST_DISABLED:
            raise OperatorError(f"{what} refused: the drives are disabled (hexacnc enable)", "invalid_state")
        if cartesian and self.cfg.operator.homing.required and not self.referenced:
            lost = self.ref.lost
            why = f": {lost['reason']}" if lost else ""
            raise OperatorError(f"{what} refused: the machine is not referenced{why} ([homing] required; "
                                f"hexacnc home)", "invalid_state")

    @property
    def referenced(self) -> bool:
        """The struts' reference can be trusted (:mod:`.reference`)."""
        sh = self.daemon.sh
        return self.ref.poll(sh.h) if sh is not None else self.ref.referenced

    def _idle_checks(self, what: str) -> None:
        d = self.daemon
        with d.lock:
            if d.current is not None or d.queue:
                name = d.current.name if d.current is not None else d.queue[0].name
                raise OperatorError(f"{what} refused: {name!r} is running; stop it or wait", "busy")
            if d.sh.h[S.H_STATE] in (S.ST_RUNNING, S.ST_STOPPING) or d.stop_requested:
                raise OperatorError(f"{what} refused: the machine is moving", "busy")

    def active_jog(self) -> JogSource | None:
        """The jog source while its job is queued or running (not after it ended or was dropped)."""
        src, job = self.jog_src, self.jog_job
        if src is None or job is None or src.finished:
            return None
        d = self.daemon
        with d.lock:                      # the feeder moves jobs between queue and current under it
            return src if (d.current is job or job in d.queue) else None

    def tool_length_mm(self) -> float:
        return self.store.state.tool_length_mm

    def tip_pose_deg(self, platform_rad) -> np.ndarray:
        X = np.asarray(platform_rad, dtype=float)
        P = np.r_[X[:3], np.degrees(X[3:6])]
        return tip_poses(self.cfg, P[None, :], self.tool_length_mm())[0]

    def pivot_platform(self) -> np.ndarray:
        if self.pivot_mm is not None:
            return self.pivot_mm
        return tool_point_platform(self.cfg, self.tool_length_mm())

    # ------------------------------------------------------------------ programs and MDI
    def carry_overrides(self, src) -> None:
        """The overrides and the M1 switch in force, on a new whole-plan :class:`ProgramSource` (from its
        first row: it has not run)."""
        src.sampler.user = src.sampler.f = min(self.feed, 2.0)
        src.sampler.set_rapid_override(self.rapid)
        src.set_optional_stop(self.optional_stop)

    def run_cfg(self):
        """The machine description programs are interpreted with: the daemon's, with the operator's
        block-delete switch (it acts on the programs taken after it, which are interpreted whole)."""
        cfg = self.cfg
        if bool(cfg.operator.block_delete) == self.block_delete:
            return cfg
        return cfg.replace(operator=replace(cfg.operator, block_delete=self.block_delete))

    def load_program(self, text, name: str, mdi: bool = False, stops: int | None = None) -> dict:
        """Interpret from the persistent state, plan, check and queue; commit the new state.  ``text``: str,
        or the chunks of an upload (list of str); ``stops``: the daemon's stop count when the program was
        taken (a stop after it refuses the program)."""
        from .progtext import joined
        from .core import Job
        from .program import ProgramSource
        d = self.daemon
        what = "MDI" if mdi else f"program {name!r}"
        self._motion_checks(what)
        if mdi:
            self._idle_checks("MDI")
        if self.active_jog() is not None:
            raise OperatorError(f"{what} refused: a jog is running", "busy")
        from .ioprog import IO_WORDS
        from .probeprog import PROBE_WORDS, run_probe_program
        words = scan_words(d, text, {"probe": PROBE_WORDS, "io": IO_WORDS}, name, stops)
        if "probe" in words:               # G38.x: run probe-synchronised, reply at the end
            return run_probe_program(d, joined(text), name, self, _check_tip_limits if mdi else None)
        if not mdi and "io" not in words:
            return self._load_streamed(text, name, stops)
        text = joined(text)
        with d.lock:
            stops = d._stops if stops is None else stops
            d._require_motion_ok()
            start = d._planned_start()
        state = self.store.snapshot()
        tip0 = self.tip_pose_deg(start)
        # interpreted and planned in a child with bounded memory and time ([daemon] max_plan_memory_mb,
        # max_plan_s), started outside the lock; a stop kills it (issue 13: the control path never waits)
        from .planproc import PlanJob
        pj = PlanJob(self.run_cfg(), text, name, start, d.period_s, work=interpret_and_plan,
                     work_args=(tip0, state, mdi))
        with d.lock:
            d._planning.add(pj)
            if d._stops != stops:
                pj.cancel()
        try:
            plan, prog, new_state = pj.result()
        finally:
            with d.lock:
                d._planning.discard(pj)
        if plan is None:
            self.store.commit(new_state)
            self.status_view.program_loaded(name, text, prog, 0.0)
            return {"blocks": len(prog.blocks), "duration_s": 0.0, "moved": False}
        p0 = np.asarray(plan.start_pose_platform, dtype=float)
        if float(np.max(np.abs(p0 - np.asarray(start, dtype=float)))) > 1e-6:
            raise PlanError(f"{what} does not start where the machine is", limit="start")
        src = ProgramSource(plan, d.period_s, name)
        self.carry_overrides(src)
        job = Job(name=name, source=src, start_rad=start, end_rad=np.asarray(plan.end_pose_platform, dtype=float),
                  blocks=len(prog.blocks), duration_s=float(plan.duration_s))
        with d.lock:
            if float(np.max(np.abs(d._planned_start() - start))) > 1e-9:
                raise OperatorError("another motion was queued while this was planned; send it again", "busy")
            if mdi:
                self._idle_checks("MDI")
            d._queue(job)
        # the files are written outside the daemon's lock (the feeder must never wait for a disk)
        self.store.commit(new_state)
        self.status_view.program_loaded(name, text, prog, float(plan.duration_s))
        return {"blocks": len(prog.blocks), "duration_s": float(plan.duration_s)}

    def _load_streamed(self, text, name: str, stops: int | None = None) -> dict:
        """A program (not MDI, no M62-M68): streamed through validation and windowed planning in bounded
        children as the daemon's own programs (:meth:`~hexacnc.daemon.motion.MotionMixin.load_streamed`),
        interpreted from the persistent state; the state after it is committed once the whole program
        is validated and the program accepted (``[planner] start_before_validated``: when its
        validation ends, while it runs).  Memory: one planning window, whatever the program's length."""
        d = self.daemon
        state = self.store.snapshot()
        done = {"accepted": False, "committed": False}
        lock = threading.Lock()

        def commit(sp) -> None:           # once: after the validation and the acceptance, whichever is last
            with lock:
                if not (done["accepted"] and sp.final_state is not None) or done["committed"]:
                    return
                done["committed"] = True
            self.store.commit(sp.final_state)

        def accept(sp, info: dict, src) -> bool:
            src.sampler.set_override(min(self.feed, 2.0))     # the overrides in force carry over
            src.sampler.set_rapid_override(self.rapid)
            src.set_optional_stop(self.optional_stop)
            # dwells and M0/M1 take their time standing still, as in LinuxCNC: a standstill job
            moves = sp.motion_blocks != 0 or bool(sp.io_blocks) or bool(sp.timed_blocks)
            self.status_view.program_loaded(name, text, sp, float(info["duration_s"]) if moves else 0.0)
            if not moves:                 # settings only (offsets, tools, ...): nothing is queued
                with lock:
                    done["accepted"] = True
                commit(sp)
            return moves

        job, info = d.load_streamed(text, name, state=state, on_valid=commit, accept=accept, stops=stops,
                                    cfg=self.run_cfg())
        if job is None:
            return {"blocks": info["blocks"], "duration_s": 0.0, "moved": False}
        with lock:
            done["accepted"] = True
        commit(job.source.stream)
        return info

    def mdi(self, text: str) -> dict:
        if len(text.encode()) > MAX_MDI_BYTES:
            raise OperatorError(f"MDI text longer than {MAX_MDI_BYTES} bytes", "bad_value")
        if "\x00" in text:
            raise OperatorError("MDI text contains a NUL character", "bad_value")
        return self.load_program(text.rstrip("\n") + "\n", "MDI", mdi=True)

    def _check_soft_limits(self, prog) -> None:
        _check_tip_limits(self.cfg, prog)

    # ------------------------------------------------------------------ overrides
    def set_override(self, feed: float | None = None, rapid: float | None = None,
                     optional_stop: bool | None = None, block_delete: bool | None = None) -> dict:
        if feed is not None:
            f = float(feed)
            if not (math.isfinite(f) and 0.0 <= f <= self.max_feed):
                raise OperatorError(f"feed override {f:g} outside 0 .. {self.max_feed:g} "
                                    f"([planner] max_feed_override)", "bad_value")
        if rapid is not None:
            r = float(rapid)
            if not (math.isfinite(r) and 0.0 <= r <= 1.0):
                raise OperatorError(f"rapid override {r:g} outside 0 .. 1", "bad_value")
        d = self.daemon
        with d.lock:
            if feed is not None:
                self.feed = float(feed)
            if rapid is not None:
                self.rapid = float(rapid)
            job = d.current
            src = getattr(job, "source", None) if job is not None else None
            if block_delete is not None:             # programs taken from now on
                self.block_delete = bool(block_delete)
            if optional_stop is not None:
                self.optional_stop = on = bool(optional_stop)
                for j in d.queue:                    # queued programs: from their start
                    if hasattr(j.source, "set_optional_stop"):
                        j.source.set_optional_stop(on)
                if hasattr(src, "set_optional_stop"):   # the running one: from REWIND_LEAD_S on (an M1 in
                    d._command(lambda: src.set_optional_stop(on))   # the rows already sent passes as it was)
            sampler = getattr(src, "sampler", None)
            if sampler is not None:
                fv, rv = self.feed, self.rapid

                def act():
                    sampler.set_override(fv)
                    sampler.set_rapid_override(rv)
                d._command(act)
            elif src is not None and feed is not None:
                d._command(lambda: src.set_feed_override(self.feed))
        return {"feed": self.feed, "rapid": self.rapid, "max_feed_override": self.max_feed,
                "optional_stop": self.optional_stop, "block_delete": self.block_delete}

    # ------------------------------------------------------------------ drives
    def enable(self, timeout_s: float = 10.0) -> dict:
        """Enable the drives: after ``disable``, or after a start with ``[daemon] enable_at_start``
        false (the daemon waits for this); refused in fault (``reset`` clears it and enables)."""
        d = self.daemon
        st = d.sh.h[S.H_STATE] if d.sh is not None else S.ST_FAULT
        if st == S.ST_FAULT:
            raise OperatorError("enable refused: the daemon is in fault; reset clears it and enables", "fault")
        if st == S.ST_DISABLED or getattr(d, "awaiting_enable", False):
            d.enable(timeout_s)
        out = d.status()
        return {"drives_enabled": d.sh.h[S.H_STATE] in (S.ST_IDLE, S.ST_RUNNING, S.ST_STOPPING),
                "waiting": out.get("waiting"), "state": out.get("state")}

    def disable(self, timeout_s: float = 10.0) -> dict:
        """Controlled stop on the path (if moving), then the drives are disabled."""
        d = self.daemon
        if d.sh is None or not d.alive:
            raise OperatorError("the daemon is not running", "fault")
        self.jog_stop()
        if d.current is not None or d.queue:
            d.stop()
            d.wait(timeout_s)
        if d.sh.h[S.H_STATE] in (S.ST_IDLE, S.ST_RUNNING, S.ST_STOPPING, S.ST_HOMING):
            d.sh.command(S.CMD_DISABLE)
            t_end = time.monotonic() + timeout_s
            while d.sh.h[S.H_STATE] != S.ST_DISABLED and time.monotonic() < t_end:
                if d.sh.h[S.H_STATE] == S.ST_FAULT:
                    break
                time.sleep(0.01)
        return {"drives_enabled": False, "loop_state": S.STATE_NAMES.get(d.sh.h[S.H_STATE], "?")}

    # ------------------------------------------------------------------ homing
    def home(self) -> dict:
        hm = self.cfg.operator.homing
        self._motion_checks("home", cartesian=False)
        self._idle_checks("home")
        if hm.method == "absolute":
            self.ref.mark(self.daemon.sh.h)
            return {"referenced": True, "method": "absolute",
                    "message": "absolute encoders: the struts are referenced from their readings"}
        return self._home_cia402(hm)

    def _home_cia402(self, hm) -> dict:
        """Every strut's drive homes in mode 6, run by the hot loop (:mod:`.homeloop`); waits for it."""
        from .homecodes import DONE, E_UNSUPPORTED, ERROR_TEXT, HOME_TIMEOUT_S, RUNNING
        d = self.daemon
        sh = d.sh
        with d.lock:
            self._idle_checks("home")
            if sh.h[S.H_STATE] != S.ST_IDLE:
                raise OperatorError(f"home refused: the loop is {S.STATE_NAMES.get(sh.h[S.H_STATE], '?')}, "
                                    f"not idle", "invalid_state")
            self.ref.unmark("homing started and did not finish", quiet=True)
            sh.h[S.H_HOME_RESULT] = RUNNING
            seq = sh.command(S.CMD_HOME)
        t_end = time.monotonic() + HOME_TIMEOUT_S + 5.0
        while time.monotonic() < t_end:
            if sh.h[S.H_CMD_ACK] >= seq and sh.h[S.H_HOME_RESULT] != RUNNING \
                    and sh.h[S.H_STATE] != S.ST_HOMING:
                break
            time.sleep(0.01)
        r, strut = sh.h[S.H_HOME_RESULT], sh.h[S.H_HOME_STRUT]
        if r != DONE:
            where = f" (strut {strut})" if strut else ""
            why = ERROR_TEXT.get(r, "no answer from the hot loop" if r == RUNNING else f"code {r}")
            self.ref.unmark(f"home failed{where}: {why}")
            raise OperatorError(f"home failed{where}: {why}", "unsupported" if r == E_UNSUPPORTED else "fault")
        self.ref.mark(sh.h)
        st = d.status()
        return {"referenced": True, "method": "cia402", "homing_method": int(hm.homing_method),
                "offset_mm": [float(v) for v in hm.offset_mm], "struts_act_mm": st.get("struts_act_mm"),
                "message": "every strut referenced by its drive (homing mode 6); back in cyclic synchronous "
                           "position mode"}

    # ------------------------------------------------------------------ jog
    def jog(self, axis: str, frame: str = "base", distance: float | None = None,
            direction: int | None = None, speed: float = 1.0) -> dict:
        """Incremental (``distance``) or continuous (``direction`` +1/-1, deadman) jog."""
        from .core import Job
        from .feeding import JOG_AHEAD_S
        d = self.daemon
        axis = str(axis).lower()
        cart = axis in ("x", "y", "z", "a", "b", "c")
        self._motion_checks("jog", cartesian=cart)
        self._idle_checks("jog")
        if (distance is None) == (direction is None):
            raise OperatorError("jog: give either distance (incremental) or direction (continuous)", "bad_value")
        with d.lock:
            start = d._planned_start()
        X0 = np.r_[start[:3], np.degrees(start[3:6])]
        plan = plan_jog(self.cfg, d.hx, X0, axis, frame, self.pivot_platform(), self.tool_length_mm(), speed)
        if distance is not None:
            s = float(distance)
            if not math.isfinite(s) or s == 0.0:
                raise OperatorError(f"jog: distance {distance!r} must be a non-zero number", "bad_value")
            if s > plan.s_hi or s < plan.s_lo:
                lim, why = (plan.s_hi, plan.why_hi) if s > 0 else (plan.s_lo, plan.why_lo)
                raise JogLimitError(f"jog {axis} {s:+g} {plan.unit} refused: {why} after {lim:+.4f} {plan.unit}")
            target, continuous = s, False
        else:
            if direction not in (1, -1):
                raise OperatorError(f"jog: direction must be +1 or -1, got {direction!r}", "bad_value")
            target, continuous = (plan.s_hi if direction > 0 else plan.s_lo), True
            if abs(target) < 1e-6:
                raise JogLimitError(f"jog {axis} {'+' if direction > 0 else '-'} refused: at the limit "
                                    f"({plan.why_hi if direction > 0 else plan.why_lo})")
        src = JogSource(plan, target, d.period_s, name=f"jog {axis}")
        end = plan.pose_of([target])[0]
        job = Job(name=src.name, source=src, start_rad=np.asarray(start, dtype=float),
                  end_rad=np.r_[end[:3], np.radians(end[3:6])], blocks=1, duration_s=src.duration_s,
                  ahead_s=JOG_AHEAD_S)
        with self.lock:
            self.jog_src = src
            self.jog_job = job
            self.jog_info = {"axis": axis, "frame": frame, "unit": plan.unit, "continuous": continuous,
                             "target": target, "limit": plan.why_hi if target > 0 else plan.why_lo}
            self._deadline = time.monotonic() + self.cfg.operator.jog.deadman_s if continuous else math.inf
        with d.lock:
            self._idle_checks("jog")
            d._queue(job)
        if continuous:
            self._start_watchdog()
        return dict(self.jog_info, duration_s=src.duration_s, s_lo=plan.s_lo, s_hi=plan.s_hi,
                    speed=plan.v, deadman_s=self.cfg.operator.jog.deadman_s)

    def jog_confirm(self) -> dict:
        """The client still holds the key: extend the deadman."""
        with self.lock:
            src = self.active_jog()
            if src is None or src.stopping or not (self.jog_info or {}).get("continuous"):
                raise OperatorError("jog confirm: no continuous jog is running (stopped by the deadman "
                                    "or at a limit?)", "invalid_state")
            self._deadline = time.monotonic() + self.cfg.operator.jog.deadman_s
        return {"jogging": True}

    def jog_stop(self) -> dict:
        with self.lock:
            src = self.active_jog()
            self._deadline = math.inf
        if src is None:
            return {"jogging": False}
        self._stop_jog(src)
        return {"jogging": False}

    def _stop_jog(self, src: JogSource) -> None:
        d = self.daemon
        with d.lock:
            job = d.current
            if job is not None and job.source is src:
                d._command(src.stop)
            else:
                src.stop()

    def _start_watchdog(self) -> None:
        if self._watch is not None and self._watch.is_alive():
            return
        self._watch = threading.Thread(target=self._watchdog, name="hexacnc-jog-deadman", daemon=True)
        self._watch.start()

    def _watchdog(self) -> None:
        d = self.daemon
        if getattr(d, "realtime", False):       # a stop must not wait behind normal work on a loaded machine
            from .rt import sched_fifo
            sched_fifo(max(1, self.cfg.cycle.realtime_priority - 31))
        while not self._closed:
            with self.lock:
                src, deadline = self.active_jog(), self._deadline
            if src is None:
                return
            if time.monotonic() > deadline and not src.stopping:
                log.info("jog deadman: no confirmation for %.0f ms; stopping",
                         1e3 * self.cfg.operator.jog.deadman_s)
                self._stop_jog(src)
                with self.lock:
                    self._deadline = math.inf
                    if self.jog_info is not None:
                        self.jog_info["stopped_by"] = "deadman"
            time.sleep(WATCHDOG_S)

    def set_pivot(self, pivot_mm) -> dict:
        if pivot_mm is None:
            self.pivot_mm = None
        else:
            v = np.asarray(pivot_mm, dtype=float)
            if v.shape != (3,) or not np.all(np.isfinite(v)) or np.any(np.abs(v) > 1e4):
                raise OperatorError(f"pivot_mm must be 3 finite numbers within +-1e4 mm, got {pivot_mm!r}",
                                    "bad_value")
            self.pivot_mm = v
        return {"pivot_mm": None if self.pivot_mm is None else self.pivot_mm.tolist(),
                "pivot": "tool tip" if self.pivot_mm is None else "platform point"}

    # ------------------------------------------------------------------ offsets and tools
    def offsets(self, system: str | None = None, values: dict | None = None, select: str | None = None) -> dict:
        if system is not None or select is not None:
            self._idle_checks("offsets")
        if system is not None and values:
            self.store.set_offset(system, values)
        if select is not None:
            self.store.select(select)
        return self.store.snapshot().offsets_view()

    def tools(self, tool: int | None = None, delete: bool = False, **fields) -> dict:
        if tool is not None:
            self._idle_checks("tools")
            if delete:
                self.store.delete_tool(int(tool))
            else:
                old = self.store.snapshot().tools.get(int(tool), ToolEntry(int(tool), int(tool)))
                e = replace(old, tool=int(tool), pocket=int(fields.get("pocket", old.pocket)),
                            z_offset_mm=float(fields.get("z_mm", old.z_offset_mm)),
                            diameter_mm=float(fields.get("diameter_mm", old.diameter_mm)),
                            comment=str(fields.get("comment", old.comment)))
                self.store.set_tool(e)
        st: MachineState = self.store.snapshot()
        return {"tools": [{"tool": e.tool, "pocket": e.pocket, "z_mm": e.z_offset_mm, "diameter_mm": e.diameter_mm,
                           "comment": e.comment} for e in (st.tools[t] for t in sorted(st.tools))],
                "tool_in_spindle": st.tool, "file": str(self.store.tool_path)}

    # ------------------------------------------------------------------ status
    def status(self, st: dict) -> dict:
        return self.status_view.add(st)

    def close(self) -> None:
        self._closed = True


def _arc_points(b, n: int = 32) -> list:
    """Points along an arc block (for the soft-limit check of MDI)."""
    c = np.asarray(b.center, dtype=float)
    nrm = np.asarray(b.normal, dtype=float)
    p0, p1 = np.asarray(b.start, dtype=float), np.asarray(b.end, dtype=float)
    r0 = p0[:3] - c
    r0 -= nrm * float(nrm @ r0)
    rad = float(np.linalg.norm(r0))
    if rad < 1e-9:
        return []
    u = r0 / rad
    v = np.cross(nrm, u)
    r1 = p1[:3] - c
    ang = math.atan2(float(v @ r1), float(u @ r1))
    if b.clockwise:
        ang = ang - 2 * math.pi if ang > 0 else ang
        ang -= 2 * math.pi * b.turns
    else:
        ang = ang + 2 * math.pi if ang <= 0 else ang
        ang += 2 * math.pi * b.turns
    out = []
    for k in range(1, n):
        t = k / n
        q = p0 + t * (p1 - p0)
        q[:3] = c + float(nrm @ (p0[:3] - c + t * (p1[:3] - p0[:3]))) * nrm \
            + rad * (math.cos(t * ang) * u + math.sin(t * ang) * v)
        out.append(q)
    return out


def interpret_and_plan(cfg, text: str, name: str, start_rad, period_s: float, tip0, state, mdi: bool):
    """The operator's program path, run in the bounded planning child (:mod:`.planproc`): interpret
    from the persistent ``state`` at tool tip ``tip0`` (mm, deg), the tool tip's soft limits for MDI,
    plan. Returns ``(plan or None without motion, program without its blocks, state after it)``."""
    from ..gcode import blocks as B
    from ..kinematics import Hexapod
    from ..planner import plan_program as planner_plan
    prog, new_state = interpret(text, name, cfg, tip0, state)
    if mdi:
        _check_tip_limits(cfg, prog)
    from .ioprog import check_io, plan_with_io
    from .program import tool_tip_pose_deg
    check_io(cfg, prog.blocks)      # I/O the machine does not map: refused before motion, with the line
    plan = None
    # outputs, dwells or M0/M1 without motion: a standstill plan
    if prog.motion_blocks or any(b.kind == B.IO or B.holds_still(b) for b in prog.blocks):
        plan = plan_with_io(prog.blocks, cfg, planner_plan, hexapod=Hexapod(cfg), period_s=period_s,
                            start_pose=tool_tip_pose_deg(cfg, start_rad))
    return plan, prog, new_state


def _check_tip_limits(cfg, prog) -> None:
    """MDI: every end point (and 32 points of each arc) of the tool tip within the [workspace] box."""
    box = tip_box(cfg)
    for b in prog.motion_blocks:
        pts = [b.end]
        if b.kind == "arc" and b.center is not None:
            pts.extend(_arc_points(b))
        for p in pts:
            why = tip_violation(cfg, p, box)
            if why:
                raise PlanError(why, line=b.line, limit="workspace")
