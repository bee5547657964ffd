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
import os
import platform
import queue
import selectors
import socket
import stat
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import msgpack

from .. import __version__
from ..errors import HexacncError, ProtocolError
from . import access as A
from . import protocol as P
from . import sockpath, tcpauth, tlsio
from .admission import Admission
from .ops_operator import OPERATOR_OPS, attach_operator

log = logging.getLogger("hexacnc.daemon.server")

#: bytes read per readiness event
_READ_CHUNK = 256 * 1024
#: a client whose unsent replies exceed this is dropped (it does not read)
_MAX_OUT_BYTES = 64 * 1024 * 1024
#: subscription samples are skipped while a client has this much unsent
_STREAM_BACKLOG_BYTES = 256 * 1024
#: slice of Daemon.wait between checks for a closed client / server
_WAIT_SLICE_S = 0.2
#: outstanding "wait" requests per client
_MAX_WAITS_PER_CLIENT = 4
#: requests handled per client per loop pass (the rest waits for the next pass: fairness)
_MAX_BATCH = 64
#: motion ops queued but not done, per client
_MAX_MOTION_PENDING = 64
#: subscriptions per client
_MAX_SUBS_PER_CLIENT = 8
#: a TCP client must authenticate within this time
_AUTH_TIMEOUT_S = tcpauth.AUTH_TIMEOUT_S
#: state values after which "wait" returns
_WAIT_DONE_STATES = ("idle", "fault")


class _Conn:
    """One client connection (touched only by the selector thread, except ``alive``)."""

    __slots__ = ("sock", "num", "kind", "peer", "dec", "out", "authenticated", "closing", "alive",
                 "subs", "waits", "motion_pending", "client_name", "registered_mask", "created", "backlog",
                 "role", "who", "last_active", "preauth_bytes", "addr")

    def __init__(self, sock: socket.socket, num: int, kind: str, peer: str, max_bytes: int):
        self.sock = sock
        self.num = num
        self.kind = kind                      # "unix" | "tcp"
        self.peer = peer
        self.dec = P.Decoder(max_bytes)
        self.out = bytearray()
        self.authenticated = kind == "unix"   # Unix socket: file permissions authenticate
        self.closing = False                  # close once ``out`` is flushed
        self.alive = True
        self.subs: dict[int, list] = {}       # sub id -> [period_s, next_due, seq, dropped]
        self.waits = 0
        self.motion_pending = 0
        self.client_name = ""
        self.created = time.monotonic()
        self.backlog = False                  # decoded data left for the next pass
        self.registered_mask = 0
        self.role: str | None = None          # access role (hexacnc.daemon.access); None before auth
        self.who = peer                       # peer uid/pid or address, for refusal logs
        self.last_active = self.created
        self.preauth_bytes = 0
        self.addr = peer.rsplit(":", 1)[0] if kind == "tcp" else ""

    def label(self) -> str:
        return f"client {self.num} ({self.kind} {self.peer}{', ' + self.client_name if self.client_name else ''})"


class SocketServer(Admission):
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
        # stop/pause/resume/reset/disable never wait behind a program being planned (or a home)
        self._control_pool = ThreadPoolExecutor(1, thread_name_prefix="hexacnc-control")
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

    # -- binding ----------------------------------------------------------------
    def _bind_unix(self) -> None:
        path = self.socket_path
        sockpath.prepare_server_dir(path)        # refuses a directory others can write (or own)
        check_socket_path(path, remove_stale=True)
        # peer credentials decide who may do what; with groups configured anyone may connect (and
        # gets a role or a logged refusal), else only the owner's group can open the socket
        mode = 0o666 if self.policy.groups_configured else 0o660
        # bind under a temporary name, set 0660, then rename: no moment with wider permissions
        tmp = f"{path}.{os.getpid()}.{threading.get_ident() % 100000}.tmp"
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            if len(os.fsencode(tmp)) <= 107:
                s.bind(tmp)
                os.chmod(tmp, mode)
                os.replace(tmp, path)
            else:
                s.bind(path)
                os.chmod(path, mode)
            s.listen(64)
            s.setblocking(False)
        except OSError as exc:
            s.close()
            for p in (tmp,):
                try:
                    os.unlink(p)
                except OSError:
                    pass
            raise HexacncError(f"cannot listen on {path!r}: {exc.strerror or exc}") from exc
        self._unix = s
        self._unix_ino = os.lstat(path).st_ino
        self._sel.register(s, selectors.EVENT_READ, "listen-unix")

    def _bind_tcp(self) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((self.tcp_host, self.tcp_port))  # 127.0.0.1 unless TLS is on ([daemon] tcp_host)
            s.listen(64)
            s.setblocking(False)
        except OSError as exc:
            s.close()
            raise HexacncError(f"cannot listen on {self.tcp_host}:{self.tcp_port}: {exc.strerror or exc}") from exc
        self._tcp = s
        self.tcp_address = s.getsockname()[:2]
        self._sel.register(s, selectors.EVENT_READ, "listen-tcp")

    def _close_listeners(self) -> None:
        for s in (self._unix, self._tcp, self._wake_r, self._wake_w):
            if s is not None:
                try:
                    if self._sel is not None:
                        self._sel.unregister(s)
                except (KeyError, ValueError):
                    pass
                s.close()
        if self._unix is not None and self._unix_ino is not None:
            try:
                if os.lstat(self.socket_path).st_ino == self._unix_ino:
                    os.unlink(self.socket_path)
            except OSError:
                pass
        self._unix = self._tcp = self._wake_r = self._wake_w = None
        if self._sel is not None:
            self._sel.close()
            self._sel = None

    # -- loop -----------------------------------------------------------------
    def _wake(self) -> None:
        w = self._wake_w
        if w is not None:
            try:
                w.send(b"\0")
            except OSError:
                pass

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

    def _register(self, s: socket.socket, kind: str, peer: str) -> _Conn:
        conn = _Conn(s, self._next_num, kind, peer, self.max_message_bytes)
        self._next_num += 1
        self._conns[conn.num] = conn
        conn.registered_mask = selectors.EVENT_READ
        self._sel.register(s, selectors.EVENT_READ, conn)
        self.stats["accepted"] += 1
        log.debug("%s connected", conn.label())
        return conn

    def _accept(self, lsock: socket.socket, kind: str) -> None:
        # few TCP accepts per pass: a flood of new connections cannot push a fresh one out of the
        # pre-auth pool before the loop has read its hello
        for _ in range(16 if kind == "unix" else 4):
            try:
                s, addr = lsock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                log.warning("accept failed: %s", exc)
                return
            s.setblocking(False)
            if kind == "tcp":
                self._admit_tcp(s, f"{addr[0]}:{addr[1]}")
            else:
                self._admit_unix(s)

    def _on_readable(self, conn: _Conn) -> None:
        want = _READ_CHUNK if conn.authenticated else tcpauth.PREAUTH_MAX_BYTES - conn.preauth_bytes
        if want <= 0:
            return
        try:
            data = tlsio.recv(conn.sock, want)      # plain or TLS; None: nothing there now
        except OSError as exc:
            if not conn.authenticated:            # e.g. a failed TLS handshake: a refusal, logged
                self._log_refusal(conn.who, "connect", f"receive failed: {exc}")
            self._drop(conn, f"receive failed: {exc}")
            return
        if data is None:
            return
        if not data:
            self._drop(conn, "disconnected")
            return
        if conn.closing:
            return                         # ignore anything after a fatal error
        conn.last_active = time.monotonic()
        if not conn.authenticated:
            conn.preauth_bytes += len(data)
        try:
            conn.dec.feed(data)
        except ProtocolError as exc:
            self._bad_stream(conn, exc)
            return
        self._process(conn)
        if (conn.alive and not conn.closing and not conn.authenticated
                and conn.preauth_bytes >= tcpauth.PREAUTH_MAX_BYTES):
            self.stats["preauth_closed"] += 1
            self._refuse_conn(conn, "hello", f"more than {tcpauth.PREAUTH_MAX_BYTES} bytes before "
                                             f"authentication", code=P.TOO_LARGE)

    def _process(self, conn: _Conn) -> None:
        """Handle up to _MAX_BATCH decoded requests; flag the connection if more are buffered."""
        conn.backlog = False
        n = 0
        try:
            for msg in conn.dec.messages():
                self._handle(conn, msg)
                n += 1
                if conn.closing or not conn.alive:
                    return
                if n >= _MAX_BATCH:
                    conn.backlog = True
                    return
        except ProtocolError as exc:
            self._bad_stream(conn, exc)

    def _bad_stream(self, conn: _Conn, exc: ProtocolError) -> None:
        self.stats["closed_bad"] += 1
        log.warning("%s: %s; closing the connection", conn.label(), exc)
        if conn.dec.too_large:
            self._send(conn, P.error_reply(None, P.TOO_LARGE, str(exc)))
            conn.closing = True
            self._flush(conn)
        else:
            self._drop(conn, "undecodable message")

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

    def _state_or_none(self) -> str | None:
        try:
            return str(self.daemon.status().get("state"))
        except Exception:
            return None

    def _status(self) -> dict:
        """The daemon's status as plain types; read at most once per loop pass (a copy each time)."""
        st = self._pass_status
        if st is None:
            st = self.daemon.status()
            if self.operator is not None:
                st = self.operator.status(st)
            ctl = self._controller
            st["controller"] = None if ctl is None else ctl.label()
            st = self._pass_status = P.plain(st)
        return dict(st)

    def _op_hello(self, conn: _Conn, req: P.Request) -> None:
        conn.client_name = str(req.fields.get("client", ""))[:64]
        try:
            info = P.plain(self.daemon.hello() or {})
        except Exception as exc:
            log.warning("Daemon.hello failed: %s", exc)
            info = {}
        versions = dict(info.get("versions") or {}) if isinstance(info.get("versions"), dict) else {}
        versions.update({"hexacnc": __version__, "protocol": P.PROTOCOL_VERSION,
                         "python": platform.python_version(), "msgpack": ".".join(map(str, msgpack.version))})
        info.update({
            "protocol": P.PROTOCOL_VERSION,
            "version": __version__,
            "versions": versions,
            "machine": info.get("machine") or self.machine_name,
            "role": "controller" if self._controller is conn else "observer",
            "access": conn.role,
            "controller_present": self._controller is not None,
            "status_rate_hz": self.status_rate_hz,
            "max_message_bytes": self.max_message_bytes,
            "ops": sorted(P.OPS),
        })
        self._send(conn, P.ok_reply(req.id, **info))

    def _op_status(self, conn: _Conn, req: P.Request) -> None:
        st = self._status()
        st["role"] = "controller" if self._controller is conn else "observer"
        st["access"] = conn.role
        self._send(conn, P.ok_reply(req.id, **st))

    def _take_control(self, conn: _Conn, req: P.Request) -> bool:
        if self._controller is None:
            self._controller = conn
            log.info("%s now controls motion", conn.label())
            return True
        if self._controller is conn:
            return True
        self.stats["errors"] += 1
        self._send(conn, P.error_reply(req.id, P.NOT_CONTROLLER,
                                       f"op {req.op!r}: {self._controller.label()} controls the machine; "
                                       f"this connection may only observe until it disconnects or "
                                       f"takes control ('take'; hexacnc ... --take)"))
        return False

    def _submit_motion(self, conn: _Conn, req: P.Request, call: Callable[[], Any],
                       reply: Callable[[Any], dict]) -> None:
        if conn.motion_pending >= _MAX_MOTION_PENDING:
            self._send(conn, P.error_reply(req.id, P.BUSY, f"more than {_MAX_MOTION_PENDING} motion ops "
                                                           f"of this client are still being executed"))
            return
        conn.motion_pending += 1

        def job() -> None:
            out: dict
            try:
                result = call()
                out = reply(result)
            except Exception as exc:
                if not isinstance(exc, HexacncError):
                    log.exception("Daemon call for op %s failed", req.op)
                out = P.error_from_exception(exc, req.id, self._state_or_none(), req.op)
            finally:
                with self._motion_cv:
                    self._motion_done += 1
                    self._motion_cv.notify_all()
            self._results.put((conn, out, "motion-done"))
            self._wake()
        with self._motion_cv:
            self._motion_submitted += 1
        # disable too: machine off never waits behind a motion op (e.g. a running CiA 402 home)
        control = req.op in ("stop", "pause", "resume", "reset", "disable") and getattr(self, "_control_pool", None)
        (self._control_pool if control else self._motion_pool).submit(job)

    def _op_program(self, conn: _Conn, req: P.Request) -> None:
        if not self._take_control(conn, req):
            return
        text, name = req.fields["text"], req.fields["name"]

        def reply(result: Any) -> dict:
            info = P.plain(result) if isinstance(result, dict) else {"blocks": result}
            info.setdefault("name", name)
            return P.ok_reply(req.id, **info)
        load = self.operator.load_program if self.operator is not None else self.daemon.load_program
        self._submit_motion(conn, req, lambda: load(text, name), reply)

    def _simple_motion(self, conn: _Conn, req: P.Request) -> None:
        if not self._take_control(conn, req):
            return
        fn = getattr(self.daemon, req.op)

        def reply(result: Any) -> dict:
            extra = P.plain(result) if isinstance(result, dict) else {}
            return P.ok_reply(req.id, **extra)
        self._submit_motion(conn, req, fn, reply)

    _op_pause = _op_resume = _op_stop = _op_reset = _simple_motion

    def _op_temperatures(self, conn: _Conn, req: P.Request) -> None:
        """A probe reading for the thermal observer (controller or sensor role; validated as a whole, applied or not at all)."""
        push = getattr(self.daemon, "push_temperatures", None)
        if push is None:
            self._send(conn, P.error_reply(req.id, P.REFUSED, "this daemon takes no temperatures"))
            return
        try:
            info = push(dict(req.fields))
        except HexacncError as exc:
            code = getattr(exc, "code", None)
            field = getattr(exc, "field", None)
            self.stats["errors"] += 1
            self._send(conn, P.error_reply(req.id, code if code in P.ERROR_CODES else P.REFUSED, str(exc),
                                           **({"field": field} if field else {})))
            return
        self._send(conn, P.ok_reply(req.id, **P.plain(info or {})))

    def _op_release(self, conn: _Conn, req: P.Request) -> None:
        was = self._controller is conn
        if was:
            self._controller = None
            log.info("%s released control", conn.label())
        self._send(conn, P.ok_reply(req.id, released=was))

    def _op_wait(self, conn: _Conn, req: P.Request) -> None:
        if conn.waits >= _MAX_WAITS_PER_CLIENT:
            self._send(conn, P.error_reply(req.id, P.BUSY,
                                           f"at most {_MAX_WAITS_PER_CLIENT} outstanding 'wait' per client"))
            return
        conn.waits += 1
        timeout_s = req.fields["timeout_s"]
        daemon = self.daemon
        stop = self._stop

        with self._motion_cv:
            after = self._motion_submitted

        def job() -> None:
            deadline = time.monotonic() + timeout_s
            out: dict | None = None
            try:
                with self._motion_cv:           # motion ops received before this wait come first
                    while self._motion_done < after and not stop.is_set() and conn.alive:
                        self._motion_cv.wait(min(_WAIT_SLICE_S, max(0.0, deadline - time.monotonic())) or 0.01)
                        if time.monotonic() >= deadline:
                            break
                while True:
                    left = deadline - time.monotonic()
                    st = daemon.wait(max(0.0, min(_WAIT_SLICE_S, left)))
                    state = st.get("state") if isinstance(st, dict) else None
                    if state in _WAIT_DONE_STATES:
                        out = P.ok_reply(req.id, timed_out=False, **P.plain(st))
                        break
                    if time.monotonic() >= deadline:
                        out = P.ok_reply(req.id, timed_out=True, **P.plain(st))
                        break
                    if not conn.alive or stop.is_set():
                        return
            except Exception as exc:
                if not isinstance(exc, HexacncError):
                    log.exception("Daemon.wait failed")
                out = P.error_from_exception(exc, req.id)
            finally:
                self._results.put((conn, out, "wait-done"))
                self._wake()
        self._wait_pool.submit(job)

    def _op_subscribe(self, conn: _Conn, req: P.Request) -> None:
        if len(conn.subs) >= _MAX_SUBS_PER_CLIENT:
            self._send(conn, P.error_reply(req.id, P.BUSY,
                                           f"at most {_MAX_SUBS_PER_CLIENT} subscriptions per client"))
            return
        rate = float(req.fields.get("rate_hz", self.status_rate_hz))
        period = 1.0 / rate
        st = self._status()
        conn.subs[req.id] = [period, time.monotonic() + period, 0, 0]
        self._send(conn, P.ok_reply(req.id, sub=req.id, rate_hz=rate, **st))

    def _op_unsubscribe(self, conn: _Conn, req: P.Request) -> None:
        sub = req.fields.get("sub")
        if sub is None:
            cancelled = sorted(conn.subs)
            conn.subs.clear()
        else:
            cancelled = [sub] if conn.subs.pop(sub, None) is not None else []
        self._send(conn, P.ok_reply(req.id, cancelled=cancelled))

    # -- output ---------------------------------------------------------------
    def _deliver_results(self) -> None:
        while True:
            try:
                item = self._results.get_nowait()
            except queue.Empty:
                return
            conn, out = item[0], item[1]
            if item[2] == "wait-done":
                conn.waits -= 1
            elif item[2] == "motion-done":
                conn.motion_pending -= 1
            conn.last_active = time.monotonic()       # idle time counts from the end of a wait/op
            if out is not None and conn.alive and not conn.closing:
                self._send(conn, out)

    def _next_stream_due(self) -> float:
        due = time.monotonic() + 0.5
        for c in self._conns.values():
            for s in c.subs.values():
                if s[1] < due:
                    due = s[1]
        return due

    def _serve_streams(self) -> None:
        now = time.monotonic()
        st: dict | None = None
        err: dict | None = None
        for conn in list(self._conns.values()):
            if not conn.alive or conn.closing or not conn.subs:
                continue
            for sid, s in conn.subs.items():
                if s[1] > now:
                    continue
                s[1] += s[0]
                if s[1] <= now:
                    s[1] = now + s[0]
                if len(conn.out) > _STREAM_BACKLOG_BYTES:
                    s[3] += 1
                    self.stats["stream_dropped"] += 1
                    continue
                if st is None and err is None:
                    try:
                        st = self._status()
                    except Exception as exc:
                        err = P.error_from_exception(exc, None)["error"]
                s[2] += 1
                if st is not None:
                    msg = {"id": sid, "ok": True, "stream": "status", "seq": s[2], "dropped": s[3]}
                    msg.update(st)
                else:
                    msg = {"id": sid, "ok": False, "stream": "status", "seq": s[2], "error": err}
                self.stats["stream_sent"] += 1
                self._send(conn, msg)
                if not conn.alive:
                    break

    def _send(self, conn: _Conn, msg: dict) -> None:
        if not conn.alive:
            return
        conn.out += P.encode(msg)
        if len(conn.out) > _MAX_OUT_BYTES:
            self._drop(conn, f"does not read its replies ({len(conn.out)} bytes unsent)")
            return
        self._flush(conn)

    def _flush(self, conn: _Conn) -> None:
        while conn.out:
            try:
                n = tlsio.send(conn.sock, conn.out)   # plain or TLS; 0: cannot take more now
            except OSError as exc:
                self._drop(conn, f"send failed: {exc}")
                return
            if not n:
                break
            del conn.out[:n]
        if not conn.out and conn.closing:
            self._drop(conn, "closed after a fatal error")
            return
        want = selectors.EVENT_READ | (selectors.EVENT_WRITE if conn.out else 0)
        if want != conn.registered_mask and conn.alive:
            self._sel.modify(conn.sock, want, conn)
            conn.registered_mask = want

    def _drop(self, conn: _Conn, why: str) -> None:
        if not conn.alive:
            return
        conn.alive = False
        conn.subs.clear()
        self._conns.pop(conn.num, None)
        self._preauth.pop(conn.num, None)
        try:
            if self._sel is not None:
                self._sel.unregister(conn.sock)
        except (KeyError, ValueError):
            pass
        try:
            conn.sock.close()
        except OSError:
            pass
        if self._controller is conn:
            self._controller = None
            log.info("%s gave up control (%s)", conn.label(), why)
        log.debug("%s: %s", conn.label(), why)


def check_socket_path(path: str, remove_stale: bool = False) -> None:
    """Raise HexacncError if ``path`` cannot be served: too long, no directory, not a socket, or
    another daemon answers on it.  A stale socket file (nobody listening) is removed when
    ``remove_stale``.  ``hexacnc run`` may call this before booting the drives."""
    if len(os.fsencode(path)) > 100:
        raise HexacncError(f"socket path {path!r} is too long for a Unix socket (max 100 bytes)")
    d = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(d):
        raise HexacncError(f"socket path {path!r}: directory {d} does not exist")
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(st.st_mode):
        raise HexacncError(f"socket path {path!r} exists and is not a socket; refusing to replace it")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    probe.settimeout(1.0)
    try:
        probe.connect(path)
    except (ConnectionRefusedError, FileNotFoundError):
        if remove_stale:
            log.info("removing stale socket %s", path)
            try:
                os.unlink(path)
            except FileNotFoundError:
                pass
        return
    except OSError as exc:
        raise HexacncError(f"socket path {path!r} exists and cannot be checked: {exc.strerror or exc}") from exc
    finally:
        probe.close()
    raise HexacncError(f"another daemon is serving {path!r}; stop it or choose another "
                       f"--socket / [daemon] socket_path")


def make_server(daemon: Any, cfg: Any, socket_path: str | None = None) -> SocketServer:
    """Factory: an unstarted :class:`SocketServer` for ``daemon``."""
    return SocketServer(daemon, cfg, socket_path)


# calibration-cycle ops (measure, measurement, reload): hexacnc.daemon.calibops
from . import calibops as _calibops  # noqa: E402

_calibops.register(SocketServer)

__all__ = ["SocketServer", "check_socket_path", "make_server"]
