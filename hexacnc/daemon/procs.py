"""Process management of the supervisor: the hot loop process, its watch, the bus and socket locks.

* :class:`HotProcess` starts ``python -m hexacnc.daemon.hot`` and reads its ready/error report.
* :class:`HotWatch` (a thread of the supervisor) notices when the hot loop ends without being told
  to (crash, SIGKILL, a signal to it alone) or hangs (SIGSTOP, a stuck cycle: its beat stops for
  ``HANG_S``; it is then killed, so it can never wake up later and command from a stale state).
  The drives stop on their own in those cases (their communication-loss reaction); the watch
  records what happened (:class:`HotEnd`) for the status, the log and the exit code.
* :func:`acquire_lock`: one daemon per bus interface and per socket (``flock`` on a lock file
  holding the owner's pid), taken before the first frame.
"""
from __future__ import annotations

import errno
import fcntl
import json
import os
import pickle
import select
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

from ..errors import BusError
from . import shm as S

#: the hot loop's beat (written every cycle) older than this while the process is stopped
#: (SIGSTOP: state T): hung, it is killed. Only reporting depends on it (the drives stop on their
#: own within [bus] comm_loss_timeout_s)
HANG_S = 0.3
#: ... and older than this while it is runnable: stuck in its cycle (a loaded 2-CPU VM without
#: SCHED_FIFO, with several daemons' hot loops on one CPU, starved a hot process for over 1 s)
STUCK_S = 5.0
#: how often the watch looks (s)
WATCH_PERIOD_S = 0.01


class HotProcess:
    """Handle of the hot loop subprocess (``python -m hexacnc.daemon.hot``)."""

    def __init__(self, args: dict, fds: tuple = ()):
        r, w = os.pipe()
        try:
            self.proc = subprocess.Popen([sys.executable, "-m", "hexacnc.daemon.hot", str(w)],
                                         stdin=subprocess.PIPE, pass_fds=(w,) + tuple(fds), close_fds=True)
        finally:
            os.close(w)
        self._r = r
        self.pid = self.proc.pid
        try:
            self.proc.stdin.write(pickle.dumps(args))
            self.proc.stdin.close()
        except BrokenPipeError:
            pass

    def wait_report(self, timeout_s: float):
        """The ready/error message, or None on timeout or exit."""
        buf = b""
        t_end = time.monotonic() + timeout_s
        try:
            while time.monotonic() < t_end:
                rd, _, _ = select.select([self._r], [], [], 0.05)
                if rd:
                    chunk = os.read(self._r, 65536)
                    if not chunk:
                        break
                    buf += chunk
                    if buf.endswith(b"\n"):
                        return json.loads(buf)
                elif self.proc.poll() is not None:
                    break
            return None
        finally:
            os.close(self._r)

    def is_alive(self) -> bool:
        return self.proc.poll() is None

    @property
    def returncode(self):
        return self.proc.poll()

    def join(self, timeout_s: float) -> None:
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            pass

    def terminate(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()


@dataclass
class HotEnd:
    """How the hot loop ended without the supervisor ordering it."""
    code: str           #: "signal" (controlled stop on SIGTERM/SIGHUP), "loop_died", "loop_hung"
    message: str
    clean: bool         #: motion stopped and drives disabled by the loop, no fault
    t_ns: int           #: monotonic ns when the supervisor noticed


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def classify_exit(h, returncode: int | None) -> HotEnd:
    """What an unordered exit of the hot loop means, from its last header ``h`` and exit status."""
    now = time.monotonic_ns()
    sig = h[S.H_EXIT_SIGNAL]
    if h[S.H_EXIT] == 1 and sig and h[S.H_FAULT] == 0:
        return HotEnd("signal", f"hot loop stopped by {signal_name(sig)}: motion stopped, drives disabled",
                      True, now)
    if h[S.H_EXIT] == 1:
        return HotEnd("loop_died", "hot loop exited after a fault: motion stopped, drives disabled", False, now)
    if h[S.H_EXIT] == 2:
        return HotEnd("loop_died", "hot loop process died (crashed in its cycle): the drives stop on their own "
                                   "(communication-loss reaction)", False, now)
    how = (f"killed by {signal_name(-returncode)}" if returncode is not None and returncode < 0
           else f"exit status {returncode}")
    return HotEnd("loop_died", f"hot loop process died ({how}): the drives stop on their own "
                               "(communication-loss reaction)", False, now)


class HotWatch(threading.Thread):
    """Watch the hot loop: ``on_end(HotEnd)`` once when it ends or hangs without being told to."""

    def __init__(self, hot: HotProcess, sh: S.Shared, on_end, hang_s: float = HANG_S,
                 stuck_s: float = STUCK_S):
        super().__init__(name="hexacnc-hotwatch", daemon=True)
        self.hot = hot
        self.sh = sh
        self.on_end = on_end
        self.hang_ns = int(hang_s * 1e9)
        self.stuck_ns = int(stuck_s * 1e9)
        self.ordered = threading.Event()       #: set before the supervisor stops the hot loop
        self.end: HotEnd | None = None

    def run(self) -> None:
        h = self.sh.h
        last = time.monotonic_ns()
        while not self.ordered.wait(WATCH_PERIOD_S):
            now = time.monotonic_ns()
            starved = now - last > 5 * WATCH_PERIOD_S * 1e9     # we were not scheduled either
            last = now
            rc = self.hot.returncode
            if rc is not None:
                if self.ordered.is_set():
                    return
                self._ended(classify_exit(h, rc))
                return
            beat = h[S.H_LOOP_BEAT_NS]
            if beat and h[S.H_EXIT] == 0 and not starved:
                age = time.monotonic_ns() - beat
                if age > self.hang_ns and not self.ordered.is_set() and (
                        age > self.stuck_ns or process_state(self.hot.pid) in ("T", "t")):
                    self.hot.kill()
                    self._ended(HotEnd("loop_hung", f"hot loop hung ({age // 1_000_000} ms without a "
                                       "cycle): killed; the drives stop on their own (communication-loss "
                                       "reaction)", False, time.monotonic_ns()))
                    return

    def _ended(self, end: HotEnd) -> None:
        self.end = end
        self.on_end(end)


def process_state(pid: int) -> str:
    """The kernel's one-letter state of ``pid`` (R, S, D, T stopped, t traced, Z ...), "" if gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return ""


# -- locks ------------------------------------------------------------------------------------
def lock_dir() -> str:
    """Where bus locks live: ``$HEXACNC_LOCK_DIR``, else ``/run/lock`` when writable (shared by a
    systemd unit with PrivateTmp and a daemon started by hand), else ``$XDG_RUNTIME_DIR``, else /tmp."""
    d = os.environ.get("HEXACNC_LOCK_DIR")
    if d:
        return d
    if os.access("/run/lock", os.W_OK | os.X_OK):
        return "/run/lock"
    return os.environ.get("XDG_RUNTIME_DIR") or "/tmp"


def bus_lock_path(cfg) -> str:
    """Lock file of the bus interface (per network namespace: vcan/udp_multicast live in one)."""
    try:
        ns = os.stat("/proc/self/ns/net").st_ino
    except OSError:
        ns = 0
    chan = "".join(c if c.isalnum() or c in "-_." else "_" for c in str(cfg.bus.channel))
    return os.path.join(lock_dir(), f"hexacnc-bus-{cfg.bus.interface}-{chan}-net{ns}.lock")


def acquire_lock(path: str, what: str) -> int:
    """Exclusive lock on ``path`` (created 0644, our pid written); returns the fd (keep it open).

    Raises :class:`BusError` naming the other daemon's pid when it is held."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        raise BusError(f"cannot create the lock {path} for {what}: {exc.strerror or exc}") from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        other = ""
        try:
            other = os.pread(fd, 32, 0).decode(errors="replace").strip()
        except OSError:
            pass
        os.close(fd)
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise BusError(f"{what} is in use by another hexacnc daemon (pid {other or 'unknown'}, lock "
                           f"{path}); stop it first") from None
        raise BusError(f"cannot lock {path} for {what}: {exc.strerror or exc}") from exc
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def release_lock(fd: int | None) -> None:
    if fd is not None:
        try:
            os.close(fd)
        except OSError:
            pass
