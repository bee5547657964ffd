"""Setpoint feeding of the supervisor: the feeder thread, rewinds for commands, the job queue.

:class:`FeedMixin` is part of :class:`hexacnc.daemon.core.Daemon` (it uses the daemon's lock,
queue, shared memory and status): the feeder thread keeps ``FEED_AHEAD_S`` of rows in the ring in
chunks with rewind marks; :meth:`FeedMixin._command` applies pause/resume/stop/override
``REWIND_LEAD_S`` ahead of the hot loop instead of after the queue; on a fault the running job is
aborted and queued ones are dropped, each with the reason (``Daemon.dropped``).
"""
from __future__ import annotations

import logging
import os
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..errors import HexacncError
from . import shm as S

log = logging.getLogger("hexacnc.daemon")

#: rows kept queued in the ring while streaming a program or move (seconds of motion; the default of
#: ``[daemon] feed_ahead_s``): how long the supervisor may go unscheduled before the ring runs dry (a
#: stop, fault "dead setpoint source").  Commands that can take rows back act from ``REWIND_LEAD_S``
#: on; one that cannot (a failed rewind: the supervisor starved through five leads) acts after the queue.
#: 0.3 s was too short on a loaded 2-core machine (CI: the supervisor unscheduled 0.3-0.4 s mid-move)
FEED_AHEAD_S = 1.0
#: ... for a jog: its dead-man stop is the supervisor's, so a short queue (1.0 s ran to the soft limit)
JOG_AHEAD_S = 0.3
#: a job's first rows are published together once this much is queued (an empty ring: the loop holds),
#: the rest chunk by chunk, so a supervisor descheduled right after the first chunk cannot run it dry
FEED_START_S = 0.25
#: a pause, resume, stop or override takes back the queued rows beyond this lead (seconds) and
#: re-plans them from the source's state there: commands act within it (regenerated from the last
#: mark, no chunk granularity), not after FEED_AHEAD_S.  It covers the supervisor's time from
#: reading the hot loop's index to lowering the write index (the first batch: ~1 ms); a longer
#: lead is tried when the hot loop overtakes (loaded machine).  History: 40 ms gave 41-43 ms
#: reactions; 25 ms + one 16 ms chunk 26-28 ms
REWIND_LEAD_S = 0.005
#: rows per feeder chunk: a source snapshot is kept at every chunk start (the rewind points)
FEED_CHUNK_ROWS = 32
#: leads tried (each twice the last) before a command falls back to acting at the end of the queue
REWIND_ATTEMPTS = 5
#: replacement rows generated before the ring's write index is lowered (the rest of the queue right
#: after): the time the hot loop may not overtake is the generation of these (~20 us a row in a
#: transition, 1.3 ms), not of the whole queue (~12 ms)
REWIND_BATCH_ROWS = 2 * FEED_CHUNK_ROWS
#: feeder thread period
FEED_PERIOD_S = 0.002
#: a job's planned start and the commanded pose (mm / rad) agree within this (else it is dropped)
START_TOL = 1e-6

@dataclass
class Job:
    """One queued motion: a program or a point-to-point move."""
    name: str
    source: object                    #: ArraySource-like: next_rows, pause, resume, stop, progress
    start_rad: np.ndarray             #: platform pose the first row starts from (mm, rad)
    end_rad: np.ndarray               #: platform pose of the END row
    blocks: int = 0
    duration_s: float = 0.0
    end_index: int = -1               #: ring index after the END row, once pushed
    started: bool = False
    marks: deque = field(default_factory=deque)   #: (ring index, source snapshot before that row)
    ahead_s: float | None = None      #: rows kept queued (s); None: ``[daemon] feed_ahead_s``
    extra: dict = field(default_factory=dict)



def _same_rows(rows: np.ndarray, sh: S.Shared, k0: int) -> bool:
    """``rows`` equal (to 1e-9 mm / rad) the ring's rows from index ``k0`` (regenerated from a mark)."""
    ring = sh.ring          # no numpy view of the shared buffer: it would keep the segment from closing
    for n, r in enumerate(rows.tolist()):
        b = ((k0 + n) % S.RING_ROWS) * S.ROW
        for j in range(S.ROW):
            if abs(ring[b + j] - r[j]) > 1e-9:
                return False
    return True


class FeedMixin:
    """The feeding half of :class:`~hexacnc.daemon.core.Daemon`."""

    def _feed_loop(self) -> None:
        sh = self.sh
        if self.realtime:   # this thread only: keep the ring filled on a loaded machine (when permitted)
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(max(1, self.cfg.cycle.realtime_priority - 30)))
                self.info["feeder_sched_fifo"] = True
            except (OSError, AttributeError):
                self.info["feeder_sched_fifo"] = False
        ahead = self._ahead_rows
        while not self.closed and sh is not None:
            try:
                sh.h[S.H_SUP_BEAT_NS] = time.monotonic_ns()
                self._feed_once(sh, ahead)
                th = self.thermal
                if th is not None:
                    th.sample_travel()
            except Exception:       # never let the feeder die silently: the loop would fault
                log.exception("feeder error")
            time.sleep(FEED_PERIOD_S)

    def _feed_once(self, sh: S.Shared, ahead: int) -> None:
        with self.lock:
            if self._last_fault_logged and not sh.h[S.H_FAULT]:
                self._last_fault_logged = 0         # a new fault after a reset is logged too
            if self.ref_watch is not None:      # every latched fault, boot-up or encoder error seen
                self.ref_watch.poll(sh.h)
            hstate = sh.h[S.H_STATE]
            if hstate == S.ST_FAULT or hstate == S.ST_DISABLED:
                if self.current is not None or self.queue:
                    self._abort_jobs("fault" if hstate == S.ST_FAULT else "drives disabled")
                self._log_fault_once()
                return
            job = self.current
            if job is None:
                if not self.queue or hstate not in (S.ST_IDLE,):
                    return
                job = self.queue[0]
                pose = self._pose_cmd_rad()
                if float(np.max(np.abs(pose - job.start_rad))) > START_TOL:
                    # the machine is not where the job was planned from (e.g. after a stop): this
                    # job and those queued behind it are dropped, each with the reason
                    self._abort_jobs("the machine moved since the job was planned; send it again")
                    return
                self.queue.popleft()
                self.current = job
                job.started = True
                log.info("start %s (%d blocks, %.2f s)", job.name, job.blocks, job.duration_s)
                self.cv.notify_all()
            src = job.source
            if self.feed_hold:
                return
            if job.end_index < 0:
                self._push(job, sh, self._job_ahead_rows(job, ahead) - sh.ring_fill())
            elif sh.h[S.H_END_SEEN] >= job.end_index and hstate == S.ST_IDLE:
                line, pct, left = src.progress()
                self.last_program = {"name": job.name, "line": line, "percent": 100.0 if not src.stopping
                                     else pct, "time_left_s": 0.0, "stopped": bool(src.stopping)}
                self.current = None
                if self.stop_requested:
                    self.queue.clear()
                    self.stop_requested = False
                err = getattr(src, "error", None)
                if err is not None:
                    self.last_program["error"] = {"line": getattr(err, "line", None), "message": str(err)}
                self._close_job(job)
                log.info("%s %s", "stopped" if src.stopping else "finished", job.name)
                self.cv.notify_all()

    def _push(self, job: Job, sh: S.Shared, need: int) -> None:
        """Queue up to ``need`` rows of ``job`` in chunks, keeping a rewind mark at each chunk.

        Chunks are published as they come while the hot loop is running on queued rows; on an empty
        ring (the loop holds: a job's start) the first ``FEED_START_S`` of them are published at once,
        so a supervisor descheduled right after the first chunk cannot run the ring dry (it did:
        32-64 rows queued, 40-130 ms unscheduled)."""
        src = job.source
        marks = job.marks
        can_mark = hasattr(src, "snapshot")
        r = sh.h[S.H_RING_R]
        while len(marks) > 1 and marks[1][0] <= r:      # keep the mark of the row being run
            marks.popleft()
        held = [] if sh.ring_fill() == 0 else None      # rows generated, not yet published
        n_held, start_rows = 0, self._start_rows
        w = sh.h[S.H_RING_W]
        while need > 0 and not src.finished:
            if can_mark:
                marks.append((w, src.snapshot()))
            rows = src.next_rows(min(need, FEED_CHUNK_ROWS))
            if len(rows):
                if held is None:
                    sh.push_rows(rows)
                else:
                    held.append(rows)
                    n_held += len(rows)
                    if n_held >= start_rows:
                        sh.push_rows(np.concatenate(held))
                        held = None
            w += len(rows)
            need -= max(1, len(rows))
        if held:
            sh.push_rows(np.concatenate(held))
        if src.finished and job.end_index < 0:
            job.end_index = sh.h[S.H_RING_W]

    def _command(self, action) -> bool:
        """Apply ``action`` (the source's pause, resume, stop or override) to the rows the drives
        get ``REWIND_LEAD_S`` from now, not after the whole queue (caller holds the lock).

        The source goes back to its snapshot at the last mark before the lead point and
        regenerates the rows up to that point (they must come out as the queued ones, else the
        first mark past it is used), the command is applied there and a first batch of replacement
        rows (``REWIND_BATCH_ROWS``) is generated; only then is the ring's write index lowered to
        the lead point (``Shared.retract``: single producer, checked against the hot loop's read
        index afterwards) and the rows written; then the rest of the queue is generated.  Rows before
        the lead point are untouched, so the command path is continuous (the source continues from
        the state it was in when it produced that row).  If the hot loop got past the point
        meanwhile (a descheduled supervisor), the source returns to where it was and a lead twice
        as long is tried; when there is nothing to take back the command acts on the end of the
        queue.  Returns whether rows were taken back.
        """
        job, sh = self.current, self.sh
        src = job.source if job is not None else None
        if src is None or sh is None or self.feed_hold or not job.marks or not hasattr(src, "snapshot"):
            action()
            return False
        end_snap = src.snapshot()
        for attempt in range(REWIND_ATTEMPTS):
            k_min = sh.h[S.H_RING_R] + (self._rewind_rows << attempt)
            if k_min >= sh.h[S.H_RING_W]:
                break
            at = self._rewind_point(job, src, sh, k_min)
            if at is None:
                break
            k, i = at
            action()
            batch, marks, idx = [], [], k
            need = min(self._ahead_rows, REWIND_BATCH_ROWS)
            while need > 0 and not src.finished:
                marks.append((idx, src.snapshot()))
                rows = src.next_rows(min(need, FEED_CHUNK_ROWS))
                batch.append(rows)
                idx += len(rows)
                need -= max(1, len(rows))
            if sh.retract(k):
                for rows in batch:
                    if len(rows):
                        sh.push_rows(rows)
                while len(job.marks) > i:
                    job.marks.pop()
                job.marks.extend(marks)
                job.end_index = sh.h[S.H_RING_W] if src.finished else -1
                # more of the queue at once (the reaction is already fixed: the hot loop reads the new
                # rows), so the ring holds FEED_START_S again, not only lead + batch; the feeder
                # tops it up (a whole 1 s queue here would hold the lock ~40 ms)
                self._push(job, sh, min(self._job_ahead_rows(job, self._ahead_rows), self._start_rows)
                           - sh.ring_fill())
                self.rewinds[0] += 1
                return True
            src.restore(end_snap)           # the hot loop got there first: a longer lead
        src.restore(end_snap)
        action()
        self.rewinds[1] += 1
        return False

    def _job_ahead_rows(self, job: Job, default_rows: int) -> int:
        """Rows to keep queued for ``job``: its own ``ahead_s`` (jogs) or the daemon's."""
        if job.ahead_s is None:
            return default_rows
        return max(50, min(default_rows, int(job.ahead_s / self.period_s)))

    @staticmethod
    def _rewind_point(job: Job, src, sh: S.Shared, k_min: int):
        """Put ``src`` in its state before ring row ``k``, the lead point ``k_min`` (regenerated from
        the last mark before it, checked against the queued rows) or else the first mark past it.
        Returns ``(k, index of the first mark to replace)`` or None (nothing to take back)."""
        marks = job.marks
        j = 0
        while j < len(marks) and marks[j][0] <= k_min:
            j += 1
        if j > 0:                                      # marks[j - 1] is at or before the lead point
            k0, snap = marks[j - 1]
            src.restore(snap)
            n = k_min - k0
            rows = src.next_rows(n) if n > 0 else np.empty((0, S.ROW))
            if not src.finished and len(rows) == n and (n == 0 or _same_rows(rows, sh, k0)):
                return k_min, (j - 1 if n == 0 else j)
        if j < len(marks) and marks[j][0] < sh.h[S.H_RING_W]:
            k, snap = marks[j]
            src.restore(snap)
            return k, j
        return None

    def _abort_jobs(self, why: str) -> None:
        for job in self.queue:          # queued behind the running one: dropped, never silently
            self._close_job(job)
            self.dropped.append({"name": job.name, "reason": why})
            log.warning("%s dropped from the queue: %s", job.name, why)
        del self.dropped[:-32]
        if self.current is not None:
            line, pct, left = self.current.source.progress()
            self.last_program = {"name": self.current.name, "line": line, "percent": pct,
                                 "time_left_s": left, "aborted": why}
            log.warning("%s aborted at line %d: %s", self.current.name, line, why)
            self._close_job(self.current)
        self.current = None
        self.queue.clear()
        self.stop_requested = False
        self.cv.notify_all()        # queued rows left in the ring are dropped by the hot loop on reset

    def _log_fault_once(self) -> None:
        h = self.sh.h
        n = h[S.H_CYCLES] if h[S.H_FAULT] else 0
        if h[S.H_FAULT] and self._last_fault_logged == 0:
            self._last_fault_logged = n or 1
            f = self._fault_dict(self.sh.read_status())
            log.error("FAULT %s: %s", f["code"], f["message"])
        elif not h[S.H_FAULT]:
            self._last_fault_logged = 0

    # ------------------------------------------------------------------ helpers
    def _pose_cmd_rad(self) -> np.ndarray:
        h, s = self.sh.read_status()
        return np.array(s[S.S_POSE_CMD:S.S_POSE_CMD + 6])

    def _planned_start(self) -> np.ndarray:
        """Where the next queued job will start: the end of the last queued one, or now."""
        job = self.queue[-1] if self.queue else self.current
        if job is None:
            return self._pose_cmd_rad()
        if job.end_rad is None:         # a streamed program started before its validation ended
            end = getattr(getattr(job.source, "stream", None), "end_rad", None)
            if end is None:
                raise HexacncError(f"{job.name} is still being validated (its end pose is not known yet): "
                                   f"send this motion when its validation is done")
            job.end_rad = np.asarray(end, dtype=float)
        return job.end_rad.copy()

    # ------------------------------------------------------------------ streamed programs
    @staticmethod
    def _close_job(job: Job) -> None:
        close = getattr(job.source, "close", None)
        if close is not None:
            close()

    def _watch_validation(self, job: Job) -> None:
        """An error the validation finds after the job was queued (``[planner] start_before_validated``)
        stops it: the running job with a controlled stop on its path, a queued one is dropped."""
        sp = getattr(job.source, "stream", None)
        if sp is None:
            return
        sp.on_invalid = lambda err: self._program_invalid(job, err)
        if sp.invalid is not None:
            self._program_invalid(job, sp.invalid)

    def _program_invalid(self, job: Job, err) -> None:
        with self.lock:
            log.error("%s: %s", job.name, err)
            if job is self.current:
                self._command(lambda: job.source.fail(err))
            elif job in self.queue:
                self.queue.remove(job)
                self._close_job(job)
                self.dropped.append({"name": job.name, "reason": str(err), "line": getattr(err, "line", None)})
                del self.dropped[:-32]
            self.cv.notify_all()

