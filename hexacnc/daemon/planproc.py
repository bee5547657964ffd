"""Parsing and planning off the control path: a child process with bounded memory and time.

:func:`plan_bounded` interprets and plans one program in a child process (``multiprocessing``
forkserver: forked from a clean single-threaded server that has the interpreter and planner
imported, so a child starts in milliseconds, not the supervisor's threads). The child runs under
``RLIMIT_AS`` = ``[daemon] max_plan_memory_mb`` (plus what the interpreter itself needs) and
``SIGALRM`` after ``[daemon] max_plan_s``; :meth:`PlanJob.cancel` (a ``stop``) kills it at once.
A program over a bound is refused with a :class:`~hexacnc.errors.PlanError` naming the limit, the
stage (interpreting or planning) and the program line reached. The supervisor's own memory holds
only the finished plan (bounded by what the child could build).
"""
from __future__ import annotations

import multiprocessing as mp
import signal

import numpy as np
import threading
import time

from ..errors import GcodeError, HexacncError, PlanError

_CTX = None
_CTX_LOCK = threading.Lock()
#: modules the forkserver imports once (children start with them loaded: those a plan imports on its first
#: call included, else every child pays ~0.7 s of imports before its first window)
PRELOAD = ["hexacnc.daemon.program", "hexacnc.daemon.planstream", "hexacnc.gcode", "hexacnc.gcode.textstream",
           "hexacnc.planner", "hexacnc.planner.window", "hexacnc.planner.sampler", "hexacnc.planner.smooth",
           "hexacnc.planner.chain", "hexacnc.kinematics", "ruckig", "scipy.linalg"]


def _context():
    global _CTX
    with _CTX_LOCK:
        if _CTX is None:
            ctx = mp.get_context("forkserver")
            ctx.set_forkserver_preload(PRELOAD)
            _CTX = ctx
        return _CTX


def warm() -> None:
    """Start the forkserver (it imports PRELOAD once), so that the first program's children start at once."""
    _context()
    from multiprocessing import forkserver
    try:
        forkserver.ensure_running()
    except Exception:           # noqa: BLE001 - a later program starts it (and reports why it cannot)
        pass


class PlanLimit(Exception):
    """Raised inside the child by the time alarm."""


def line_reached(frame) -> tuple[str, int]:
    """(stage, program line) of the innermost interpreter or planner frame at or above ``frame``."""
    f = frame
    while f is not None:
        loc = f.f_locals
        mod = f.f_globals.get("__name__", "")
        if mod.startswith("hexacnc.gcode"):
            ln = loc.get("ln")
            num = getattr(ln, "num", None)
            if isinstance(num, int):
                return "interpreting", num
            me = loc.get("self")
            num = getattr(me, "line_now", None)
            if isinstance(num, int) and num > 0:
                return "interpreting", num
        elif mod.startswith("hexacnc.planner"):
            for name, v in loc.items():
                num = v if name in ("line", "line_no") else getattr(v, "line", None)
                if isinstance(num, (int, np.integer)) and not isinstance(num, bool) and num > 0:
                    return "planning", int(num)
                if isinstance(v, list) and v and isinstance(getattr(v[-1], "line", None), int):
                    return "planning", int(v[-1].line)      # blocks / pieces built so far
        f = f.f_back
    f = frame
    while f is not None:
        if f.f_globals.get("__name__", "").startswith("hexacnc.planner"):
            return "planning", 0
        f = f.f_back
    return "interpreting", 0


def _error_fields(exc: HexacncError) -> dict:
    """A child's error as plain fields (exceptions with extra constructor arguments do not pickle)."""
    f = {"kind": type(exc).__name__, "message": getattr(exc, "bare_message", str(exc))}
    for k in ("line", "column", "code", "limit"):
        if hasattr(exc, k):
            f[k] = getattr(exc, k)
    f["text"] = str(exc)
    return f


def _error_from(f: dict) -> HexacncError:
    if f["kind"] == "GcodeError":
        return GcodeError(f["message"], f.get("line"), f.get("column"), f.get("code", "gcode"))
    if f["kind"] == "PlanError":
        return PlanError(f["message"], f.get("line"), f.get("limit"), f.get("code", "limit"))
    return HexacncError(f["text"])


def _innermost(tb):
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb.tb_frame if tb is not None else None


def _child(conn, cfg, text, name, start_rad, period_s, max_mb, max_s, work=None, work_args=()) -> None:
    import resource
    if max_mb > 0:
        lim = int(max_mb) << 20
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))

    def alarm(signum, frame):
        raise PlanLimit(*line_reached(frame))
    signal.signal(signal.SIGALRM, alarm)
    if max_s > 0:
        signal.setitimer(signal.ITIMER_REAL, float(max_s))
    try:
        if work is not None:            # another interpret-and-plan (the operator's: persistent state in and out)
            res = work(cfg, text, name, start_rad, period_s, *work_args)
            signal.setitimer(signal.ITIMER_REAL, 0.0)
            out = ("ok",) + tuple(res)
        else:
            from ..kinematics import Hexapod
            from .program import plan_program
            plan = plan_program(cfg, Hexapod(cfg), text, name, start_rad, period_s)
            signal.setitimer(signal.ITIMER_REAL, 0.0)
            out = ("ok", plan.source.plan, plan.blocks, plan.duration_s, plan.end_rad, plan.summary)
    except PlanLimit as exc:
        out = ("time", exc.args[0], exc.args[1])
    except MemoryError as exc:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        stage, line = line_reached(_innermost(exc.__traceback__))
        out = ("memory", stage, line)
    except HexacncError as exc:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        out = ("error", _error_fields(exc))
    except Exception as exc:           # a bug in the interpreter or planner: a clear refusal, not silence
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        stage, line = line_reached(_innermost(exc.__traceback__))
        out = ("error", {"kind": "HexacncError",
                         "text": f"{name}: internal error while {stage}" + (f" at line {line}" if line else "")
                                 + f": {type(exc).__name__}: {exc}"})
    try:
        conn.send(out)
    except MemoryError:
        conn.send(("memory", "planning", 0))
    conn.close()


class PlanJob:
    """One program being planned in a child; :meth:`result` waits, :meth:`cancel` kills."""

    def __init__(self, cfg, text: str, name: str, start_rad, period_s: float, work=None, work_args: tuple = ()):
        """``work``: a module-level function ``work(cfg, text, name, start_rad, period_s, *work_args)``
        run in the child instead of the plain interpret-and-plan; its returned tuple is what
        :meth:`result` returns."""
        d = cfg.daemon
        self.max_mb = float(getattr(d, "max_plan_memory_mb", 0) or 0)
        self.max_s = float(getattr(d, "max_plan_s", 0) or 0)
        self.name = name
        ctx = _context()
        self._r, w = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=_child, args=(w, cfg, text, name, start_rad, period_s, self.max_mb,
                                                     self.max_s, work, work_args), name="hexacnc-plan", daemon=True)
        self.proc.start()
        w.close()
        self.cancelled = False
        self.t0 = time.monotonic()

    def cancel(self) -> None:
        self.cancelled = True
        if self.proc.is_alive():
            self.proc.kill()

    def result(self):
        """``(plan, blocks, duration_s, end_rad, summary)``; raises GcodeError/PlanError/HexacncError."""
        grace = self.max_s + 5.0 if self.max_s > 0 else None
        try:
            while True:
                if self._r.poll(0.05):
                    try:
                        msg = self._r.recv()
                    except EOFError:
                        msg = None
                    break
                if not self.proc.is_alive() and not self._r.poll(0):
                    msg = None
                    break
                if grace is not None and time.monotonic() - self.t0 > grace:
                    self.proc.kill()        # the alarm did not fire (stuck in C): refuse anyway
                    msg = ("time", "planning", 0)
                    break
        finally:
            self._r.close()
            self.proc.join(1.0)
            if self.proc.is_alive():
                self.proc.kill()
        if self.cancelled:
            raise HexacncError(f"{self.name}: stopped while it was being interpreted and planned")
        if msg is None:
            code = self.proc.exitcode
            if code is not None and code < 0 and self.max_mb > 0:
                raise PlanError(f"{self.name}: planning ended by signal {-code} (over [daemon] max_plan_memory_mb "
                                f"= {self.max_mb:g} MB?)", limit="max_plan_memory_mb")
            raise HexacncError(f"{self.name}: the planning process ended without an answer (exit {code})")
        if msg[0] == "ok":
            return msg[1:]
        raise refusal(self.name, msg, self.max_s, self.max_mb)


def refusal(name: str, msg: tuple, max_s: float, max_mb: float) -> HexacncError:
    """The exception for a child's ("error", fields), ("time", stage, line) or ("memory", stage, line)."""
    kind = msg[0]
    if kind == "error":
        return _error_from(msg[1])
    stage, line = msg[1], msg[2]
    where = f" at line {line}" if line else ""
    if kind == "time":
        return PlanError(f"{name}: {stage} took longer than [daemon] max_plan_s = {max_s:g} s "
                         f"(stopped{where}); split the program or raise the limit", line=line or None,
                         limit="max_plan_s")
    return PlanError(f"{name}: {stage} needs more than [daemon] max_plan_memory_mb = {max_mb:g} MB "
                     f"(stopped{where}); split the program or raise the limit", line=line or None,
                     limit="max_plan_memory_mb")


__all__ = ["PlanJob", "line_reached", "refusal", "GcodeError"]
