"""``hexacnc send program.ngc``: queue a G-code program on the running daemon and follow it.

The program is parsed, placed and checked against every limit by the daemon
before any motion; a refused program prints ``file:line: reason [code]``.
While it runs a progress bar shows line, percent and time left (plain
periodic lines when stdout is not a terminal).  Ctrl-C asks the daemon for a
controlled stop (a second Ctrl-C leaves without waiting).

Exit codes (stable, for scripts):

====  ==========================================================
0     program finished (with ``--no-wait``: accepted and queued)
2     local error (file unreadable, bad config or arguments)
3     program refused: G-code error, unsupported feature or limit
4     fault (before or during the program)
5     stopped before the end (stop by any client, or Ctrl-C)
6     connection error (daemon not running, connection lost)
7     refused for another reason (another client controls motion, busy)
====  ==========================================================
"""
from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import time
from typing import Any, TextIO

from ..errors import HexacncError

HELP = "send a G-code program to the running daemon and follow it to the end"

EXIT_OK = 0
EXIT_LOCAL = 2
EXIT_REFUSED = 3
EXIT_FAULT = 4
EXIT_STOPPED = 5
EXIT_CONNECTION = 6
EXIT_OTHER = 7

#: seconds an accepted program may show "idle" before it is considered started and gone
_START_GRACE_S = 3.0


# -- connection options shared with ``hexacnc status`` -----------------------
def add_connection_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--socket", metavar="PATH", default=None,
                        help="daemon's Unix socket (default: $HEXACNC_SOCKET, else [daemon] socket_path "
                             "of --config)")
    parser.add_argument("--config", metavar="FILE", default=None,
                        help="machine description giving the socket path (default: embedded default)")
    parser.add_argument("--tcp", metavar="PORT", type=int, default=None,
                        help="connect over TCP to 127.0.0.1:PORT instead (needs the token)")
    parser.add_argument("--token", default=None,
                        help="TCP token (default: $HEXACNC_TOKEN, else [daemon] token_file / tcp_token of --config)")
    parser.add_argument("--host", default="127.0.0.1", help="--tcp: the daemon's address (default 127.0.0.1)")
    parser.add_argument("--tls-ca", metavar="FILE", default=None,
                        help="--tcp over TLS: the daemon's certificate or its CA (default: $HEXACNC_TLS_CA)")


def connect(args: argparse.Namespace, name: str):
    """A :class:`~hexacnc.daemon.protocol.Client` from the connection options, after "hello"."""
    from ..daemon.protocol import Client
    from ..daemon.sockpath import client_socket_path, connect_checked
    if args.tcp is not None:
        token = args.token or os.environ.get("HEXACNC_TOKEN")
        if not token:
            from ..daemon.tcpauth import client_token
            token = client_token(_load_cfg(args).daemon)
        return Client.tcp(args.tcp, token, host=getattr(args, "host", "127.0.0.1"), client_name=name,
                          tls_ca=getattr(args, "tls_ca", None) or os.environ.get("HEXACNC_TLS_CA"))
    cfg = None if args.socket or os.environ.get("HEXACNC_SOCKET") else _load_cfg(args)
    path = args.socket or os.environ.get("HEXACNC_SOCKET") or client_socket_path(cfg)
    # refuses a socket (or serving process) not owned by this user, root or [daemon] service_user
    client = Client(connect_checked(path, (cfg or _load_cfg(args)).daemon.service_user))
    client.call("hello", client=name)
    return client


def _load_cfg(args: argparse.Namespace):
    from ..config import load_config
    return load_config(args.config)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("program", help="G-code file (RS274NGC as LinuxCNC reads it)")
    add_connection_args(parser)
    parser.add_argument("--chunk-bytes", type=int, default=1024 * 1024,
                        help="programs larger than this are streamed in chunks of this size with an upload "
                             "progress bar (program_begin/program_chunk/program_end; default 1 MiB)")
    parser.add_argument("--name", default=None, help="program name shown in status (default: file name)")
    parser.add_argument("--no-wait", action="store_true",
                        help="return as soon as the program is accepted and queued")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress output")
    parser.epilog = ("exit codes: 0 finished, 2 local error, 3 program refused, 4 fault, 5 stopped, "
                     "6 connection error, 7 refused otherwise (not controller, busy)")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter


# -- formatting --------------------------------------------------------------
def fmt_duration(s: Any) -> str:
    try:
        s = float(s)
    except (TypeError, ValueError):
        return "--:--"
    if not math.isfinite(s) or s < 0:
        return "--:--"
    s = int(round(s))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


def progress_of(st: dict) -> dict:
    """The status' program progress map (``progress``, or the daemon's ``program``), or {}."""
    for key in ("progress", "program"):
        pr = st.get(key)
        if isinstance(pr, dict):
            return pr
    return {}


def _progress(st: dict) -> tuple[float | None, Any, Any]:
    pr = progress_of(st)
    pct = pr.get("percent")
    try:
        pct = float(pct) if pct is not None else None
        if pct is not None and not math.isfinite(pct):
            pct = None
    except (TypeError, ValueError):
        pct = None
    line = pr.get("line", st.get("line"))
    return pct, line, pr.get("time_left_s")


class Progress:
    """Progress output: a redrawn bar on a terminal, periodic plain lines otherwise."""

    def __init__(self, out: TextIO, name: str, quiet: bool = False, plain_every_s: float = 2.0):
        self.out = out
        self.name = name
        self.quiet = quiet
        self.tty = bool(getattr(out, "isatty", lambda: False)())
        self.plain_every_s = plain_every_s
        self._last_plain = 0.0
        self._last_state = None
        self._drawn = False

    def update(self, st: dict) -> None:
        if self.quiet:
            return
        state = st.get("state", "?")
        pct, line, left = _progress(st)
        pct_s = f"{pct:5.1f} %" if pct is not None else "  -.- %"
        text = f"line {line if line is not None else '-'}  {pct_s}  left {fmt_duration(left)}  {state}"
        if self.tty:
            width = 30
            filled = int(round(width * min(max(pct or 0.0, 0.0), 100.0) / 100.0))
            bar = "#" * filled + "-" * (width - filled)
            self.out.write(f"\r\x1b[K{self.name[:24]} [{bar}] {text}")
            self.out.flush()
            self._drawn = True
        else:
            now = time.monotonic()
            if state != self._last_state or now - self._last_plain >= self.plain_every_s:
                self.out.write(f"{self.name}: {text}\n")
                self.out.flush()
                self._last_plain = now
        self._last_state = state

    def finish(self) -> None:
        if self._drawn and self.tty:
            self.out.write("\n")
            self.out.flush()
            self._drawn = False


def _fault_text(st: dict) -> str:
    f = st.get("fault")
    if isinstance(f, dict):
        return f.get("message") or f.get("text") or f.get("cause") or str(f)
    return str(f) if f else "unknown cause"


def _finished(st: dict, blocks: Any) -> bool:
    """Did the program we queued run to its end (judged from the final status)?"""
    pr = progress_of(st)
    if pr.get("stopped") or pr.get("aborted"):
        return False
    res = st.get("result") or st.get("last_result") or pr.get("result")
    if isinstance(res, str):
        return res in ("finished", "done", "complete", "completed")
    pct, _, _ = _progress(st)
    return pct is not None and pct >= 99.999


# -- main --------------------------------------------------------------------
def main(args: argparse.Namespace) -> int:
    from ..daemon import protocol as P

    out, err = sys.stdout, sys.stderr
    path = args.program
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
        text = raw.decode("utf-8")
    except OSError as exc:
        print(f"hexacnc send: cannot read {path}: {exc.strerror or exc}", file=err)
        return EXIT_LOCAL
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        print(f"hexacnc send: {path}:{line}: not valid UTF-8 text", file=err)
        return EXIT_LOCAL
    name = args.name or os.path.basename(path)
    if not 1024 <= args.chunk_bytes <= 8 * 1024 * 1024:
        print(f"hexacnc send: --chunk-bytes must be in [1024, 8388608], got {args.chunk_bytes}", file=err)
        return EXIT_LOCAL

    try:
        client = connect(args, "hexacnc send")
    except P.DaemonError as exc:
        print(f"hexacnc send: the daemon refused the connection: {exc}", file=err)
        return EXIT_CONNECTION
    except P.ConnectionLost as exc:
        print(f"hexacnc send: {exc}", file=err)
        return EXIT_CONNECTION
    except HexacncError as exc:
        print(f"hexacnc send: {exc}", file=err)
        return EXIT_LOCAL
    with client:
        try:
            return _run(client, args, path, name, text, out, err)
        except P.ConnectionLost as exc:
            print(f"\nhexacnc send: {exc}", file=err)
            return EXIT_CONNECTION


def _run(client, args, path: str, name: str, text: str, out: TextIO, err: TextIO) -> int:
    from ..daemon import protocol as P
    from .upload_client import send_program

    try:
        r = send_program(client, text, name, args.chunk_bytes, err, args.quiet)
    except P.DaemonError as exc:
        e = exc.error
        if exc.code in P.PROGRAM_CODES:
            where = f"{path}:{exc.line}" if exc.line is not None else path
            col = e.get("column")
            where += f":{col}" if col is not None and exc.line is not None else ""
            extra = f" ({e['limit']})" if e.get("limit") else ""
            msg = str(e.get("message", ""))
            if exc.line is not None and msg.startswith(f"line {exc.line}: "):
                msg = msg[len(f"line {exc.line}: "):]          # the file:line prefix says it
            print(f"{where}: program refused: {msg}{extra} [{exc.code}]", file=err)
            return EXIT_REFUSED
        print(f"hexacnc send: {name} refused: {e.get('message', '')} [{exc.code}]", file=err)
        return EXIT_FAULT if exc.code == P.FAULT else EXIT_OTHER
    blocks = r.get("blocks")
    dur = r.get("duration_s")
    if not args.quiet:
        print(f"{name}: accepted, {blocks} blocks, about {fmt_duration(dur)}", file=out)
    if args.no_wait:
        return EXIT_OK

    prog = Progress(out, name, args.quiet)
    interrupted = {"n": 0}
    old = signal.getsignal(signal.SIGINT)

    def on_sigint(signum, frame):          # noqa: ARG001
        interrupted["n"] += 1
        if interrupted["n"] > 1:
            raise KeyboardInterrupt

    try:
        signal.signal(signal.SIGINT, on_sigint)
    except ValueError:                     # not the main thread (tests)
        old = None
    try:
        return _follow(client, prog, blocks, name, interrupted, err)
    except KeyboardInterrupt:
        prog.finish()
        print(f"hexacnc send: left without waiting; {name} may still be stopping", file=err)
        return EXIT_STOPPED
    finally:
        prog.finish()
        if old is not None:
            signal.signal(signal.SIGINT, old)


def _stdin_is_tty() -> bool:
    try:
        return sys.stdin is not None and sys.stdin.isatty()
    except (ValueError, OSError):
        return False


def _enter_pressed() -> bool:
    import select
    try:
        r, _, _ = select.select([sys.stdin], [], [], 0)
    except (ValueError, OSError):
        return False
    if r:
        sys.stdin.readline()
        return True
    return False


def _follow(client, prog: Progress, blocks: Any, name: str, interrupted: dict, err: TextIO) -> int:
    from ..daemon import protocol as P

    t_queued = time.monotonic()
    sub_id = client.send("subscribe")
    wait_id = client.send("wait", timeout_s=P.MAX_WAIT_S)
    seen_active = False
    stop_sent = False
    # a program pause (M0/M1) or a pause waits for this client, which controls motion: on a
    # terminal, Enter resumes
    interactive = _stdin_is_tty()
    paused_shown = False
    while True:
        if interactive and paused_shown and _enter_pressed():
            client.send("resume")
            paused_shown = False
        if interrupted["n"] and not stop_sent:
            stop_sent = True
            prog.finish()
            print(f"hexacnc send: stopping {name} (Ctrl-C again to leave at once)", file=err)
            client.send("stop")
        msg = client.next_message(0.25)
        if msg is None or not isinstance(msg, dict):
            continue
        rid = msg.get("id")
        if rid == sub_id:
            if msg.get("ok"):
                if msg.get("state") in ("running", "paused", "stopping"):
                    seen_active = True
                prog.update(msg)
                if msg.get("state") == "paused" and not paused_shown and not stop_sent:
                    paused_shown = True
                    prog.finish()
                    how = "press Enter to resume, Ctrl-C to stop" if interactive else \
                        "this client controls motion; run on a terminal to resume with Enter"
                    print(f"{name}: paused at line {msg.get('line')} ({how})", file=err)
                elif msg.get("state") != "paused":
                    paused_shown = False
            continue
        if rid != wait_id:
            if not msg.get("ok") and msg.get("error", {}).get("code") not in (None,):
                e = msg.get("error") or {}
                if stop_sent:
                    print(f"hexacnc send: stop refused: {e.get('message')} [{e.get('code')}]", file=err)
            continue
        # the reply to "wait"
        if not msg.get("ok"):
            e = msg.get("error") or {}
            prog.finish()
            print(f"hexacnc send: wait failed: {e.get('message')} [{e.get('code')}]", file=err)
            return EXIT_FAULT if e.get("code") == P.FAULT else EXIT_OTHER
        state = msg.get("state")
        prog.update(msg)
        if state == "fault":
            prog.finish()
            print(f"hexacnc send: {name} ended in fault at line {msg.get('line')}: {_fault_text(msg)}",
                  file=err)
            return EXIT_FAULT
        if state == "idle" and not msg.get("timed_out"):
            if _finished(msg, blocks):
                prog.finish()
                if not prog.quiet:
                    print(f"{name}: finished", file=prog.out)
                return EXIT_OK
            aborted = progress_of(msg).get("aborted")
            if aborted and progress_of(msg).get("name") == name:
                prog.finish()
                print(f"hexacnc send: {name} aborted at line {msg.get('line')}: {aborted}", file=err)
                return EXIT_STOPPED
            if seen_active or stop_sent or time.monotonic() - t_queued > _START_GRACE_S:
                prog.finish()
                print(f"hexacnc send: {name} stopped at line {msg.get('line')} before its end", file=err)
                return EXIT_STOPPED
        # not started yet, or timed out: wait again
        time.sleep(0.02)
        wait_id = client.send("wait", timeout_s=P.MAX_WAIT_S)
