"""Socket protocol of the daemon: msgpack framing, request validation, a small client.

Messages are msgpack maps written back to back on a byte stream (no length
prefix: msgpack is self-delimiting).  A request is ``{"id": int, "op": str, ...}``;
every reply carries the request's ``id`` and ``ok``::

    {"id": 7, "ok": true, ...}
    {"id": 7, "ok": false, "error": {"code": str, "message": str, "line": int | None}}

This module has no I/O policy of its own: :class:`Decoder` turns received bytes
into objects, :func:`validate_request` checks one object against the op table
(``OPS``) and returns a :class:`Request` or raises :class:`RequestError` with a
stable error code, :func:`encode` packs a reply.  :class:`Client` is the
blocking client used by ``hexacnc send`` / ``hexacnc status`` and the tests.
The full contract is in ``docs/protocol.md``.
"""
from __future__ import annotations

import math
import socket
import time
from dataclasses import dataclass, field
from typing import Any, Iterator

import msgpack

from ..errors import GcodeError, HexacncError, KinematicsError, PlanError, ProtocolError

#: protocol version announced by "hello"; raised only on incompatible changes
PROTOCOL_VERSION = 1
#: largest message accepted by default (bytes); a larger one closes the connection
MAX_MESSAGE_BYTES = 16 * 1024 * 1024
#: most simultaneous clients by default
MAX_CLIENTS = 32

# -- error codes (stable strings, documented in docs/protocol.md) -------------
BAD_REQUEST = "bad_request"        #: the message is not a map, or is not a request at all
UNAUTHORIZED = "unauthorized"      #: TCP: first message was not "hello" with the right token
UNKNOWN_OP = "unknown_op"          #: "op" names no operation
MISSING_FIELD = "missing_field"    #: a required field (id, op, text, ...) is absent
BAD_TYPE = "bad_type"              #: a field has the wrong type
BAD_VALUE = "bad_value"            #: a field has the right type but an impossible value
NOT_CONTROLLER = "not_controller"  #: another client controls motion
GCODE = "gcode"                    #: the program cannot be parsed
UNSUPPORTED = "unsupported"        #: the program uses something the interpreter does not support
LIMIT = "limit"                    #: the program (or a pose) violates a machine limit
BUSY = "busy"                      #: the daemon cannot take this now (program running, too many clients)
FAULT = "fault"                    #: the daemon is in fault; "reset" first
INVALID_STATE = "invalid_state"    #: the op makes no sense in the current state (e.g. resume when idle)
REFUSED = "refused"                #: the daemon refused for another reason named in the message
TOO_LARGE = "too_large"            #: a message over the size limit (sent just before closing)
INTERNAL = "internal"              #: a bug in the daemon; the message says what happened

ERROR_CODES: tuple[str, ...] = (
    BAD_REQUEST, UNAUTHORIZED, UNKNOWN_OP, MISSING_FIELD, BAD_TYPE, BAD_VALUE, NOT_CONTROLLER,
    GCODE, UNSUPPORTED, LIMIT, BUSY, FAULT, INVALID_STATE, REFUSED, TOO_LARGE, INTERNAL,
)

#: codes that refuse a program because of its content (the error names the line)
PROGRAM_CODES = (GCODE, UNSUPPORTED, LIMIT)

#: ops that move the machine or change its motion state: controller only
MOTION_OPS = frozenset({"program", "program_begin", "program_chunk", "program_end", "pause", "resume", "stop",
                        "reset", "override", "enable", "disable", "home", "jog", "mdi", "take"})

_NUM = (int, float)
#: op -> {field: (accepted python types, required)}.  "id" and "op" are checked for all.
OPS: dict[str, dict[str, tuple[tuple[type, ...], bool]]] = {
    "hello": {"token": ((str,), False), "client": ((str,), False)},
    "status": {},
    "program": {"text": ((str,), True), "name": ((str,), True)},
    "program_begin": {"name": ((str,), True), "bytes": ((int,), True)},
    "program_chunk": {"seq": ((int,), True), "text": ((str,), True)},
    "program_end": {},
    "pause": {},
    "resume": {},
    "stop": {},
    "reset": {},
    "wait": {"timeout_s": (_NUM, True)},
    "subscribe": {"rate_hz": (_NUM, False)},
    "unsubscribe": {"sub": ((int,), False)},
    "release": {},
    "temperatures": {"probes_C": ((list, tuple, dict), True), "spindle_C": (_NUM, False), "time_s": (_NUM, False)},
    # operator control (hexacnc/daemon/ops_operator.py)
    "override": {"feed": (_NUM, False), "rapid": (_NUM, False), "optional_stop": ((bool,), False),
                 "block_delete": ((bool,), False)},
    "enable": {},
    "disable": {},
    "take": {},
    "home": {},
    "mdi": {"text": ((str,), True)},
    "jog": {"action": ((str,), False), "axis": ((str, int), False), "frame": ((str,), False),
            "distance": (_NUM, False), "direction": ((int,), False), "speed": (_NUM, False)},
    "pivot": {"pivot_mm": ((list, tuple), False)},
    "offsets": {"system": ((str,), False), "values": ((dict,), False), "select": ((str,), False)},
    "tools": {"tool": ((int,), False), "z_mm": (_NUM, False), "diameter_mm": (_NUM, False),
              "pocket": ((int,), False), "comment": ((str,), False), "delete": ((bool,), False)},
}

#: states reported in status["state"]
STATES = ("idle", "running", "paused", "stopping", "fault")
#: wait timeout cap (s); a longer wait is simply repeated by the client
MAX_WAIT_S = 24 * 3600.0
#: subscription rate bounds (Hz)
MIN_RATE_HZ, MAX_RATE_HZ = 0.1, 1000.0


class RequestError(ProtocolError):
    """A request that gets an error reply.  ``id`` is the request id when it was readable."""

    def __init__(self, code: str, message: str, req_id: int | None = None, line: int | None = None,
                 **extra: Any):
        super().__init__(message)
        self.code = code
        self.message = message
        self.id = req_id
        self.line = line
        self.extra = extra

    def reply(self) -> dict:
        return error_reply(self.id, self.code, self.message, self.line, **self.extra)


@dataclass
class Request:
    id: int
    op: str
    fields: dict = field(default_factory=dict)


def _type_name(v: Any) -> str:
    if v is None:
        return "nil"
    if isinstance(v, bool):
        return "bool"
    if isinstance(v, int):
        return "int"
    if isinstance(v, float):
        return "float"
    if isinstance(v, str):
        return "str"
    if isinstance(v, (bytes, bytearray)):
        return "bin"
    if isinstance(v, (list, tuple)):
        return "array"
    if isinstance(v, dict):
        return "map"
    return type(v).__name__


def _is_type(v: Any, types: tuple[type, ...]) -> bool:
    """v is one of the types; a bool only where bool is asked for (never as an int)."""
    if isinstance(v, bool):
        return bool in types
    return isinstance(v, types)


_TYPE_WORDS = {str: "str", int: "int", float: "float", bool: "bool"}


def validate_request(msg: Any) -> Request:
    """Check one decoded message; return the :class:`Request` or raise :class:`RequestError`.

    Unknown extra fields are ignored (forward compatibility).  Numbers given as
    int where a float is expected are accepted.
    """
    if not isinstance(msg, dict):
        raise RequestError(BAD_REQUEST, f"a request must be a msgpack map, got {_type_name(msg)}")
    rid = msg.get("id")
    if "id" not in msg:
        raise RequestError(MISSING_FIELD, "request has no 'id' (an integer chosen by the client)")
    if not _is_type(rid, (int,)):
        raise RequestError(BAD_TYPE, f"'id' must be an integer, got {_type_name(rid)}")
    if not -(2 ** 63) <= rid < 2 ** 64:
        raise RequestError(BAD_VALUE, "'id' does not fit in 64 bits")
    if "op" not in msg:
        raise RequestError(MISSING_FIELD, "request has no 'op'", rid)
    op = msg["op"]
    if not isinstance(op, str):
        raise RequestError(BAD_TYPE, f"'op' must be a string, got {_type_name(op)}", rid)
    spec = OPS.get(op)
    if spec is None:
        shown = op if len(op) <= 40 else op[:40] + "..."
        raise RequestError(UNKNOWN_OP, f"unknown op {shown!r}; known: {', '.join(sorted(OPS))}", rid)
    fields: dict[str, Any] = {}
    for name, (types, required) in spec.items():
        if name not in msg or (msg[name] is None and not required):
            if required:
                raise RequestError(MISSING_FIELD, f"op {op!r} needs field {name!r}", rid, field=name)
            continue
        v = msg[name]
        if not _is_type(v, types):
            want = " or ".join(_TYPE_WORDS.get(t, t.__name__) for t in types)
            raise RequestError(BAD_TYPE, f"op {op!r}: field {name!r} must be {want}, got {_type_name(v)}", rid,
                               field=name)
        fields[name] = v
    # value checks
    if op == "wait":
        t = float(fields["timeout_s"])
        if not math.isfinite(t) or t < 0:
            raise RequestError(BAD_VALUE, f"op 'wait': timeout_s must be a finite number >= 0, got {t!r}", rid)
        fields["timeout_s"] = min(t, MAX_WAIT_S)
    elif op == "subscribe" and "rate_hz" in fields:
        r = float(fields["rate_hz"])
        if not math.isfinite(r) or not MIN_RATE_HZ <= r <= MAX_RATE_HZ:
            raise RequestError(BAD_VALUE, f"op 'subscribe': rate_hz must be in [{MIN_RATE_HZ}, {MAX_RATE_HZ}], "
                                          f"got {r!r}", rid)
        fields["rate_hz"] = r
    elif op in OPERATOR_CHECKS:
        OPERATOR_CHECKS[op](fields, rid)
    elif op == "program":
        if "\x00" in fields["text"]:
            raise RequestError(BAD_VALUE, "op 'program': text contains a NUL character", rid)
    return Request(rid, op, fields)


def _check_override(fields: dict, rid) -> None:
    for name, hi in (("feed", 2.0), ("rapid", 1.0)):
        if name in fields:
            v = float(fields[name])
            if not math.isfinite(v) or not 0.0 <= v <= hi:
                raise RequestError(BAD_VALUE, f"op 'override': {name} must be in [0, {hi:g}], got {v!r}", rid,
                                   field=name)


def _check_jog(fields: dict, rid) -> None:
    a = fields.get("action", "start")
    if a not in ("start", "confirm", "stop"):
        raise RequestError(BAD_VALUE, f"op 'jog': action must be start, confirm or stop, got {a!r}", rid)
    if "axis" in fields:
        ax = str(fields["axis"]).lower()
        if ax not in ("x", "y", "z", "a", "b", "c", "1", "2", "3", "4", "5", "6"):
            raise RequestError(BAD_VALUE, f"op 'jog': axis must be x y z a b c or a strut 1..6, got {ax!r}", rid,
                               field="axis")
        fields["axis"] = ax
    if fields.get("frame", "base") not in ("base", "tool", "work"):
        raise RequestError(BAD_VALUE, f"op 'jog': frame must be base, tool or work, got {fields['frame']!r}", rid)
    if "direction" in fields and fields["direction"] not in (1, -1):
        raise RequestError(BAD_VALUE, f"op 'jog': direction must be 1 or -1, got {fields['direction']!r}", rid)
    for name in ("distance", "speed"):
        if name in fields and not math.isfinite(float(fields[name])):
            raise RequestError(BAD_VALUE, f"op 'jog': {name} must be finite", rid, field=name)
    if "speed" in fields and not 0.0 < float(fields["speed"]) <= 1.0:
        raise RequestError(BAD_VALUE, "op 'jog': speed is a fraction of the [jog] speed in (0, 1]", rid)


def _check_mdi(fields: dict, rid) -> None:
    t = fields["text"]
    if "\x00" in t or len(t) > 4096:
        raise RequestError(BAD_VALUE, "op 'mdi': text must be at most 4096 characters without NUL", rid)


def _check_values(fields: dict, rid) -> None:
    for k, v in (fields.get("values") or {}).items():
        if not _is_type(v, _NUM) or not math.isfinite(float(v)):
            raise RequestError(BAD_VALUE, f"op 'offsets': values[{k!r}] must be a finite number", rid)
    if "pivot_mm" in fields:
        pv = fields["pivot_mm"]
        if len(pv) not in (0, 3) or not all(_is_type(v, _NUM) and math.isfinite(float(v)) for v in pv):
            raise RequestError(BAD_VALUE, "op 'pivot': pivot_mm must be 3 finite numbers ([]: the tool tip)", rid)


#: value checks of the operator ops
OPERATOR_CHECKS = {"override": _check_override, "jog": _check_jog, "mdi": _check_mdi,
                   "offsets": _check_values, "pivot": _check_values}


# -- replies ----------------------------------------------------------------
def ok_reply(req_id: int | None, **fields: Any) -> dict:
    out = dict(fields)
    out.pop("error", None)
    out["id"] = req_id            # framing keys always win over payload keys of the same name
    out["ok"] = True
    return out


def error_reply(req_id: int | None, code: str, message: str, line: int | None = None, **extra: Any) -> dict:
    err = {"code": code, "message": message, "line": line}
    err.update(extra)
    return {"id": req_id, "ok": False, "error": err}


def _int_or_none(v: Any) -> int | None:
    try:
        return None if v is None or isinstance(v, bool) else int(v)
    except (TypeError, ValueError):
        return None


def error_from_exception(exc: BaseException, req_id: int | None, state: str | None = None,
                         op: str | None = None) -> dict:
    """Map a daemon exception to an error reply with a stable code.

    ``GcodeError`` -> gcode/unsupported with line and column; ``PlanError`` ->
    limit (or gcode/unsupported when the planner says so) with line and the
    limit's name; other ``HexacncError`` -> the exception's ``code`` attribute
    when it is one of :data:`ERROR_CODES`, else fault / busy by daemon ``state``,
    invalid_state for pause/resume/reset, else refused; anything else -> internal.
    """
    if isinstance(exc, GcodeError):
        raw = getattr(exc, "code", None)
        code = raw if raw in (GCODE, UNSUPPORTED) else GCODE
        return error_reply(req_id, code, str(exc), _int_or_none(exc.line),
                           column=_int_or_none(exc.column), reason=str(raw or code))
    if isinstance(exc, PlanError):
        raw = getattr(exc, "code", None)
        # a planner code other than the stable ones (e.g. "empty") is about the program's
        # content, not a machine limit
        code = raw if raw in PROGRAM_CODES else (LIMIT if raw in (None, "limit") else GCODE)
        limit = exc.limit if isinstance(exc.limit, str) else (None if exc.limit is None else str(exc.limit))
        return error_reply(req_id, code, str(exc), _int_or_none(exc.line), limit=limit, reason=str(raw or code))
    if isinstance(exc, HexacncError):
        raw = getattr(exc, "code", None)
        if raw in ERROR_CODES:
            code = raw
        elif isinstance(exc, KinematicsError):
            code = LIMIT
        elif state == "fault":
            code = FAULT
        elif op in ("pause", "resume", "reset"):
            code = INVALID_STATE
        elif state in ("running", "paused", "stopping"):
            code = BUSY
        else:
            code = REFUSED
        return error_reply(req_id, code, str(exc), _int_or_none(getattr(exc, "line", None)))
    return error_reply(req_id, INTERNAL, f"{type(exc).__name__}: {exc}")


# -- encoding ----------------------------------------------------------------
def plain(obj: Any) -> Any:
    """A copy of ``obj`` made of msgpack-native types (numpy arrays and scalars, tuples, sets)."""
    if obj is None or isinstance(obj, (bool, int, float, str, bytes)):
        return obj
    if isinstance(obj, dict):
        return {str(k) if not isinstance(k, (str, int)) else k: plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [plain(v) for v in obj]
    tolist = getattr(obj, "tolist", None)          # numpy arrays and scalars
    if tolist is not None:
        return plain(tolist())
    if hasattr(obj, "__float__"):
        return float(obj)
    return str(obj)


def encode(msg: dict) -> bytes:
    """One message as msgpack bytes (str as UTF-8 str, bytes as bin)."""
    try:
        return msgpack.packb(msg, use_bin_type=True)
    except (TypeError, ValueError, OverflowError):
        return msgpack.packb(plain(msg), use_bin_type=True)


class Decoder:
    """Incremental decoder: ``feed(data)`` then iterate ``messages()``.

    Raises :class:`ProtocolError` for undecodable bytes or a message over
    ``max_bytes``; after that the stream cannot be resynchronised and the
    connection must be closed.
    """

    def __init__(self, max_bytes: int = MAX_MESSAGE_BYTES):
        self.max_bytes = int(max_bytes)
        # non-string map keys decode (and then fail validation with a reply); only what cannot
        # become a Python object at all (bad bytes, invalid UTF-8, unhashable keys) is fatal
        self._u = msgpack.Unpacker(raw=False, max_buffer_size=self.max_bytes, strict_map_key=False)
        self.too_large = False

    def feed(self, data: bytes) -> None:
        try:
            self._u.feed(data)
        except msgpack.BufferFull as exc:
            self.too_large = True
            raise ProtocolError(f"message larger than {self.max_bytes} bytes") from exc

    def messages(self) -> Iterator[Any]:
        while True:
            try:
                msg = next(self._u)
            except StopIteration:
                return
            except Exception as exc:  # FormatError, StackError, ValueError, UnicodeDecodeError, ...
                raise ProtocolError(f"undecodable msgpack: {type(exc).__name__}: {exc}") from exc
            yield msg


# -- client -----------------------------------------------------------------
class ConnectionLost(ProtocolError):
    """The daemon closed the connection or could not be reached."""


class DaemonError(ProtocolError):
    """An error reply: ``code``, ``line`` and the whole ``reply``."""

    def __init__(self, reply: dict):
        err = reply.get("error") or {}
        self.code = err.get("code", INTERNAL)
        self.line = err.get("line")
        self.reply = reply
        self.error = err
        super().__init__(f"{err.get('message', 'error')} [{self.code}]")


class Client:
    """Blocking client: ``Client.unix(path)`` or ``Client.tcp(port, token)``.

    ``call(op, **fields)`` sends a request and returns its reply (raising
    :class:`DaemonError` on ``ok: false`` when ``check``).  Messages for other
    ids that arrive meanwhile (subscription stream) are kept in ``pending``
    and handed out by ``next_message``.
    """

    def __init__(self, sock: socket.socket, max_bytes: int = MAX_MESSAGE_BYTES):
        self.sock = sock
        self.dec = Decoder(max_bytes)
        self.pending: list[dict] = []
        self._next_id = 1
        self.server_info: dict = {}             #: the daemon's last "hello" reply

    @classmethod
    def unix(cls, path: str, timeout_s: float = 5.0) -> "Client":
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(timeout_s)
        try:
            s.connect(path)
        except OSError as exc:
            s.close()
            raise ConnectionLost(f"cannot connect to the daemon at {path}: {exc.strerror or exc}") from exc
        s.settimeout(None)
        return cls(s)

    @classmethod
    def tcp(cls, port: int, token: str, host: str = "127.0.0.1", timeout_s: float = 5.0,
            client_name: str = "", tls_ca: str | None = None) -> "Client":
        """Connect over TCP (TLS checking the daemon's certificate against ``tls_ca`` when given)
        and authenticate with ``hello`` + ``token``."""
        try:
            s = socket.create_connection((host, port), timeout=timeout_s)
            if tls_ca:
                from .tlsio import client_context
                s = client_context(tls_ca).wrap_socket(s, server_hostname=host)
        except OSError as exc:
            raise ConnectionLost(f"cannot connect to the daemon at {host}:{port}: {exc.strerror or exc}") from exc
        s.settimeout(None)
        c = cls(s)
        try:
            c.call("hello", token=token, client=client_name)
        except BaseException:
            c.close()
            raise
        return c

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def send(self, op: str, **fields: Any) -> int:
        rid = self._next_id
        self._next_id += 1
        msg = {"id": rid, "op": op}
        msg.update(fields)
        try:
            self.sock.sendall(encode(msg))
        except OSError as exc:
            why = self._parting_words()
            raise ConnectionLost(f"connection to the daemon lost: {exc.strerror or exc}"
                                 + (f" ({why})" if why else "")) from exc
        return rid

    def _parting_words(self) -> str:
        """The error the daemon sent before it closed (e.g. why it refused this peer), or ""."""
        try:
            while self._read_more(0.5):
                pass
        except (ProtocolError, OSError):
            pass
        for m in self.pending:
            if isinstance(m, dict) and m.get("ok") is False and isinstance(m.get("error"), dict):
                return f"{m['error'].get('message', '')} [{m['error'].get('code', '')}]"
        return ""

    def _read_more(self, timeout_s: float | None) -> bool:
        self.sock.settimeout(timeout_s)
        try:
            data = self.sock.recv(65536)
        except (socket.timeout, BlockingIOError):
            return False
        except OSError as exc:
            raise ConnectionLost(f"connection to the daemon lost: {exc.strerror or exc}") from exc
        if not data:
            raise ConnectionLost("the daemon closed the connection")
        self.dec.feed(data)
        self.pending.extend(m for m in self.dec.messages())
        return True

    def next_message(self, timeout_s: float | None = None) -> dict | None:
        """The next message of any id, or None after ``timeout_s``."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self.pending:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return None
            self._read_more(left)
        return self.pending.pop(0)

    def reply_to(self, rid: int, timeout_s: float | None = None, check: bool = True) -> dict:
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            for i, m in enumerate(self.pending):
                if isinstance(m, dict) and m.get("id") == rid and "stream" not in m:
                    del self.pending[i]
                    if check and not m.get("ok"):
                        raise DaemonError(m)
                    return m
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise ConnectionLost(f"no reply from the daemon within {timeout_s} s")
            self._read_more(left)

    def call(self, op: str, reply_timeout_s: float | None = 30.0, check: bool = True, **fields: Any) -> dict:
        """Send ``op`` with ``fields`` and return its reply (``reply_timeout_s`` None: no limit).

        A "wait" gets ``reply_timeout_s`` extended by its own ``timeout_s``.
        """
        if op == "wait" and reply_timeout_s is not None and isinstance(fields.get("timeout_s"), (int, float)):
            reply_timeout_s += float(fields["timeout_s"])
        reply = self.reply_to(self.send(op, **fields), reply_timeout_s, check)
        if op == "hello" and reply.get("ok"):
            self.server_info = reply            # e.g. the daemon's max_message_bytes
        return reply
