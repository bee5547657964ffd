"""Chunked program transfer: ``program_begin`` / ``program_chunk`` / ``program_end`` (see docs/protocol.md).

A program larger than one protocol message arrives in chunks on one connection: ``program_begin`` declares its
name and size in bytes (UTF-8), ``program_chunk`` carries the next piece of text with its sequence number
(0, 1, 2, ...), ``program_end`` hands the assembled text to the same path as ``program`` (parsed, planned and
checked before any motion).  Nothing accepted is lost: every chunk is acknowledged with the bytes received so
far; a chunk out of sequence, over the declared size or with a NUL is refused and changes nothing (the client
sends it again or starts over).  Each chunk is at most one message (``[daemon] max_message_bytes``,
2 MiB by default), so the socket loop spends about a millisecond per MiB on it.  Memory is bounded: one open upload per connection, at most
:data:`MAX_PROGRAM_BYTES` each and :data:`MAX_OPEN_BYTES` over all connections; a disconnect or a new
``program_begin`` drops the open upload.
"""
from __future__ import annotations

from dataclasses import dataclass, field

#: the largest program accepted in chunks (bytes of UTF-8 text)
MAX_PROGRAM_BYTES = 256 * 1024 * 1024
#: declared bytes of all open uploads together
MAX_OPEN_BYTES = 512 * 1024 * 1024


class UploadError(Exception):
    """A refused upload step: ``code`` is a protocol error code (``bad_value``, ``too_large``,
    ``invalid_state``), the message names the field."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


@dataclass
class _Upload:
    name: str
    declared: int
    parts: list = field(default_factory=list)
    received: int = 0
    seq: int = 0


class Uploads:
    """Open uploads keyed by connection (any hashable key)."""

    def __init__(self, max_program_bytes: int = MAX_PROGRAM_BYTES, max_open_bytes: int = MAX_OPEN_BYTES):
        self.max_program_bytes = int(max_program_bytes)
        self.max_open_bytes = int(max_open_bytes)
        self._open: dict = {}

    def begin(self, key, name: str, nbytes: int) -> dict:
        if isinstance(nbytes, bool) or not isinstance(nbytes, int) or nbytes < 0:
            raise UploadError("bad_value", f"op 'program_begin': bytes must be an integer >= 0, got {nbytes!r}")
        if nbytes > self.max_program_bytes:
            raise UploadError("too_large", f"op 'program_begin': {nbytes} bytes over the limit of "
                                           f"{self.max_program_bytes} bytes per program")
        self._open.pop(key, None)
        held = sum(u.declared for u in self._open.values())
        if held + nbytes > self.max_open_bytes:
            raise UploadError("too_large", f"op 'program_begin': {nbytes} bytes would exceed the "
                                           f"{self.max_open_bytes} bytes of all open uploads ({held} held)")
        self._open[key] = _Upload(name, nbytes)
        return {"name": name, "bytes": nbytes, "next_seq": 0}

    def chunk(self, key, seq: int, text: str) -> dict:
        up = self._open.get(key)
        if up is None:
            raise UploadError("invalid_state", "op 'program_chunk': no upload open on this connection "
                                               "(send program_begin first)")
        if isinstance(seq, bool) or not isinstance(seq, int) or seq != up.seq:
            raise UploadError("bad_value", f"op 'program_chunk': seq {seq!r} out of order, expected {up.seq} "
                                           f"({up.received} bytes received)")
        if "\x00" in text:
            raise UploadError("bad_value", f"op 'program_chunk': chunk {seq} contains a NUL character")
        n = len(text.encode("utf-8"))
        if up.received + n > up.declared:
            raise UploadError("too_large", f"op 'program_chunk': chunk {seq} brings the program to "
                                           f"{up.received + n} bytes, over the {up.declared} declared")
        up.parts.append(text)
        up.received += n
        up.seq += 1
        return {"seq": seq, "received_bytes": up.received, "next_seq": up.seq}

    def end(self, key) -> tuple[str, str]:
        """(text, name) of the complete upload, which is closed; refused while bytes are missing."""
        parts, name = self.take(key)
        return "".join(parts), name

    def take(self, key) -> tuple[list, str]:
        """As :meth:`end` with the text still in pieces, to be joined off the socket loop (a join of a
        20 MB program holds the GIL for milliseconds)."""
        up = self._open.get(key)
        if up is None:
            raise UploadError("invalid_state", "op 'program_end': no upload open on this connection")
        if up.received != up.declared:
            raise UploadError("bad_value", f"op 'program_end': {up.received} of {up.declared} declared bytes "
                                           f"received (next seq {up.seq})")
        del self._open[key]
        return up.parts, up.name

    def drop(self, key) -> None:
        self._open.pop(key, None)

    def open_bytes(self) -> int:
        return sum(u.received for u in self._open.values())


class UploadOps:
    """The three ops for :class:`hexacnc.daemon.server.SocketServer` (a mixin: uses its ``_take_control``,
    ``_program_loader``, ``_send``, ``_submit_motion`` and ``daemon``; the server keeps an :class:`Uploads` in ``_uploads``)."""

    def _upload_step(self, conn, req, step) -> None:
        from . import protocol as P
        if not self._take_control(conn, req):
            return
        try:
            self._send(conn, P.ok_reply(req.id, **step()))
        except UploadError as exc:
            self.stats["errors"] += 1
            self._send(conn, P.error_reply(req.id, exc.code, exc.message))

    def _op_program_begin(self, conn, req) -> None:
        self._upload_step(conn, req, lambda: self._uploads.begin(conn.num, req.fields["name"],
                                                                 req.fields["bytes"]))

    def _op_program_chunk(self, conn, req) -> None:
        self._upload_step(conn, req, lambda: self._uploads.chunk(conn.num, req.fields["seq"],
                                                                 req.fields["text"]))

    def _op_program_end(self, conn, req) -> None:
        from . import protocol as P
        if not self._take_control(conn, req):
            return
        try:
            parts, name = self._uploads.take(conn.num)
        except UploadError as exc:
            self.stats["errors"] += 1
            self._send(conn, P.error_reply(req.id, exc.code, exc.message))
            return

        def reply(result) -> dict:
            info = P.plain(result) if isinstance(result, dict) else {"blocks": result}
            info.setdefault("name", name)
            return P.ok_reply(req.id, **info)
        load = self._program_loader()           # as op "program": the operator's state when there is one
        # the chunks go on as they came (never joined here: one join of a large program holds the
        # interpreter lock for tens of ms, and a stop would wait behind it; :mod:`.progtext`)
        self._submit_motion(conn, req, self._unless_stopped(lambda stops: load(parts, name, stops), name),
                            reply)
