"""Status of the supervisor: the status map, cycle statistics, fault texts, hello, wait.

:class:`StatusMixin` is part of :class:`hexacnc.daemon.core.Daemon` (reads the daemon's shared
memory, job and hot-loop end); every field of ``status`` is documented in docs/protocol.md.
"""
from __future__ import annotations

import math
import time

from .. import __version__
from . import shm as S
from .torqueread import status_keys
from .faults import F_EMCY, F_LIMIT, F_NONE, fault_code_name, fault_message


class StatusMixin:
    """The status half of :class:`~hexacnc.daemon.core.Daemon`."""

    def hello(self) -> dict:
        import can
        import canopen
        import numpy
        return {"machine": self.cfg.name, "versions": {"hexacnc": __version__, "numpy": numpy.__version__,
                                                       "python-can": can.__version__,
                                                       "canopen": canopen.__version__},
                "cycle_period_s": self.period_s, "io": self.info.get("io_mode"),
                "bus_layout": self.cfg.bus.layout, "privileges": self.info.get("privileges")}

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
        lat = S.percentiles_us(sh.hist_late)
        comp = S.percentiles_us(sh.hist_comp)
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
            state = self._motion_state(hstate)
            if job is not None:
                line, pct, left = job.source.progress()
                prog = {"name": job.name, "line": line, "percent": round(pct, 2), "time_left_s": round(left, 3),
                        "queued": len(self.queue)}
                prog.update(getattr(job.source, "stream_status", dict)())
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
            # the loop's time of this snapshot (its cycle count x the period: the setpoints' time base, free of
            # the jitter of the message's delivery; hexacnc record differentiates the commanded lengths over it)
            "loop_time_s": h[S.H_STATUS_CYCLE] * self.period_s,
            "fault": fault,
            "waiting": waiting_reason(hstate, fault, self.awaiting_enable),
            "cycle": self.cycle_stats(),
            "program": prog,
            "dropped_programs": list(self.dropped),
            "thermal": self.thermal.status(s, h) if self.thermal is not None else {"source": "none", "state": "off"},
            **status_keys(s, time.monotonic()),       # drive torque / current (0x6077 / 0x6078), when sampled
        }

    def _motion_state(self, hstate: int) -> str:
        """The status key ``state`` from the loop state and the job queue (caller holds the lock)."""
        job = self.current
        if hstate == S.ST_FAULT:
            return "fault"
        if hstate == S.ST_STOPPING or self.stop_requested:
            return "stopping"
        if job is not None and getattr(job.source, "paused", False):
            return "paused"
        if job is not None or self.queue or hstate == S.ST_RUNNING:
            return "running"
        return "idle"

    def wait(self, timeout_s: float) -> dict:
        """Block until idle (no motion queued or running) or fault, or the timeout; returns the status.

        Polls the cheap state (not the whole status: its statistics and thermal report would take
        the interpreter from the feeder thread every 20 ms of every waiting client)."""
        t_end = time.monotonic() + max(0.0, float(timeout_s))
        while True:
            sh = self.sh
            if sh is None or not self.alive:
                return self.status()
            with self.lock:
                state = self._motion_state(sh.h[S.H_STATE])
            if state in ("idle", "fault"):
                st = self.status()
                if st["state"] in ("idle", "fault"):
                    return st
            left = t_end - time.monotonic()
            if left <= 0:
                st = self.status()
                st["timeout"] = True
                return st
            with self.cv:
                self.cv.wait(min(left, 0.02))


def waiting_reason(hstate: int, fault, awaiting_enable: bool) -> str | None:
    """Why the machine does not move on its own (status key ``waiting``), or None."""
    if fault is None and (hstate == S.ST_DISABLED or (hstate == S.ST_BOOT and awaiting_enable)):
        return ("waiting for enable: the drives are disabled " + ("since the start ([daemon] enable_at_start "
                "is false)" if hstate == S.ST_BOOT else "") + "; a controller sends 'enable' (or 'reset')")
    return None
