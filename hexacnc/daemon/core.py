"""The supervisor: the daemon's public API in the main process.

Process structure (one machine):

* **supervisor** (this module, the ``hexacnc run`` process): parses and plans programs, feeds
  setpoint rows into the shared ring from a feeder thread, answers the socket server, reads the
  status block, pets the systemd watchdog.  Nothing here is real-time.
* **hot loop** (:mod:`hexacnc.daemon.loop`, a ``spawn`` child): boots the drives, then runs only
  the cycle.  Talks to the supervisor through one shared-memory segment (:mod:`.shm`).
* **simulated drives** (``drivers.simdrive``, another child) when ``[bus] simulate``.

API (used by :mod:`hexacnc.daemon.server`): :meth:`Daemon.load_program`, :meth:`pause`,
:meth:`resume`, :meth:`stop`, :meth:`reset`, :meth:`status`, :meth:`wait`, :meth:`hello`,
:meth:`close`, plus :meth:`move_to` (platform pose) for tests and tools.
"""
from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .. import __version__
from ..errors import BusError, HexacncError
from ..kinematics import Hexapod
from ..transform import CycleTransform
from . import shm as S
from .faults import F_EMCY, F_LIMIT, F_NONE, fault_code_name
from .feed import ArraySource, point_to_point
from .loop import fault_message
from .procs import HotEnd, HotProcess, HotWatch, acquire_lock, bus_lock_path, release_lock

log = logging.getLogger("hexacnc.daemon")

#: rows kept queued in the ring while streaming (seconds of motion)
FEED_AHEAD_S = 0.3
#: a pause, resume, stop or override takes back the queued rows beyond this lead (seconds) and
#: re-plans them from the source's state there: commands act within it, not after FEED_AHEAD_S
REWIND_LEAD_S = 0.04
#: rows per feeder chunk: a source snapshot is kept at every chunk start (the rewind points)
FEED_CHUNK_ROWS = 32
#: marks tried before a command falls back to acting at the end of the queue
REWIND_ATTEMPTS = 3
#: feeder thread period
FEED_PERIOD_S = 0.002
#: how long the hot process may take to boot the bus and enable the drives
BOOT_TIMEOUT_S = 30.0


def _spawn_hot(args: dict, fds: tuple = ()) -> HotProcess:
    return HotProcess(args, fds)


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
    extra: dict = field(default_factory=dict)


class Daemon:
    """Supervisor of the hot loop. ``Daemon(cfg).start()``; or use as a context manager."""

    def __init__(self, cfg, *, io_mode: str = "auto", period_s: float | None = None,
                 realtime: bool = True, start: bool = True, log_level: str | None = None,
                 sim_faults=(), channel: str | None = None):
        self.cfg = cfg
        self.period_s = float(period_s or cfg.cycle.period_s)
        self._rewind_rows = max(8, int(math.ceil(REWIND_LEAD_S / self.period_s)))
        self._ahead_rows = max(50, int(FEED_AHEAD_S / self.period_s))
        self.rewinds = [0, 0]           #: commands that took queued rows back / acted at the queue's end
        self.io_mode = io_mode
        self.sim_faults = list(sim_faults)
        self.channel = channel
        self.realtime = realtime
        self.log_level = log_level or cfg.daemon.log_level
        self.hx = Hexapod(cfg)
        self._ct_text = CycleTransform(cfg, self.hx, period_s=self.period_s)  # slow path: describe()
        self.sh: S.Shared | None = None
        self.hot: HotProcess | None = None
        self.sim = None
        self.info: dict = {}
        self.lock = threading.RLock()
        self.cv = threading.Condition(self.lock)
        self.queue: deque[Job] = deque()
        self.current: Job | None = None
        self.last_program: dict | None = None
        self.stop_requested = False
        self.closed = False
        self._feeder: threading.Thread | None = None
        self.feed_hold = False          #: tests: the setpoint source stops delivering (dead source)
        self.thermal = None               #: ThermalSupervisor (observer, limits, simulated plant)
        self._stats_cache: tuple[float, dict] = (0.0, {})
        self._last_fault_logged = 0
        self._notifier = None
        self.watch: HotWatch | None = None
        self.hot_end: HotEnd | None = None      #: how the hot loop ended without being told to
        self.dropped: list[dict] = []           #: programs dropped from the queue (name, reason)
        self.final_fault: dict | None = None    #: the fault latched when the daemon was closed
        self._bus_lock: int | None = None
        self._planning: set = set()             #: programs being planned (planproc.PlanJob)
        self._stops = 0                         #: stop() calls so far (a plan started before one is dropped)
        if start:
            self.start()

    # ------------------------------------------------------------------ life cycle
    def start(self, timeout_s: float = BOOT_TIMEOUT_S) -> "Daemon":
        from . import busio
        from drivers import busload
        mode = busio.resolve_mode(self.cfg, self.io_mode)
        self.info["io_mode"] = mode
        rep = busload.check_layout(self.cfg.bus, self.period_s)   # refuse a layout over max_load, with figures
        self.info["bus_load"] = rep["load"]
        self.info["bus_summary"] = busload.describe(rep)
        from .thermalsup import check_offset_rate, thermal_supervisor
        check_offset_rate(self.cfg, self.period_s)      # refuse a rate the cycle's acceleration guard would trip on
        if mode == "bus":           # a real (or netns) bus: one daemon per interface, before any frame
            self._bus_lock = acquire_lock(bus_lock_path(self.cfg),
                                          f"bus {self.cfg.bus.interface} {self.cfg.bus.channel}")
        self.sh = S.Shared(create=True)
        self.sh.h[S.H_SUP_PID] = os.getpid()
        self._keep_off_hot_cpu()
        try:
            self.thermal = thermal_supervisor(self.cfg, self.sh, self.status_state)
            self.sim = busio.start_simulation(self.cfg, mode, self.period_s, self.sim_faults, self.channel)
            self.hot = _spawn_hot({"cfg": self.cfg, "shm": self.sh.name, "io_mode": mode,
                                   "period_s": self.period_s, "realtime": self.realtime,
                                   "log_level": self.log_level, "cpu": self.info.get("hot_cpu"),
                                   "sim_args": busio.child_args(self.sim, self.channel)},
                                  busio.pass_fds(self.sim))
            if hasattr(self.sim, "close_fds"):
                self.sim.close_fds()          # the hot process holds its ends now
            t_end = time.monotonic() + timeout_s
            msg = self.hot.wait_report(timeout_s)
            if msg is None or msg[0] != "ready":
                why = msg[1] if msg else ("hot loop process died" if not self.hot.is_alive()
                                          else f"no answer within {timeout_s:g} s")
                raise BusError(f"daemon start failed: {why}")
            self.info.update(msg[1])
            # wait for the CiA 402 walk to Operation Enabled (inside the loop)
            while time.monotonic() < t_end:
                r = self.sh.h[S.H_READY]
                if r == 1:
                    break
                if r == -1 or not self.hot.is_alive():
                    h, s = self.sh.read_status()
                    raise BusError("daemon start failed: " + fault_message(
                        h[S.H_FAULT], h[S.H_FAULT_STRUT], h[S.H_FAULT_ARG]))
                time.sleep(0.01)
            else:
                raise BusError(f"daemon start failed: drives not enabled within {timeout_s:g} s")
        except BaseException:
            self._teardown()
            raise
        self.sh.h[S.H_SUP_BEAT_NS] = time.monotonic_ns()
        self.watch = HotWatch(self.hot, self.sh, self._hot_ended)
        self.watch.start()
        self.thermal.start()
        self._feeder = threading.Thread(target=self._feed_loop, name="hexacnc-feeder", daemon=True)
        self._feeder.start()
        log.info("daemon ready: %s drives enabled, cycle %.3f ms, io %s", self.cfg.name,
                 self.period_s * 1e3, mode)
        return self

    def _keep_off_hot_cpu(self) -> None:
        """Supervisor (and the processes/threads it starts later) off the hot loop's CPU."""
        try:
            cpus = sorted(os.sched_getaffinity(0))
            hot = cpus[-1] if self.cfg.cycle.cpu < 0 else self.cfg.cycle.cpu
            rest = {c for c in cpus if c != hot}
            self.info["hot_cpu"] = hot
            if rest and hot in cpus:
                self._saved_affinity = set(cpus)
                os.sched_setaffinity(0, rest)
                self.info["supervisor_cpus"] = sorted(rest)
        except (OSError, AttributeError):
            pass

    def __enter__(self) -> "Daemon":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self, timeout_s: float = 5.0) -> None:
        """Controlled stop, drives disabled, processes ended, shared memory released."""
        if self.closed:
            return
        self.closed = True
        self._cancel_planning()
        if self.thermal is not None:
            self.thermal.close()
        if self.watch is not None:
            self.watch.ordered.set()
        if self.sh is not None and self.hot is not None and self.hot.is_alive():
            self.sh.command(S.CMD_SHUTDOWN)
            self.hot.join(timeout_s)
        if self.sh is not None:
            h = self.sh.h
            self.final_fault = self._fault_dict(self.sh.read_status())
            if self.final_fault is None and self.hot_end is not None and not self.hot_end.clean:
                self.final_fault = {"code": self.hot_end.code, "message": self.hot_end.message}
            if self.final_fault is None and self.hot is not None and h[S.H_EXIT] != 1:
                self.final_fault = {"code": "loop_exited", "message": "the hot loop did not stop cleanly"}
        if self._feeder is not None:
            self._feeder.join(1.0)
        self._teardown()

    def _teardown(self) -> None:
        from . import busio
        if self.hot is not None:
            if self.hot.is_alive():
                self.hot.terminate()
                self.hot.join(2.0)
            self.hot = None
        if self.sim is not None:
            busio.stop_simulation(self.sim)
            self.sim = None
        if self.sh is not None:
            self.sh.close()
            self.sh = None
        release_lock(self._bus_lock)
        self._bus_lock = None
        saved = getattr(self, "_saved_affinity", None)
        if saved:
            try:
                os.sched_setaffinity(0, saved)
            except OSError:
                pass

    def _hot_ended(self, end: HotEnd) -> None:
        """The hot loop ended or hung without being told to (the watch thread)."""
        (log.warning if end.clean else log.error)("%s", end.message)
        with self.lock:
            self.hot_end = end
            self._abort_jobs(end.message)
            self.cv.notify_all()

    @property
    def alive(self) -> bool:
        return self.hot is not None and self.hot.is_alive()

    # ------------------------------------------------------------------ feeding
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
                if float(np.max(np.abs(pose - job.start_rad))) > 1e-6:
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
                self._push(job, sh, ahead - sh.ring_fill())
            elif sh.h[S.H_END_SEEN] >= job.end_index and hstate == S.ST_IDLE:
                line, pct, left = src.progress()
                self.last_program = {"name": job.name, "line": line, "percent": 100.0 if not src.stopping
                                     else pct, "time_left_s": 0.0, "stopped": bool(src.stopping)}
                self.current = None
                if self.stop_requested:
                    self.queue.clear()
                    self.stop_requested = False
                log.info("%s %s", "stopped" if src.stopping else "finished", job.name)
                self.cv.notify_all()

    def _push(self, job: Job, sh: S.Shared, need: int) -> None:
        """Queue up to ``need`` rows of ``job`` in chunks, keeping a rewind mark at each chunk."""
        src = job.source
        marks = job.marks
        can_mark = hasattr(src, "snapshot")
        r = sh.h[S.H_RING_R]
        while marks and marks[0][0] < r:
            marks.popleft()
        while need > 0 and not src.finished:
            if can_mark:
                marks.append((sh.h[S.H_RING_W], src.snapshot()))
            rows = src.next_rows(min(need, FEED_CHUNK_ROWS))
            if len(rows):
                sh.push_rows(rows)
            need -= max(1, len(rows))
        if src.finished and job.end_index < 0:
            job.end_index = sh.h[S.H_RING_W]

    def _command(self, action) -> bool:
        """Apply ``action`` (the source's pause, resume, stop or override) to the rows the drives
        get ``REWIND_LEAD_S`` from now, not after the whole queue (caller holds the lock).

        The source goes back to its snapshot at the first mark past the lead, the command is
        applied there and the replacement rows (the full queue length, ~2-3 ms of work) are
        generated first; only then is the ring's write index lowered to the mark and the new rows
        written, so the queue stays full and the hot loop never waits for the generation.
        Continuity holds because the source continues from exactly the state it was in when it
        produced that row the first time.  If the hot loop got past the mark meanwhile (a
        descheduled supervisor), the source returns to where it was and the next mark is tried;
        when there is nothing to take back the command acts on the end of the queue.  Returns
        whether rows were taken back.
        """
        job, sh = self.current, self.sh
        src = job.source if job is not None else None
        if src is None or sh is None or self.feed_hold or not job.marks or not hasattr(src, "snapshot"):
            action()
            return False
        end_snap = src.snapshot()
        for _attempt in range(REWIND_ATTEMPTS):
            k_min = sh.h[S.H_RING_R] + self._rewind_rows
            w = sh.h[S.H_RING_W]
            for i, (k, snap) in enumerate(job.marks):
                if k >= k_min:
                    break
            else:
                break
            if k >= w:
                break
            src.restore(snap)
            action()
            marks, chunks, idx, need = [], [], k, self._ahead_rows
            while need > 0 and not src.finished:
                marks.append((idx, src.snapshot()))
                rows = src.next_rows(min(need, FEED_CHUNK_ROWS))
                chunks.append(rows)
                idx += len(rows)
                need -= max(1, len(rows))
            if sh.retract(k):
                for rows in chunks:
                    if len(rows):
                        sh.push_rows(rows)
                while len(job.marks) > i:
                    job.marks.pop()
                job.marks.extend(marks)
                job.end_index = sh.h[S.H_RING_W] if src.finished else -1
                self.rewinds[0] += 1
                return True
            src.restore(end_snap)           # the hot loop got there first: try a later mark
        action()
        self.rewinds[1] += 1
        return False

    # ------------------------------------------------------------------ thermal
    def push_temperatures(self, fields: dict) -> dict:
        """One reading for the thermal observer (the socket op ``temperatures``).

        ``fields``: ``probes_C`` (map or flat list, see :mod:`.thermalsup`), optional ``spindle_C``
        and ``time_s``.  Raises :class:`~.thermalsup.ThermalInputError` (``code``, ``field``) on a
        bad reading, which then changes nothing.
        """
        if self.thermal is None:
            raise HexacncError("the daemon is not running")
        return self.thermal.push(fields, origin="socket")

    def set_temperatures(self, ambient_C: float, frame_C: float, probes_C=None,
                         spindle_C: float | None = None, time_s: float | None = None) -> dict:
        """Python form of :meth:`push_temperatures`: ``probes_C`` (6, n_probes) degC."""
        return self.push_temperatures({"probes_C": {"struts": np.asarray(probes_C, dtype=float).tolist(),
                                                    "ambient": ambient_C, "frame": frame_C},
                                       "spindle_C": spindle_C, "time_s": time_s})

    def _abort_jobs(self, why: str) -> None:
        for job in self.queue:          # queued behind the running one: dropped, never silently
            self.dropped.append({"name": job.name, "reason": why})
            log.warning("%s dropped from the queue: %s", job.name, why)
        del self.dropped[:-32]
        if self.current is not None:
            line, pct, left = self.current.source.progress()
            self.last_program = {"name": self.current.name, "line": line, "percent": pct,
                                 "time_left_s": left, "aborted": why}
            log.warning("%s aborted at line %d: %s", self.current.name, line, why)
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
        if self.queue:
            return self.queue[-1].end_rad.copy()
        if self.current is not None:
            return self.current.end_rad.copy()
        return self._pose_cmd_rad()

    def _require_motion_ok(self) -> None:
        if self.sh is None or not self.alive:
            raise HexacncError("the daemon is not running")
        st = self.sh.h[S.H_STATE]
        if st == S.ST_FAULT:
            raise HexacncError("the daemon is in fault: reset first ("
                               + self._fault_dict(self.sh.read_status())["message"] + ")")
        if st == S.ST_DISABLED:
            raise HexacncError("the drives are disabled: reset to enable them")
        if st == S.ST_STOPPING or self.stop_requested:
            raise HexacncError("a stop is in progress; wait for idle")

    def _queue(self, job: Job) -> None:
        with self.lock:
            self._require_motion_ok()
            self.queue.append(job)
            self.cv.notify_all()

    # ------------------------------------------------------------------ public API
    def hello(self) -> dict:
        import can
        import canopen
        import numpy
        return {"machine": self.cfg.name, "versions": {"hexacnc": __version__, "numpy": numpy.__version__,
                                                       "python-can": can.__version__,
                                                       "canopen": canopen.__version__},
                "cycle_period_s": self.period_s, "io": self.info.get("io_mode"),
                "bus_layout": self.cfg.bus.layout, "privileges": self.info.get("privileges")}

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
            if float(np.max(np.abs(self._planned_start() - start))) > 1e-9:
                raise HexacncError("another motion was queued meanwhile; plan again")
            self._queue(job)
        return {"blocks": 1, "duration_s": job.duration_s}

    def load_program(self, text: str, name: str) -> dict:
        """Parse, plan and check the whole program, then queue it. Raises GcodeError/PlanError."""
        from .planproc import PlanJob
        from .program import ProgramSource
        with self.lock:
            self._require_motion_ok()
            start = self._planned_start()
            stops = self._stops
        # interpreted and planned in a child with bounded memory and time (started outside the
        # lock: stop/pause never wait for it); a stop kills it
        pj = PlanJob(self.cfg, text, name, start, self.period_s)
        with self.lock:
            self._planning.add(pj)
            if self._stops != stops:        # a stop came while the child was being started
                pj.cancel()
        try:
            plan, blocks, duration_s, end_rad, _summary = pj.result()
        finally:
            with self.lock:
                self._planning.discard(pj)
        job = Job(name=name, source=ProgramSource(plan, self.period_s, name), start_rad=start, end_rad=end_rad,
                  blocks=blocks, duration_s=duration_s)
        with self.lock:
            if float(np.max(np.abs(self._planned_start() - start))) > 1e-9:
                raise HexacncError("another motion was queued while this program was planned; send it again")
            self._queue(job)
        return {"blocks": blocks, "duration_s": duration_s}

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
            self._cancel_planning()         # a program still being interpreted or planned: dropped
            for job in self.queue:
                self.dropped.append({"name": job.name, "reason": "stop requested"})
            del self.dropped[:-32]
            self.queue.clear()
            if self.current is not None:
                self.stop_requested = True
                self._command(self.current.source.stop)
            elif self.sh.h[S.H_STATE] == S.ST_RUNNING:
                self.sh.command(S.CMD_STOP)
            self.cv.notify_all()
        return self.status()

    def reset(self, timeout_s: float = 5.0) -> dict:
        """Clear a fault: fault reset and re-enable by controlword; returns the status."""
        with self.lock:
            if self.sh is None or not self.alive:
                raise HexacncError("the daemon is not running")
            st = self.sh.h[S.H_STATE]
            if st not in (S.ST_FAULT, S.ST_DISABLED):
                return self.status()
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

    def reset_stats(self, timeout_s: float = 1.0) -> None:
        """Start the cycle statistics afresh (benchmarks: one phase at a time)."""
        seq = self.sh.command(S.CMD_STATS_RESET)
        t_end = time.monotonic() + timeout_s
        while self.sh.h[S.H_CMD_ACK] < seq and time.monotonic() < t_end:
            time.sleep(0.001)
        for hist in (self.sh.hist_late, self.sh.hist_comp):
            for i in range(S.HIST_BINS):
                hist[i] = 0
        self._stats_cache = (0.0, {})

    # ------------------------------------------------------------------ status
    def _fault_dict(self, hs) -> dict | None:
        h, s = hs
        code = h[S.H_FAULT]
        if code == F_NONE:
            return None
        detail = ""
        strut = h[S.H_FAULT_STRUT]
        emcy = ""
        if code == F_LIMIT:
            ct = self._ct_text
            ct.fail_index = strut - 1
            ct.fail_value = s[S.S_FAULT_VALUE]
            detail = ct.describe(h[S.H_FAULT_ARG])
        elif code == F_EMCY:
            try:
                from drivers import cia402
                emcy = cia402.emcy_text(h[S.H_FAULT_ARG])
            except (ImportError, AttributeError):
                emcy = ""
        return {"code": fault_code_name(code),
                "message": fault_message(code, strut, h[S.H_FAULT_ARG], emcy, detail),
                "strut": strut or None, "line": h[S.H_LINE] or None}

    def cycle_stats(self) -> dict:
        now = time.monotonic()
        t, cached = self._stats_cache
        if now - t < 0.05 and cached:
            return cached
        sh = self.sh
        h = sh.h
        lat = S.percentiles_us(sh.hist_late.tolist())
        comp = S.percentiles_us(sh.hist_comp.tolist())
        cycles = h[S.H_CYCLES] - h[S.H_STATS_CYCLES0]
        out = {
            "period_s": self.period_s, "cycles": cycles,
            "lateness_us": {"median": lat[0], "p99": lat[1], "p999": lat[2], "max": h[S.H_LAT_MAX_NS] / 1e3},
            "compute_us": {"median": comp[0], "p99": comp[1], "p999": comp[2], "max": h[S.H_COMP_MAX_NS] / 1e3},
            "overruns": h[S.H_OVERRUNS],
            "overrun_pct": 100.0 * h[S.H_OVERRUNS] / cycles if cycles else 0.0,
            "max_overruns_in_row": h[S.H_MAX_IN_ROW],
            "compute_phases_us": {name: {"mean": round(h[S.H_PHASE_SUM_NS + j] / cycles / 1e3, 2) if cycles else None,
                                         "max": h[S.H_PHASE_MAX_NS + j] / 1e3}
                                  for j, name in enumerate(S.PHASE_NAMES)},
            "underruns": h[S.H_UNDERRUNS],
            "bus_load": sh.s[S.S_BUS_LOAD],
            "ring_fill": sh.ring_fill(),
            "commands_rewound": self.rewinds[0], "commands_at_queue_end": self.rewinds[1],
            "privileges": self.info.get("privileges"),
        }
        self._stats_cache = (now, out)
        return out

    def status_state(self) -> str:
        """Cheap: "running" while the loop consumes setpoints, else the loop state's name."""
        sh = self.sh
        if sh is None:
            return "fault"
        return S.STATE_NAMES.get(sh.h[S.H_STATE], "unknown")

    def status(self) -> dict:
        if self.sh is None:
            return {"state": "fault", "fault": {"code": "not_running", "message": "the daemon is not running"}}
        hs = self.sh.read_status()
        h, s = hs
        hstate = h[S.H_STATE]
        with self.lock:
            job = self.current
            if hstate == S.ST_FAULT:
                state = "fault"
            elif hstate == S.ST_STOPPING or self.stop_requested:
                state = "stopping"
            elif job is not None and getattr(job.source, "paused", False):
                state = "paused"
            elif job is not None or self.queue or hstate == S.ST_RUNNING:
                state = "running"
            else:
                state = "idle"
            if job is not None:
                line, pct, left = job.source.progress()
                prog = {"name": job.name, "line": line, "percent": round(pct, 2), "time_left_s": round(left, 3),
                        "queued": len(self.queue)}
            else:
                prog = dict(self.last_program) if self.last_program else None
        if not self.alive and state != "fault":
            state = "fault"
        pc = s[S.S_POSE_CMD:S.S_POSE_CMD + 6]
        pa = s[S.S_POSE_ACT:S.S_POSE_ACT + 6]
        fault = self._fault_dict(hs)
        end = self.hot_end
        if fault is None and end is not None:
            fault = {"code": end.code, "message": end.message, "strut": None, "line": None}
        if fault is None and not self.alive and not self.closed:
            fault = {"code": "loop_exited", "message": "the hot loop process is not running", "strut": None,
                     "line": None}
        if prog is not None and self.dropped:
            prog["dropped"] = list(self.dropped)
        return {
            "state": state,
            "drives_enabled": hstate in (S.ST_IDLE, S.ST_RUNNING, S.ST_STOPPING),
            "loop_state": S.STATE_NAMES.get(hstate, str(hstate)),
            "pose_cmd": pc[:3] + [math.degrees(v) for v in pc[3:]],
            "pose_act": pa[:3] + [math.degrees(v) for v in pa[3:]],
            "struts_cmd_mm": s[S.S_STRUT_CMD:S.S_STRUT_CMD + 6],
            "struts_act_mm": s[S.S_STRUT_ACT:S.S_STRUT_ACT + 6],
            "following_error_max_mm": s[S.S_FOLLOW_MAX:S.S_FOLLOW_MAX + 6],
            "thermal_offsets_mm": s[S.S_THERMAL_APP:S.S_THERMAL_APP + 6],
            "spindle_growth_mm": s[S.S_SPINDLE_APP],
            "statuswords": h[S.H_STATUSWORDS:S.H_STATUSWORDS + 6],
            "line": h[S.H_LINE],
            "fault": fault,
            "cycle": self.cycle_stats(),
            "program": prog,
            "dropped_programs": list(self.dropped),
            "thermal": self.thermal.status(s, h) if self.thermal is not None else {"source": "none", "state": "off"},
        }

    def wait(self, timeout_s: float) -> dict:
        """Block until idle (no motion queued or running) or fault, or the timeout; returns the status."""
        t_end = time.monotonic() + max(0.0, float(timeout_s))
        while True:
            st = self.status()
            if st["state"] in ("idle", "fault"):
                return st
            left = t_end - time.monotonic()
            if left <= 0:
                st["timeout"] = True
                return st
            with self.cv:
                self.cv.wait(min(left, 0.02))
