"""``hexacnc status``: the running daemon's state, poses, struts, fault and cycle statistics.

``--json`` prints the status reply as one JSON object (non-finite numbers as
null); ``--watch`` subscribes and redraws at ``[daemon] status_rate_hz`` (or
``--rate``), one JSON object per line with ``--json``.  Exit code 0 when the
daemon answered, 6 when it cannot be reached.
"""
from __future__ import annotations

import argparse
import json
import math
import textwrap
import sys
from typing import Any, TextIO

from ..errors import HexacncError
from .send import (EXIT_CONNECTION, EXIT_FAULT, EXIT_LOCAL, EXIT_OK, add_connection_args, connect, fmt_duration,
                   progress_of)
from .statusview import WIDTH, fixed, format_compact

HELP = "show the running daemon's state, poses, struts and cycle statistics"

#: reply keys that are protocol framing, not status
_FRAMING = ("id", "ok", "stream", "seq", "dropped", "sub", "rate_hz", "role")


def configure(parser: argparse.ArgumentParser) -> None:
    add_connection_args(parser)
    parser.add_argument("--json", action="store_true", help="print JSON (one object; one per line with --watch)")
    parser.add_argument("--watch", action="store_true", help="keep showing the status until Ctrl-C")
    parser.add_argument("--rate", type=float, default=None, metavar="HZ",
                        help="--watch update rate (default: [daemon] status_rate_hz of the daemon)")
    parser.add_argument("--count", type=int, default=0, metavar="N",
                        help="--watch: stop after N updates (0: until Ctrl-C)")


def json_safe(obj: Any) -> Any:
    """Strict-JSON copy: NaN/inf -> None, bytes -> hex."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (bytes, bytearray)):
        return obj.hex()
    return obj


def _vec(v: Any, digits: int = 3) -> str:
    if not isinstance(v, (list, tuple)):
        return "-" if v is None else str(v)
    parts = []
    for x in v:
        if isinstance(x, (int, float)) and not isinstance(x, bool):
            parts.append(fixed(x, digits) if math.isfinite(x) else "nan")
        else:
            parts.append(str(x))
    return "[" + ", ".join(parts) + "]"


def _scalar(v: Any) -> str:
    """One value of the details: numbers to 6 significant digits, None and non-finite as '-'."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.6g}" if math.isfinite(v) else "-"
    return str(v)


def _wrapped(head: str, text: str, indent: int) -> list[str]:
    """``head`` + ``text`` on lines of at most WIDTH characters, broken at spaces (after a list's commas
    first), continuations indented by ``indent``."""
    return textwrap.wrap(head + text, width=WIDTH, subsequent_indent=" " * indent, break_on_hyphens=False,
                         drop_whitespace=True) or [head.rstrip()]


def _detail_lines(key: str, v: Any, indent: int = 0) -> list[str]:
    """A status field as text lines of at most WIDTH characters: nested maps indented under their key, lists of
    scalars on one (wrapped) line, lists of maps item by item (no Python reprs)."""
    pad = " " * indent
    if isinstance(v, dict):
        if not v:
            return [f"{pad}{key}: -"]
        out = [f"{pad}{key}:"]
        for k, x in v.items():
            out.extend(_detail_lines(str(k), x, indent + 2))
        return out
    if isinstance(v, (list, tuple)):
        if not v:
            return [f"{pad}{key}: -"]
        if all(not isinstance(x, (dict, list, tuple)) for x in v):
            head = f"{pad}{key}: "
            return _wrapped(head, ", ".join(_scalar(x) for x in v), len(head))
        out = [f"{pad}{key}:"]
        for i, x in enumerate(v):
            out.extend(_detail_lines(f"[{i}]", x, indent + 2))
        return out
    return _wrapped(f"{pad}{key}: ", _scalar(v), indent + 2)


#: operator fields shown by the compact view (not repeated in the details)
_OPERATOR = ("tool_tip", "work_offset", "tool", "feed", "overrides", "block", "modal", "message", "elapsed_s",
             "remaining_s", "referenced", "jog", "why_idle", "controller", "drives_enabled")


def format_status(st: dict) -> str:
    """Human-readable multi-line status: the compact operator view, then the details."""
    out = [format_compact(st), "", f"state      {st.get('state', '?')}"]
    pr = progress_of(st)
    if pr.get("name") or pr.get("percent") is not None:
        pct = pr.get("percent")
        pct_s = f"{pct:.1f} %" if isinstance(pct, (int, float)) and math.isfinite(pct) else "-"
        out.append(f"program    {pr.get('name') or '-'}  line {pr.get('line', st.get('line'))}  {pct_s}  "
                   f"left {fmt_duration(pr.get('time_left_s'))}")
    else:
        out.append(f"line       {st.get('line')}")
    out.append(f"pose_cmd   {_vec(st.get('pose_cmd'))}  (mm, deg)")
    out.append(f"pose_act   {_vec(st.get('pose_act'))}")
    out.append(f"struts_cmd {_vec(st.get('struts_cmd_mm'))} mm")
    out.append(f"struts_act {_vec(st.get('struts_act_mm'))} mm")
    f = st.get("fault")
    if isinstance(f, dict):
        where = "".join(f" {k} {f[k]}" for k in ("strut", "line") if f.get(k) is not None)
        out.append(f"fault      {f.get('code', '')}: {f.get('message', '')}{(' (' + where.strip() + ')') if where else ''}")
    elif f:
        out.append(f"fault      {f}")
    cy = st.get("cycle", st.get("cycle_stats"))
    if cy is not None:
        out.extend(_detail_lines("cycle", cy))
    shown = {"state", "progress", "program", "line", "pose_cmd", "pose_act", "struts_cmd_mm", "struts_act_mm", "fault",
             "cycle", "cycle_stats", *_FRAMING, *_OPERATOR}
    for k, v in st.items():
        if k not in shown:
            out.extend(_detail_lines(k, v))
    return "\n".join(out)


def _exit_of(st: dict) -> int:
    """0, or 4 with a one-line reason on stderr when the machine is in fault."""
    if st.get("state") == "fault":
        f = st.get("fault") or {}
        print(f"hexacnc status: fault: {f.get('message', f) if isinstance(f, dict) else f}", file=sys.stderr)
        return EXIT_FAULT
    return EXIT_OK


def _strip(msg: dict) -> dict:
    return {k: v for k, v in msg.items() if k not in _FRAMING}


def main(args: argparse.Namespace) -> int:
    from ..daemon import protocol as P
    out: TextIO = sys.stdout
    try:
        client = connect(args, "hexacnc status")
    except P.ConnectionLost as exc:
        print(f"hexacnc status: {exc}", file=sys.stderr)
        return EXIT_CONNECTION
    except P.DaemonError as exc:
        print(f"hexacnc status: the daemon refused the connection: {exc}", file=sys.stderr)
        return EXIT_CONNECTION
    except HexacncError as exc:
        print(f"hexacnc status: {exc}", file=sys.stderr)
        return EXIT_LOCAL
    with client:
        try:
            if not args.watch:
                st = _strip(client.call("status"))
                if args.json:
                    out.write(json.dumps(json_safe(st), sort_keys=True) + "\n")
                else:
                    out.write(format_status(st) + "\n")
                return _exit_of(st)
            fields = {} if args.rate is None else {"rate_hz": args.rate}
            first = client.call("subscribe", **fields)
            sub = first.get("sub", first.get("id"))
            tty = out.isatty() and not args.json
            n = 0
            msg: dict | None = first
            while True:
                if msg is not None and msg.get("id") == sub and msg.get("ok"):
                    st = _strip(msg)
                    if args.json:
                        out.write(json.dumps(json_safe(st), sort_keys=True) + "\n")
                    elif tty:
                        out.write("\x1b[H\x1b[J" + format_compact(st) + "\n")
                    else:
                        out.write(format_compact(st) + "\n\n")
                    out.flush()
                    n += 1
                    if args.count and n >= args.count:
                        return EXIT_OK
                msg = client.next_message(None)
        except KeyboardInterrupt:
            return EXIT_OK
        except P.DaemonError as exc:
            print(f"hexacnc status: {exc}", file=sys.stderr)
            return EXIT_CONNECTION
        except P.ConnectionLost as exc:
            print(f"hexacnc status: {exc}", file=sys.stderr)
            return EXIT_CONNECTION
