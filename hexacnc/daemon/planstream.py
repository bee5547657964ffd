"""Programs of any length in the daemon: streamed validation and windowed planning in bounded children.

A program is handled by two forkserver children (as :mod:`.planproc`: ``RLIMIT_AS`` =
``[daemon] max_plan_memory_mb``, ``SIGALRM`` after ``max_plan_s``):

* the **validator** streams the text through the interpreter (:func:`hexacnc.gcode.textstream.iter_text_blocks`)
  and checks every window's path (strut lengths, joint angles, singularity, soft limits, continuity:
  :func:`hexacnc.planner.grid.check_path`) without its time parameterisation; it answers ``valid`` (blocks,
  nominal seconds) or the first error with line and reason;
* the **planner** streams the text again and plans window by window (:func:`hexacnc.planner.window.plan_windows`),
  sending each window to the supervisor only when granted: :data:`AHEAD_WINDOWS` beyond the one the
  motion needs.  Both hold one window at a time: memory is proportional to the look-ahead.

By default (``[planner] start_before_validated = false``) nothing moves until the validator has checked the
whole program.  With ``true`` the motion starts as soon as the first window is planned; an error the
validator finds later stops the motion at once with a controlled stop (the error's window is never
planned, so the motion is always before the bad line) and is reported with its line and reason.

The time bound ``max_plan_s`` applies to each window (re-armed per window: interpreting, checking and
planning at most ``window_blocks`` blocks), not to the program: a 10 h program is never refused for its
length, while an interpreter loop without motion or a pathological window still is.  The planner's bound
is disarmed while it waits for the motion to need more.
"""
from __future__ import annotations

import logging
import signal
import threading
import time

from ..errors import HexacncError, PlanError
from ..planner.timefit import Counted, Planned, unplanned_s
from .progtext import count_lines, pieces
from .planproc import PlanLimit, _context, _error_fields, _innermost, line_reached, refusal

log = logging.getLogger("hexacnc.daemon.planstream")

#: windows planned ahead of the one the motion is in
AHEAD_WINDOWS = 2
#: (MSG, ...) comments kept for the status (the first ones; memory stays bounded whatever the program)
MAX_MESSAGES = 10_000
#: motion lines whose feed the planner holds before it hands them out with their window
MAX_FEED_LINES = 200_000


#: niceness of the validator, which runs flat out for minutes on a long program: background work beside the
#: supervisor's feeder and the simulated drives (the planner needs ~1 % of a CPU on average, in bursts that
#: the motion may wait for: it keeps the normal priority)
VALIDATOR_NICE = 10
#: with start_before_validated the validator starts once the first window is planned (or after this long),
#: so that it does not compete with the first window
VALIDATOR_DELAY_S = 2.0


def _setup(max_mb: float, stream_ref: list, nice: int = 0) -> None:
    import os
    import resource
    if nice:
        try:
            os.nice(nice)
        except OSError:
            pass
    if max_mb > 0:
        lim = int(max_mb) << 20
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))

    def alarm(signum, frame):
        stage, line = line_reached(frame)
        if not line and stream_ref:
            line = int(getattr(stream_ref[0]._it, "line_now", 0) or 0)
            stage = "interpreting"
        raise PlanLimit(stage, line)
    signal.signal(signal.SIGALRM, alarm)


def _arm(max_s: float) -> None:
    signal.setitimer(signal.ITIMER_REAL, float(max_s) if max_s > 0 else 0.0)


def _failure(exc: BaseException, name: str) -> tuple:
    signal.setitimer(signal.ITIMER_REAL, 0.0)
    if isinstance(exc, PlanLimit):
        return ("time", exc.args[0], exc.args[1])
    stage, line = line_reached(_innermost(exc.__traceback__))
    if isinstance(exc, MemoryError):
        return ("memory", stage, line)
    if isinstance(exc, HexacncError):
        return ("error", _error_fields(exc))
    return ("error", {"kind": "HexacncError", "text": f"{name}: internal error while {stage}"
                      + (f" at line {line}" if line else "") + f": {type(exc).__name__}: {exc}"})


def _recv_text(conn) -> str:
    """The program text, sent in pieces after the child started (:meth:`StreamPlan._send_text`)."""
    parts = []
    while True:
        msg = conn.recv()
        if msg[0] == "text":
            parts.append(msg[1])
        elif msg[0] == "text_end":
            return "".join(parts)


def _blocks(cfg, text: str, name: str, start_tip, state=None):
    """The program's block stream: from the machine's defaults, or from the operator's persistent
    ``state`` (:class:`hexacnc.state.MachineState`: offsets, G92, tools, the modal state left)."""
    if state is not None:
        from ..state import interpret_stream
        return interpret_stream(text, name, cfg, start_tip, state)
    from ..gcode.factory import machine_defaults
    from ..gcode.textstream import iter_text_blocks
    kw = machine_defaults(cfg)
    kw["start_pose"] = start_tip
    return iter_text_blocks(text, name, **kw)


class _Counted:
    """The blocks of a stream, counting motion blocks, M62-M68 / M66 blocks and the blocks that take time
    standing still (a G4 of more than 0 s, M0, M1) on the way."""

    def __init__(self, blocks):
        from ..gcode import blocks as B
        self._it = iter(blocks)
        self._motion, self._io, self._still = B.MOTION_KINDS, B.IO, B.holds_still
        self.motion = 0
        self.io = 0
        self.timed = 0

    def __iter__(self):
        return self

    def __next__(self):
        b = next(self._it)
        k = b.kind
        if k in self._motion:
            self.motion += 1
        elif k == self._io:
            self.io += 1
        elif self._still(b):
            self.timed += 1
        return b


def _validate_child(conn, cfg, name, start_tip, start_rad, max_mb, max_s, state=None) -> None:
    from ..planner.window import validate_windows
    ref: list = []
    _setup(max_mb, ref, VALIDATOR_NICE)
    try:
        text = _recv_text(conn)
        stream = _blocks(cfg, text, name, start_tip, state)
        ref.append(stream)
        del text
        counted = _Counted(stream)
        nb, est, end = 0, 0.0, start_rad
        _arm(max_s)
        for nb, est, line, end in validate_windows(counted, cfg, start_rad=start_rad):
            conn.send(("checked", line, nb, est))
            _arm(max_s)
        _arm(0)
        prog = stream.wait_program()        # set by the interpreter thread, maybe after the last block
        if prog is None:
            raise HexacncError(f"{name}: the interpreter did not reach the program's end")
        extra = {"motion_blocks": counted.motion, "io_blocks": counted.io, "timed_blocks": counted.timed,
                 "messages": list(prog.messages[:MAX_MESSAGES])}
        if state is not None:
            from ..state import state_after_stream
            extra["state"] = state_after_stream(stream)
        out = ("valid", nb, est, end, extra)
    except BaseException as exc:       # noqa: BLE001 - every failure is an answer
        out = _failure(exc, name)
    conn.send(out)
    conn.close()


class _Feeds:
    """The blocks of a stream, noting the programmed feed (mm/min; None for rapids) of each motion
    line, handed out per window (the operator's status shows the feed of the line being run)."""

    def __init__(self, blocks):
        from ..gcode import blocks as B
        self._it = iter(blocks)
        self._motion, self._rapid = B.MOTION_KINDS, B.RAPID
        self.seen: dict = {}

    def __iter__(self):
        return self

    def __next__(self):
        b = next(self._it)
        if b.kind in self._motion:
            f = b.feed_mm_s
            if len(self.seen) >= MAX_FEED_LINES:
                self.seen.clear()
            self.seen[int(b.line)] = 60.0 * f if f is not None and b.kind != self._rapid else None
        return b

    def take(self, w) -> dict:
        lo, hi = w.first_line, w.last_line
        out = {k: v for k, v in self.seen.items() if lo <= k <= hi}
        for k in out:
            del self.seen[k]
        return out


def _stream_child(conn, cfg, name, start_tip, period_s, max_mb, max_s, state=None) -> None:
    from ..kinematics import Hexapod
    from ..planner.window import FIRST_WINDOW_BLOCKS, plan_windows
    ref: list = []
    _setup(max_mb, ref)
    granted = 0
    try:
        text = _recv_text(conn)
        stream = _blocks(cfg, text, name, start_tip, state)
        ref.append(stream)
        del text
        feeds = _Feeds(stream)
        first = FIRST_WINDOW_BLOCKS if cfg.planner.start_before_validated else 0
        gen = plan_windows(feeds, cfg, hexapod=Hexapod(cfg), period_s=period_s, start_pose=start_tip,
                           first_blocks=first)
        while True:
            _arm(max_s)
            w = next(gen, None)
            _arm(0)
            if w is None:
                break
            w.feeds = feeds.take(w)
            while w.index >= granted:
                msg = conn.recv()
                if msg[0] == "grant":
                    granted = int(msg[1])
            conn.send(("window", w))
            del w
        out = ("done",)
    except (EOFError, BrokenPipeError):
        return
    except BaseException as exc:       # noqa: BLE001
        out = _failure(exc, name)
    try:
        conn.send(out)
    except (BrokenPipeError, OSError):
        pass
    conn.close()


class _Child:
    """One child process and the thread that receives its messages."""

    def __init__(self, target, args: tuple, on_message, name: str):
        ctx = _context()
        self.conn, child_conn = ctx.Pipe(duplex=True)
        self.proc = ctx.Process(target=target, args=(child_conn, *args), name=name, daemon=True)
        self.proc.start()
        child_conn.close()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._recv_loop, args=(on_message,), name=name, daemon=True)
        self._thread.start()

    def _recv_loop(self, on_message) -> None:
        while True:
            try:
                msg = self.conn.recv()
            except (EOFError, OSError):
                self.proc.join(1.0)
                msg = None
            except MemoryError:
                msg = ("memory", "planning", 0)
            on_message(msg)
            if msg is None or msg[0] not in ("window", "checked"):
                return

    def send(self, msg) -> None:
        """Send to the child; nothing happens once it is gone or killed (a stop while the text is sent)."""
        with self._lock:
            try:
                self.conn.send(msg)
            except (OSError, ValueError, TypeError):    # TypeError: closed meanwhile (handle None)
                pass

    def kill(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join(1.0)
        # a send in progress ends with EPIPE now that the child is dead: close after it, never under
        # it (multiprocessing's Connection is not thread-safe: the sender then met a None handle)
        locked = self._lock.acquire(timeout=2.0)
        try:
            self.conn.close()
        except OSError:
            pass
        finally:
            if locked:
                self._lock.release()


class StreamPlan:
    """A program streamed through a validator and a windowed planner (see the module docstring); also the
    window feed of a :class:`~hexacnc.planner.chain.ChainSampler` (``window``, ``peek``, ``release``,
    ``finished``, ``error``, ``total_lines``)."""

    def __init__(self, cfg, text, name: str, start_rad, period_s: float, state=None, on_valid=None,
                 start: bool = True):
        """``text``: the program (str, or the list of chunks of an upload: :mod:`.progtext`; it reaches
        the children in pieces, never as one pickled object); ``state``: interpret from the operator's persistent state (:class:`hexacnc.state.MachineState`;
        the state after the program is then ``final_state`` once validated); ``on_valid``: called (from
        a receiver thread) once the validator has checked the whole program, before ``end_rad`` is set
        and ready is signalled; ``start`` false: the children start with :meth:`start` (the caller can
        register the object first, so that a stop that comes while the text is sent cancels it)."""
        from ..planner.window import tool_tip_pose_deg
        d = cfg.daemon
        self.max_mb = float(getattr(d, "max_plan_memory_mb", 0) or 0)
        self.max_s = float(getattr(d, "max_plan_s", 0) or 0)
        self.name = name
        self.before_validated = bool(cfg.planner.start_before_validated)
        text = pieces(text)
        self.total_lines = count_lines(text)
        self.finished = False
        self.error: HexacncError | None = None
        self.validation: dict = {"state": "running", "line": 0, "blocks": 0}
        self.invalid: HexacncError | None = None
        self.end_rad = None             #: platform pose (mm, rad) at the program's end, once validated
        self.on_invalid = None          #: called with the error the validator finds (after the start)
        self.cancelled = False
        self.final_state = None         #: the persistent state after the program (with ``state``), once valid
        self.messages: list = []        #: (line, text) of its (MSG, ...) comments, once valid
        self.motion_blocks = None       #: motion blocks of the whole program, once valid
        self.io_blocks = None           #: M62-M68 / M66 blocks of the whole program, once valid
        self.timed_blocks = None        #: dwells (> 0 s) and M0/M1 of the whole program, once valid
        self.on_valid = on_valid
        self.planned = Planned()        #: the windows received so far (seconds, nominal seconds, blocks, ...)
        self._checked_nominal_s = None  #: the validator's nominal seconds so far (its last "checked" report)
        self._cv = threading.Condition()
        self._have: dict = {}
        self._granted = 0
        self.t0 = time.monotonic()
        tip = tool_tip_pose_deg(cfg, start_rad)
        self._text = text               # until both children have it
        self._plan = self._val = None
        self._args = ((cfg, name, tip, period_s, self.max_mb, self.max_s, state),
                      (cfg, name, tip, start_rad, self.max_mb, self.max_s, state))
        if start:
            self.start()

    def start(self) -> None:
        """Start the planner (and the validator) and send them the text (see ``start`` of the constructor)."""
        plan_args, val_args = self._args
        with self._cv:
            if self.cancelled or self._plan is not None:
                return
        plan = _Child(_stream_child, plan_args, self._on_plan, "hexacnc-plan")
        with self._cv:
            self._plan, cancelled = plan, self.cancelled
        if cancelled:                   # a stop while the child was started: cancel() did not see it
            plan.kill()
            return
        self._send_text(self._plan)
        self._grant(AHEAD_WINDOWS)
        if self.before_validated:
            threading.Thread(target=self._start_validator, args=(val_args, VALIDATOR_DELAY_S),
                             name="hexacnc-validate-start", daemon=True).start()
        else:
            self._start_validator(val_args, 0.0)

    def _start_validator(self, args: tuple, delay_s: float) -> None:
        with self._cv:
            t_end = time.monotonic() + delay_s
            while 0 not in self._have and not self.finished and not self.cancelled and time.monotonic() < t_end:
                self._cv.wait(0.05)
            if self.cancelled:
                return
            self._val = _Child(_validate_child, args, self._on_val, "hexacnc-validate")
        self._send_text(self._val)
        self._text = None

    def _send_text(self, child) -> None:
        for p in self._text:
            if self.cancelled:
                return
            child.send(("text", p))
        child.send(("text_end",))

    # -- messages (receiver threads) ----------------------------------------------------------
    def _exc(self, msg, child=None) -> HexacncError:
        if msg is None:
            code = child.proc.exitcode if child is not None else None
            if code is not None and code < 0 and self.max_mb > 0:
                return PlanError(f"{self.name}: planning ended by signal {-code} (over [daemon] max_plan_memory_mb "
                                 f"= {self.max_mb:g} MB?)", limit="max_plan_memory_mb")
            return HexacncError(f"{self.name}: the planning process ended without an answer (exit {code})")
        return refusal(self.name, msg, self.max_s, self.max_mb)

    def _on_val(self, msg) -> None:
        cb = None
        if msg is not None and msg[0] == "valid":
            extra = msg[4] if len(msg) > 4 else {}
            with self._cv:
                self.final_state = extra.get("state")
                self.messages = extra.get("messages", [])
                self.motion_blocks, self.io_blocks = extra.get("motion_blocks"), extra.get("io_blocks")
                self.timed_blocks = extra.get("timed_blocks")
                ok = not self.cancelled
            if ok and self.on_valid is not None:
                try:                    # before ready / end_rad: the state is committed before the next load
                    self.on_valid(self)
                except Exception:       # noqa: BLE001 - the program's answer must still come
                    log.exception("%s: after its validation", self.name)
        with self._cv:
            if msg is not None and msg[0] == "checked":
                self.validation.update(line=msg[1], blocks=msg[2])
                self._checked_nominal_s = float(msg[3]) if len(msg) > 3 else None
                return
            if msg is not None and msg[0] == "valid":
                self.validation.update(state="valid", blocks=msg[1], estimate_s=round(msg[2], 3))
                self.end_rad = msg[3]
            elif not self.cancelled:
                self.invalid = self._exc(msg, self._val)
                self.validation.update(state="invalid", error=str(self.invalid),
                                       error_line=getattr(self.invalid, "line", None))
                cb = self.on_invalid
            self._cv.notify_all()
        if cb is not None:
            cb(self.invalid)

    def _on_plan(self, msg) -> None:
        with self._cv:
            if msg is not None and msg[0] == "window":
                w = msg[1]
                self._have[w.index] = w
                self.planned.add(w)
                self.finished = self.finished or w.last
            elif msg is not None and msg[0] == "done":
                self.finished = True
            elif not self.cancelled and not self.finished:
                self.error = self._exc(msg, self._plan)
                self.finished = True
            self._cv.notify_all()

    def _grant(self, n: int) -> None:
        if n > self._granted and self._plan is not None:
            self._granted = n
            self._plan.send(("grant", n))

    def unplanned_s(self) -> float:
        """Estimated seconds of the program's part not planned yet, learnt from the windows planned so far
        (:mod:`hexacnc.planner.timefit`: per line, planned seconds against nominal seconds at the programmed
        feeds and blocks; 3D_Chips.ngc's F4.5e6, capped at the rapid feed, gives 24 s nominal for 89 s
        planned) and applied to the validation's totals.  Before the validation has counted the program
        (``start_before_validated``): the same fit applied to the validator's counts so far scaled to the
        program's lines, once the validator is ahead of the planner (the first window holds the approach from
        home: by lines alone the fast raster of tests/test_timefit.py is +84 % after it, +42 % / +26 % with
        the validator 2x / 4x as far); else by the program's lines.  0 once every window is planned."""
        with self._cv:
            if self.finished:
                return 0.0
            val = self.validation
            whole = val.get("state") == "valid"
            nominal = float(val.get("estimate_s", 0.0)) if whole else self._checked_nominal_s
            counted = None if nominal is None else Counted(int(val.get("line", 0)), nominal,
                                                           int(val.get("blocks", 0)), whole)
            return unplanned_s(self.planned, self.total_lines, counted)

    @property
    def planned_s(self) -> float:
        """Planned seconds of the windows received so far."""
        return self.planned.seconds

    # -- window feed ----------------------------------------------------------------------------
    def window(self, i: int):
        self._grant(i + 1 + AHEAD_WINDOWS)
        with self._cv:
            return self._have.get(i)

    def peek(self, i: int):
        with self._cv:
            return self._have.get(i)

    def feed_at(self, line: int):
        """Programmed feed (mm/min; None: a rapid or not known) of ``line`` in the windows held."""
        with self._cv:
            for w in self._have.values():
                f = getattr(w, "feeds", None)
                if f and line in f:
                    return f[line]
        return None

    def release(self, i: int) -> None:
        with self._cv:
            for k in [k for k in self._have if k < i]:
                del self._have[k]

    # -- control ----------------------------------------------------------------------------------
    def wait_ready(self) -> "object":
        """The first window once motion may start: after the validation (default), or at once with
        ``start_before_validated``.  Raises the program's error (nothing moved), or when cancelled."""
        with self._cv:
            while True:
                if self.cancelled:
                    raise HexacncError(f"{self.name}: stopped while it was being interpreted and planned")
                if self.invalid is not None:
                    raise self.invalid
                first = self._have.get(0)
                valid = self.validation["state"] == "valid"
                if first is not None and (valid or self.before_validated):
                    return first
                if first is None and self.error is not None and (valid or self.before_validated):
                    raise self.error
                if self.finished and first is None and self.error is None:
                    raise HexacncError(f"{self.name}: the planner sent no window")
                self._cv.wait(0.05)

    def cancel(self) -> None:
        with self._cv:
            self.cancelled = True
            self._cv.notify_all()
            val, plan = self._val, self._plan
        for child in (val, plan):
            if child is not None:
                child.kill()

    close = cancel

    def alive(self) -> list:
        return [c.proc for c in (self._val, self._plan) if c is not None and c.proc.is_alive()]


__all__ = ["StreamPlan", "AHEAD_WINDOWS", "PlanError"]
