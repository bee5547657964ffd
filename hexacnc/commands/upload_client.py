"""Client side of the chunked program transfer (``program_begin`` / ``program_chunk`` / ``program_end``) for
``hexacnc send``: a program larger than one chunk is sent in pieces split at line ends (never inside a UTF-8
character) with an upload progress bar; a smaller one, or a daemon without the ops, gets the single
``program`` op."""
from __future__ import annotations

import sys
import time
from typing import TextIO

#: default chunk size (bytes; the daemon's message limit, [daemon] max_message_bytes, is 2 MiB by default)
CHUNK_BYTES = 1024 * 1024
#: bytes of a message besides its text (msgpack framing, id, op, seq, name), with room to spare
MESSAGE_OVERHEAD_BYTES = 4096


def chunk_limit(client, chunk_bytes: int) -> int:
    """``chunk_bytes``, at most what fits one message of the daemon (its ``hello``'s ``max_message_bytes``)."""
    limit = (getattr(client, "server_info", None) or {}).get("max_message_bytes")
    if isinstance(limit, int) and not isinstance(limit, bool) and limit > 2 * MESSAGE_OVERHEAD_BYTES:
        return max(1024, min(int(chunk_bytes), limit - MESSAGE_OVERHEAD_BYTES))
    return int(chunk_bytes)


def split_chunks(data: bytes, chunk_bytes: int) -> list[bytes]:
    """``data`` in pieces of at most ``chunk_bytes``, cut after a newline where one lies in the second half
    of the piece, else at a UTF-8 character boundary."""
    out = []
    i, n = 0, len(data)
    while i < n:
        j = min(n, i + chunk_bytes)
        if j < n:
            nl = data.rfind(b"\n", i + chunk_bytes // 2, j)
            if nl >= 0:
                j = nl + 1
            else:
                while j > i + 1 and (data[j] & 0xC0) == 0x80:      # inside a multi-byte character
                    j -= 1
        out.append(data[i:j])
        i = j
    return out


def _bar(err: TextIO, name: str, done: int, total: int, t0: float) -> None:
    pct = 100.0 * done / total if total else 100.0
    rate = done / max(time.monotonic() - t0, 1e-6) / 1e6
    width = 30
    filled = int(round(width * pct / 100.0))
    line = f"{name[:24]} upload [{'#' * filled}{'-' * (width - filled)}] {pct:5.1f} %  {done / 1e6:.1f} MB  {rate:.1f} MB/s"
    if getattr(err, "isatty", lambda: False)():
        err.write("\r\x1b[K" + line)
    else:
        err.write(line + "\n")
    err.flush()


def send_program(client, text: str, name: str, chunk_bytes: int = CHUNK_BYTES, err: TextIO | None = None,
                 quiet: bool = False) -> dict:
    """Queue ``text`` on the daemon (single op or chunks); returns the daemon's reply to the program.
    Raises the protocol's DaemonError on a refusal (of a chunk or of the program)."""
    from ..daemon import protocol as P
    err = sys.stderr if err is None else err
    chunk_bytes = chunk_limit(client, chunk_bytes)
    data = text.encode("utf-8")
    if len(data) <= chunk_bytes:
        return client.call("program", text=text, name=name, reply_timeout_s=None)
    try:
        client.call("program_begin", name=name, bytes=len(data))
    except P.DaemonError as exc:
        if exc.code == P.UNKNOWN_OP:                 # an older daemon: one message
            return client.call("program", text=text, name=name, reply_timeout_s=None)
        raise
    t0 = time.monotonic()
    done = 0
    last_draw = 0.0
    for seq, part in enumerate(split_chunks(data, chunk_bytes)):
        r = client.call("program_chunk", seq=seq, text=part.decode("utf-8"))
        done = int(r.get("received_bytes", done + len(part)))
        now = time.monotonic()
        if not quiet and (now - last_draw >= 0.2 or done == len(data)):
            _bar(err, name, done, len(data), t0)
            last_draw = now
    if not quiet and getattr(err, "isatty", lambda: False)():
        err.write("\n")
    return client.call("program_end", reply_timeout_s=None)
