"""The daemon's socket server (supervisor process, never the hot loop's process).

One selector thread owns every socket: a Unix stream socket (mode 0660) and,
only when ``[daemon] tcp_port`` is set, a TCP socket bound to 127.0.0.1 whose
clients must first send ``hello`` with the ``[daemon] tcp_token``.  Requests are
validated by :mod:`hexacnc.daemon.protocol` apart from their handling:

* ``hello`` and ``status`` are answered inline (``Daemon.status`` reads shared state);
* motion ops (program/pause/resume/stop/reset) run in order on one worker
  thread, so parsing and planning a long program never stalls other clients;
* ``wait`` runs on its own thread in short slices of ``Daemon.wait`` and is
  dropped when its client goes away;
* subscriptions are served from the selector loop at their rate; a client that
  does not read its stream loses samples instead of growing a queue.

Results from worker threads come back through a queue and a wake-up socket
pair, so only the selector thread ever writes to a client.  Anything a client
sends - bad maps, unknown ops, random bytes, huge messages - costs that client
an error reply or its connection, never the loop or the other clients.

Usage::

    srv = SocketServer(daemon, cfg)          # socket path from [daemon] socket_path
    srv.start()                              # background thread
    ...
    srv.close()
"""
from __future__ import annotations

import logging
import queue
import selectors
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from ..errors import HexacncError
from . import access as A
from . import protocol as P
from . import sockpath, tcpauth
from .admission import Admission
from .ops_operator import OPERATOR_OPS, attach_operator
from .upload import UploadOps, Uploads
from .serverio import _MAX_BATCH, _MAX_OUT_BYTES, _READ_CHUNK, ConnectionIO, _Conn, check_socket_path
from .servermotion import _MAX_MOTION_PENDING, MotionOps
from .serverstreams import (_MAX_SUBS_PER_CLIENT, _MAX_WAITS_PER_CLIENT, _STREAM_BACKLOG_BYTES, _WAIT_DONE_STATES,
                            _WAIT_SLICE_S, StatusStreams)

log = logging.getLogger("hexacnc.daemon.server")

#: a TCP client must authenticate within this time
_AUTH_TIMEOUT_S = tcpauth.AUTH_TIMEOUT_S


def _control_priority(daemon) -> None:
    """The control worker (stop, pause, override, ...) runs SCHED_FIFO just below the feeder thread when
    the daemon is real-time (permitted): a loaded machine must not delay a stop behind normal work."""
    cfg = getattr(daemon, "cfg", None)
    if getattr(daemon, "realtime", False) and cfg is not None:
        from .rt import sched_fifo
        sched_fifo(max(1, cfg.cycle.realtime_priority - 31))


class SocketServer(ConnectionIO, StatusStreams, MotionOps, UploadOps, Admission):
    """Serve the protocol of ``docs/protocol.md`` for ``daemon``.

    ``daemon`` offers ``hello() status() load_program(text, name) pause()
    resume() stop() reset() wait(timeout_s)``.  ``socket_path`` overrides
    ``[daemon] socket_path``; ``tcp_port``/``tcp_token`` override the config
    (``tcp_port=0``: no TCP).
    """

    def __init__(self, daemon: Any, cfg: Any, socket_path: str | None = None, *,
                 tcp_port: int | None = None, tcp_token: str | None = None,
                 max_clients: int | None = None, max_message_bytes: int | None = None,
                 status_rate_hz: float | None = None):
        dcfg = cfg.daemon
        self.daemon = daemon
        self.cfg = cfg
        self.socket_path = sockpath.server_socket_path(dcfg, socket_path)
        self.tcp_port = int(dcfg.tcp_port if tcp_port is None else tcp_port)
        self._init_admission(cfg, tcp_token)
        self.max_clients = int(max_clients if max_clients is not None
                               else getattr(dcfg, "max_clients", P.MAX_CLIENTS))
        self.max_message_bytes = int(max_message_bytes if max_message_bytes is not None
                                     else getattr(dcfg, "max_message_bytes", P.MAX_MESSAGE_BYTES))
        self.status_rate_hz = float(status_rate_hz if status_rate_hz is not None else dcfg.status_rate_hz)
        self.tcp_address: tuple[str, int] | None = None
        self.auth_timeout_s = _AUTH_TIMEOUT_S
        self.machine_name = str(getattr(cfg, "name", "") or "")
        self.operator = attach_operator(daemon, cfg)     # overrides, jog, MDI, offsets (ops_operator.py)

        self._sel: selectors.BaseSelector | None = None
        self._unix: socket.socket | None = None
        self._unix_ino: int | None = None
        self._tcp: socket.socket | None = None
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._results: queue.SimpleQueue = queue.SimpleQueue()
        self._pass_status: dict | None = None
        self._conns: dict[int, _Conn] = {}
        self._uploads = Uploads()              # chunked programs (program_begin/_chunk/_end), per connection
        self._controller: _Conn | None = None
        self._next_num = 1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._motion_pool: ThreadPoolExecutor | None = None
        # motion ops submitted (selector thread) / completed (worker): a "wait" first lets the
        # motion ops received before it complete, so "program" then "wait" back to back waits
        # for that program even though the program's reply has not been sent yet
        self._motion_cv = threading.Condition()
        self._motion_submitted = 0
        self._motion_done = 0
        self._wait_pool: ThreadPoolExecutor | None = None
        self.stats = {"accepted": 0, "refused": 0, "requests": 0, "errors": 0, "closed_bad": 0,
                      "stream_sent": 0, "stream_dropped": 0, "refused_peer": 0, "refused_op": 0,
                      "auth_failed": 0, "auth_throttled": 0, "preauth_closed": 0, "idle_closed": 0}

    # -- lifecycle ------------------------------------------------------------
    def start(self) -> "SocketServer":
        """Bind the sockets and serve in a background thread; raises HexacncError if it cannot bind."""
        if self._thread is not None:
            raise HexacncError("socket server already started")
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        try:
            self._bind_unix()
            if self.tcp_port:
                self._bind_tcp()
        except BaseException:
            self._close_listeners()
            raise
        self._motion_pool = ThreadPoolExecutor(1, thread_name_prefix="hexacnc-motion")
        # stop/pause/resume/reset never wait behind a program being interpreted and planned
        self._control_pool = ThreadPoolExecutor(1, thread_name_prefix="hexacnc-control",
                                                initializer=_control_priority, initargs=(self.daemon,))
        self._wait_pool = ThreadPoolExecutor(self.max_clients * _MAX_WAITS_PER_CLIENT,
                                             thread_name_prefix="hexacnc-wait")
        self._thread = threading.Thread(target=self._run, name="hexacnc-socket", daemon=True)
        self._thread.start()
        log.info("serving %s%s", self.socket_path,
                 f" and tcp {self.tcp_address[0]}:{self.tcp_address[1]}" if self.tcp_address else "")
        return self

    def close(self) -> None:
        """Stop serving, close every connection and remove the socket file (if still ours)."""
        self._stop.set()
        self._wake()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)
        self._thread = None
        for c in list(self._conns.values()):
            self._drop(c, "server closing")
        self._close_listeners()
        for pool in (self._motion_pool, self._wait_pool, getattr(self, "_control_pool", None)):
            if pool is not None:
                pool.shutdown(wait=False, cancel_futures=True)
        self._motion_pool = self._wait_pool = self._control_pool = None

    def __enter__(self) -> "SocketServer":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def clients(self) -> int:
        return len(self._conns)

    # -- loop -----------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._once()
            except Exception:  # a bug here must not end service for everyone
                log.exception("socket server loop error")
                time.sleep(0.01)

    def _once(self) -> None:
        self._pass_status = None
        timeout = self._next_stream_due() - time.monotonic()
        timeout = min(max(timeout, 0.0), 0.5)
        backlog = [c for c in self._conns.values() if c.backlog]
        if backlog:
            timeout = 0.0
        for conn in backlog:
            if conn.alive and not conn.closing:
                try:
                    self._process(conn)
                except Exception:
                    log.exception("%s: unexpected error; closing it", conn.label())
                    self._drop(conn, "internal error")
        for key, mask in self._sel.select(timeout):
            tag = key.data
            if tag == "wake":
                try:
                    while self._wake_r.recv(4096):
                        pass
                except (BlockingIOError, InterruptedError):
                    pass
            elif tag == "listen-unix" or tag == "listen-tcp":
                self._accept(key.fileobj, "unix" if tag == "listen-unix" else "tcp")
            else:
                conn: _Conn = tag
                try:
                    if mask & selectors.EVENT_READ and conn.alive:
                        self._on_readable(conn)
                    if mask & selectors.EVENT_WRITE and conn.alive:
                        self._flush(conn)
                except Exception:
                    log.exception("%s: unexpected error; closing it", conn.label())
                    self._drop(conn, "internal error")
        self._deliver_results()
        self._serve_streams()
        self._expire_connections()

    # -- requests -------------------------------------------------------------
    def _handle(self, conn: _Conn, msg: Any) -> None:
        self.stats["requests"] += 1
        try:
            req = P.validate_request(msg)
        except P.RequestError as exc:
            self.stats["errors"] += 1
            self._send(conn, exc.reply())
            if not conn.authenticated:
                conn.closing = True
                self._flush(conn)
            return
        if not conn.authenticated and not self._authenticate(conn, req):
            return
        if not A.allowed(conn.role, req.op):
            self.stats["refused_op"] += 1
            self.stats["errors"] += 1
            why = A.refusal(conn.role, req.op)
            self._log_refusal(conn.who, req.op, why)
            self._send(conn, P.error_reply(req.id, P.UNAUTHORIZED, why, access=conn.role))
            return
        handler = getattr(self, "_op_" + req.op, None)
        try:
            if handler is None:
                OPERATOR_OPS[req.op](self, conn, req)
            else:
                handler(conn, req)
        except Exception as exc:
            log.exception("%s: op %s failed", conn.label(), req.op)
            self._send(conn, P.error_from_exception(exc, req.id, self._state_or_none()))


def make_server(daemon: Any, cfg: Any, socket_path: str | None = None) -> SocketServer:
    """Factory: an unstarted :class:`SocketServer` for ``daemon``."""
    return SocketServer(daemon, cfg, socket_path)


# calibration-cycle ops (measure, measurement, reload): hexacnc.daemon.calibops
from . import calibops as _calibops  # noqa: E402

_calibops.register(SocketServer)

__all__ = ["SocketServer", "check_socket_path", "make_server"]
# importable here as before the split (connection state and limits live in serverio/serverstreams/servermotion)
_REEXPORTED = (_Conn, _READ_CHUNK, _MAX_OUT_BYTES, _MAX_BATCH, _STREAM_BACKLOG_BYTES, _WAIT_SLICE_S,
               _MAX_WAITS_PER_CLIENT, _MAX_SUBS_PER_CLIENT, _WAIT_DONE_STATES, _MAX_MOTION_PENDING)
