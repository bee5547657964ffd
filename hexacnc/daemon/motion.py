"""Motion commands of the supervisor: queue moves and programs, pause, resume, stop, reset.

:class:`MotionMixin` is part of :class:`hexacnc.daemon.core.Daemon`. Programs are interpreted and
planned in a bounded child process (:mod:`.planproc`) outside the daemon's lock; ``stop`` kills a
plan in progress and drops queued jobs with the reason.
"""
from __future__ import annotations

import time

import numpy as np

from ..errors import HexacncError
from . import shm as S
from .feed import ArraySource, point_to_point
from .feeding import START_TOL, Job


def scan_words(daemon, text, patterns: dict, name: str, stops: int | None) -> set:
    """:func:`.progtext.scan` of a program for ``patterns`` (which path it takes: probing, I/O), ended
    by a stop that comes meanwhile (``daemon._stops`` no longer ``stops``: the program is refused)."""
    from .progtext import Aborted, scan
    if stops is None:
        stops = daemon._stops
    try:
        return scan(patterns, text, abort=lambda: daemon._stops != stops)
    except Aborted:
        raise HexacncError(f"{name}: stopped while it was being interpreted and planned") from None


class MotionMixin:
    """The motion-command half of :class:`~hexacnc.daemon.core.Daemon`."""

    def _require_motion_ok(self) -> None:
        if self.sh is None or not self.alive:
            raise HexacncError("the daemon is not running")
        st = self.sh.h[S.H_STATE]
        if st == S.ST_FAULT:
            raise HexacncError("the daemon is in fault: reset first ("
                               + self._fault_dict(self.sh.read_status())["message"] + ")")
        if st == S.ST_DISABLED:
            raise HexacncError("the drives are disabled: reset to enable them")
        if st == S.ST_BOOT and self.awaiting_enable:
            raise HexacncError("the drives are disabled, waiting for enable ([daemon] enable_at_start is "
                               "false): a controller sends 'enable' (or 'reset') first")
        if st == S.ST_STOPPING or self.stop_requested:
            raise HexacncError("a stop is in progress; wait for idle")

    def _queue(self, job: Job) -> None:
        with self.lock:
            self._require_motion_ok()
            self.queue.append(job)
            self.cv.notify_all()

    def move_to(self, pose_deg, feed_mm_s: float, name: str = "move_to") -> dict:
        """Queue a straight jerk-limited move of the **platform** pose to ``pose_deg`` (mm/deg)."""
        with self.lock:
            self._require_motion_ok()
            start = self._planned_start()
        # planning and checks outside the lock: the feeder thread must never wait for them
        rows = point_to_point(self.cfg, self.hx, start, pose_deg, float(feed_mm_s), self.period_s)
        return self._queue_planned(rows, start, name)

    def queue_rows(self, rows, name: str = "rows", check: bool = True) -> dict:
        """Queue precomputed rows (N, 8) that start at the current pose (tests, tools)."""
        from .feed import check_rows
        rows = np.asarray(rows, dtype=float)
        with self.lock:
            self._require_motion_ok()
            start = self._planned_start()
        if check:
            check_rows(self.cfg, self.hx, np.vstack([np.r_[start, 0, 0][None, :], rows]), self.period_s)
        return self._queue_planned(rows, start, name)

    def _queue_planned(self, rows: np.ndarray, start: np.ndarray, name: str) -> dict:
        src = ArraySource(self.cfg, self.hx, rows, self.period_s, name)
        job = Job(name=name, source=src, start_rad=start, end_rad=rows[-1, :6].copy(), blocks=1,
                  duration_s=(len(rows) - 1) * self.period_s)
        with self.lock:
            # the feeder's own start check (FeedMixin._feed_once) allows 1e-6: the job planned from
            # may have ended meanwhile, and the start is then read back from the status block
            if float(np.max(np.abs(self._planned_start() - start))) > START_TOL:
                raise HexacncError("another motion was queued meanwhile; plan again")
            self._queue(job)
        return {"blocks": 1, "duration_s": job.duration_s}

    def load_program(self, text, name: str, stops: int | None = None) -> dict:
        """Stream the program through validation and windowed planning (:mod:`.planstream`), then queue it:
        after the whole program is validated, or at the first planned window with ``[planner]
        start_before_validated``. G38.x programs run probe-synchronised (reply at the end).
        Raises GcodeError/PlanError (nothing moved).  ``text``: str, or the chunks of an upload (a list
        of str); ``stops``: :meth:`load_streamed`."""
        from .probeprog import PROBE_WORDS, run_probe_program
        from .progtext import joined
        if scan_words(self, text, {"probe": PROBE_WORDS}, name, stops):
            return run_probe_program(self, joined(text), name)
        job, info = self.load_streamed(text, name, stops=stops)
        return info

    def load_streamed(self, text, name: str, state=None, on_valid=None, accept=None, stops: int | None = None,
                      cfg=None):
        """The streamed program path of :meth:`load_program` (also the operator's, which interprets from
        its persistent ``state``; ``on_valid(stream_plan)`` once the whole program is validated; ``accept
        (stream_plan, info, source)`` before the job is queued: False leaves it unqueued, e.g. a program without
        motion).  Returns ``(job or None, info)``.  A ``stop`` (or reset) that comes while the program is
        interpreted, validated or planned kills its children and the program is refused; ``stops``: the count of
        stops (``_stops``) when the caller took the program (default: now), a stop after it refuses it; ``cfg``:
        the description to interpret and plan it with (default the daemon's; the operator's switches)."""
        from .planstream import StreamPlan
        from .program import program_source
        with self.lock:
            stops = self._stops if stops is None else stops
            if self._stops != stops:        # taken by the motion worker before the stop: stopped while prepared
                raise HexacncError(f"{name}: stopped while it was being interpreted and planned")
            self._require_motion_ok()
            start = self._planned_start()
        # interpreted, validated and planned in children with bounded memory and time (started outside
        # the lock: stop/pause never wait for them); a stop kills them
        sp = StreamPlan(cfg if cfg is not None else self.cfg, text, name, start, self.period_s, state=state,
                        on_valid=on_valid, start=False)
        with self.lock:
            self._planning.add(sp)
            if self._stops != stops:        # a stop came meanwhile
                sp.cancel()
        try:
            sp.start()                      # a stop from now on kills the children, even while they get the text
            src, info = program_source(sp, name, start, self.period_s)
        finally:
            with self.lock:
                self._planning.discard(sp)
        out = {k: v for k, v in info.items() if k != "end_rad"}
        if accept is not None and not accept(sp, out, src):
            src.close()
            return None, out
        job = Job(name=name, source=src, start_rad=start, end_rad=info["end_rad"], blocks=info["blocks"],
                  duration_s=info["duration_s"])
        with self.lock:
            try:
                if self._stops != stops:
                    raise HexacncError(f"{name}: stopped while it was being interpreted and planned")
                if float(np.max(np.abs(self._planned_start() - start))) > 1e-9:
                    raise HexacncError("another motion was queued while this program was planned; send it again")
                self._queue(job)
            except BaseException:
                src.close()
                raise
        self._watch_validation(job)
        return job, out

    def _cancel_planning(self) -> None:
        for pj in list(self._planning):
            pj.cancel()

    def pause(self) -> dict:
        with self.lock:
            if self.current is None:
                raise HexacncError("nothing to pause: no program is running")
            self._command(self.current.source.pause)
        return self.status()

    def resume(self) -> dict:
        with self.lock:
            if self.current is None or not getattr(self.current.source, "paused", False):
                raise HexacncError("nothing to resume: not paused")
            self._require_motion_ok()
            self._command(self.current.source.resume)
        return self.status()

    def set_feed_override(self, factor: float) -> None:
        with self.lock:
            if self.current is not None:
                src = self.current.source
                self._command(lambda: src.set_feed_override(factor))

    def stop(self) -> dict:
        """Controlled stop: decelerate along the path (jerk-limited), drop the queue, stay enabled."""
        with self.lock:
            if self.sh is None:
                raise HexacncError("the daemon is not running")
            self._stops += 1
            for job in self.queue:
                self._close_job(job)
                self.dropped.append({"name": job.name, "reason": "stop requested"})
            del self.dropped[:-32]
            self.queue.clear()
            if self.current is not None:
                self.stop_requested = True
                self._command(self.current.source.stop)
            elif self.sh.h[S.H_STATE] in (S.ST_RUNNING, S.ST_HOMING):     # homing: stopped, not referenced
                self.sh.command(S.CMD_STOP)
            # a program still being interpreted or planned: its children killed, after the motion's stop
            # was commanded (killing and reaping them must not delay it)
            self._cancel_planning()
            self.cv.notify_all()
        return self.status()

    def reset(self, timeout_s: float = 5.0) -> dict:
        """Clear a fault: fault reset and re-enable by controlword; returns the status."""
        with self.lock:
            if self.sh is None or not self.alive:
                raise HexacncError("the daemon is not running")
            st = self.sh.h[S.H_STATE]
            if st not in (S.ST_FAULT, S.ST_DISABLED) and not (st == S.ST_BOOT and self.awaiting_enable):
                return self.status()
            if self.ref_watch is not None:      # the fault being cleared: seen before it is gone
                self.ref_watch.poll(self.sh.h)
            self.awaiting_enable = False
            self._abort_jobs("reset")
            self.last_program = None
            self.sh.h[S.H_READY] = 0
            self.sh.command(S.CMD_RESET)
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            st = self.sh.h[S.H_STATE]
            if st == S.ST_IDLE and self.sh.h[S.H_READY] == 1:
                break
            time.sleep(0.01)
        st = self.status()
        if st["state"] == "fault":
            raise HexacncError(f"reset failed: {st['fault']['message']}")
        return st

    def enable(self, timeout_s: float = 5.0) -> dict:
        """Enable the drives (op ``enable``): the :meth:`reset` path; returns the status."""
        return self.reset(timeout_s)

    def inject_fault(self, code: int = 0) -> None:
        """Tests: latch an internal fault (controlled stop follows)."""
        from .faults import F_TEST
        self.sh.command(S.CMD_FAULT_TEST, code or F_TEST)

    def stall_loop_us(self, us: int) -> None:
        """Tests: make the hot loop sleep once for ``us`` microseconds (deadline burst)."""
        from .loop import CMD_STALL
        self.sh.command(CMD_STALL, int(us))

    def crash_loop(self) -> None:
        """Tests: make the hot loop raise in its cycle (a crashing hot process)."""
        from .loop import CMD_CRASH
        self.sh.command(CMD_CRASH)

    def inject_drive(self, kind: str, node: int, value=0) -> None:
        """Tests and ``hexacnc bench faults``: fault injection into the simulated drives process
        (:func:`hexacnc.daemon.simhost.inject`)."""
        if not hasattr(self.sim, "inject"):
            raise HexacncError("fault injection needs the simulated drives on shm or pipe buses")
        self.sim.inject(kind, node, value)
