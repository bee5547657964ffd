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

import numpy as np

from ..errors import BusError, HexacncError
from ..kinematics import Hexapod
from ..transform import CycleTransform
from . import shm as S
from .faults import fault_message
from .feeding import (FEED_AHEAD_S, FEED_CHUNK_ROWS, FEED_PERIOD_S, FEED_START_S, REWIND_ATTEMPTS,  # noqa: F401 (re-export)
                      REWIND_LEAD_S, FeedMixin, Job)
from .motion import MotionMixin
from .procs import HotEnd, HotProcess, HotWatch, acquire_lock, bus_lock_path, release_lock
from .statusview import StatusMixin

log = logging.getLogger("hexacnc.daemon")

#: how long the hot process may take to boot the bus and enable the drives
BOOT_TIMEOUT_S = 30.0


def _spawn_hot(args: dict, fds: tuple = ()) -> HotProcess:
    return HotProcess(args, fds)


class Daemon(MotionMixin, FeedMixin, StatusMixin):
    """Supervisor of the hot loop. ``Daemon(cfg).start()``; or use as a context manager."""

    def __init__(self, cfg, *, io_mode: str = "auto", period_s: float | None = None,
                 realtime: bool = True, start: bool = True, log_level: str | None = None,
                 sim_faults=(), channel: str | None = None):
        self.cfg = cfg
        self.period_s = float(period_s or cfg.cycle.period_s)
        self._rewind_rows = max(8, int(math.ceil(REWIND_LEAD_S / self.period_s)))
        self._ahead_rows = max(50, int(cfg.daemon.feed_ahead_s / self.period_s))
        self._start_rows = min(self._ahead_rows, max(FEED_CHUNK_ROWS, int(FEED_START_S / self.period_s)))
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
        self.awaiting_enable = False      #: started with drives disabled; "enable"/"reset" not sent yet
        self.ref_watch = None             #: reference.ReferenceWatch (the operator's), polled by the feeder
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
        from .thermalin import check_offset_rate
        from .thermalsup import thermal_supervisor
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
            # wait for the CiA 402 walk to Operation Enabled (inside the loop); with [daemon]
            # enable_at_start false the loop cycles with the drives disabled until "enable"/"reset"
            self.awaiting_enable = not getattr(self.cfg.daemon, "enable_at_start", True)
            while time.monotonic() < t_end:
                r = self.sh.h[S.H_READY]
                if r == 1 or (self.awaiting_enable and r == 0 and self.sh.h[S.H_CYCLES] > 0):
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
        from .planproc import warm      # the planning children's server, ready before the first program
        threading.Thread(target=warm, name="hexacnc-plan-warm", daemon=True).start()
        log.info("daemon ready: %s drives %s, cycle %.3f ms, io %s", self.cfg.name,
                 "disabled: waiting for enable ([daemon] enable_at_start false)" if self.awaiting_enable
                 else "enabled", self.period_s * 1e3, mode)
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
        with self.lock:
            self.hot_end = end
            self._abort_jobs(end.message)
            self.cv.notify_all()
        (log.warning if end.clean else log.error)("%s", end.message)

    def await_hot_end(self, timeout_s: float) -> HotEnd | None:
        """How the hot loop ended, once the watch thread has classified its exit (it polls); None if
        it has not within ``timeout_s`` (or the loop still runs)."""
        with self.lock:
            self.cv.wait_for(lambda: self.hot_end is not None, timeout_s)
            return self.hot_end

    @property
    def alive(self) -> bool:
        return self.hot is not None and self.hot.is_alive()

    # ------------------------------------------------------------------ thermal
    def push_temperatures(self, fields: dict) -> dict:
        """One reading for the thermal observer (the socket op ``temperatures``).

        ``fields``: ``probes_C`` (map or flat list, see :mod:`.thermalsup`), optional ``spindle_C``
        and ``time_s``.  Raises :class:`~.thermalin.ThermalInputError` (``code``, ``field``) on a
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


#: names other modules read here (tests, bench hold)
__all__ = ["Daemon", "Job", "FEED_AHEAD_S", "FEED_CHUNK_ROWS", "FEED_PERIOD_S", "REWIND_ATTEMPTS",
           "REWIND_LEAD_S", "BOOT_TIMEOUT_S"]
