"""Operator commands, one protocol op each: ``hexacnc pause | resume | stop | reset | enable |
disable | take | home``, ``hexacnc feed PERCENT``, ``hexacnc rapid PERCENT`` and ``hexacnc mdi
"G1 X10 F600"``.

Every command connects, (with ``--take``) takes control from whoever holds it - that client is
told - sends its op and prints one line.  Exit codes as ``hexacnc send``: 0 done, 2 local error,
3 refused for its content (G-code, limit, value), 4 fault, 5 stopped, 6 connection error, 7
refused otherwise (another client controls the machine, busy, wrong state).  Every refusal
prints one line: ``hexacnc OP: reason [code]``.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from typing import Any, Callable

from ..errors import HexacncError
from .send import (EXIT_CONNECTION, EXIT_FAULT, EXIT_LOCAL, EXIT_OK, EXIT_OTHER, EXIT_REFUSED, EXIT_STOPPED,
                   add_connection_args, connect)

#: error codes refused for their content (exit 3)
_CONTENT = ("gcode", "unsupported", "limit", "bad_value", "bad_type", "missing_field")


def exit_code_of(code: str) -> int:
    if code in _CONTENT:
        return EXIT_REFUSED
    if code == "fault":
        return EXIT_FAULT
    return EXIT_OTHER


def add_common(parser: argparse.ArgumentParser) -> None:
    add_connection_args(parser)
    parser.add_argument("--take", action="store_true",
                        help="take control of the machine first (the client holding it is told)")
    parser.add_argument("--json", action="store_true", help="print the reply as JSON")


def run_op(args: argparse.Namespace, name: str, body: Callable[[Any], int]) -> int:
    """Connect, take control if asked, run ``body(client)``; map errors to one line and an exit code."""
    from ..daemon import protocol as P
    try:
        client = connect(args, f"hexacnc {name}")
    except (P.ConnectionLost, P.DaemonError) as exc:
        print(f"hexacnc {name}: {exc}", file=sys.stderr)
        return EXIT_CONNECTION
    except HexacncError as exc:
        print(f"hexacnc {name}: {exc}", file=sys.stderr)
        return EXIT_LOCAL
    with client:
        try:
            if getattr(args, "take", False):
                r = client.call("take")
                if r.get("previous"):
                    print(f"hexacnc {name}: took control from {r['previous']}", file=sys.stderr)
            return body(client)
        except P.DaemonError as exc:
            msg = str(exc.error.get("message", exc))
            line = f" (line {exc.line})" if exc.line and not msg.startswith(f"line {exc.line}:") else ""
            print(f"hexacnc {name}: {msg}{line} [{exc.code}]", file=sys.stderr)
            return exit_code_of(exc.code)
        except P.ConnectionLost as exc:
            print(f"hexacnc {name}: {exc}", file=sys.stderr)
            return EXIT_CONNECTION
        except KeyboardInterrupt:
            return EXIT_STOPPED


def print_reply(args, r: dict, text: str) -> None:
    if getattr(args, "json", False):
        import json

        from .status import json_safe
        print(json.dumps(json_safe({k: v for k, v in r.items() if k not in ("id", "ok")}), sort_keys=True))
    else:
        print(text)


@dataclass
class SimpleOp:
    """A subcommand that sends one op without fields."""
    op: str
    HELP: str
    done: str

    def configure(self, parser: argparse.ArgumentParser) -> None:
        add_common(parser)
        if self.op in ("stop", "disable"):
            parser.add_argument("--wait", type=float, default=30.0, metavar="S",
                                help="wait up to S s for the machine to stand still (0: do not wait)")

    def main(self, args: argparse.Namespace) -> int:
        def body(client) -> int:
            r = client.call(self.op, reply_timeout_s=60.0)
            if self.op in ("stop",) and args.wait > 0:
                r = client.call("wait", timeout_s=args.wait)
                if r.get("state") == "fault":
                    print(f"hexacnc {self.op}: fault: {(r.get('fault') or {}).get('message')}", file=sys.stderr)
                    return EXIT_FAULT
            msg = self.done
            if self.op == "take":
                msg += f" (from {r['previous']})" if r.get("previous") else " (nobody held it)"
                msg += "; it is free again when this command exits"
            if self.op == "home" and r.get("message"):
                msg += f": {r['message']}"
            print_reply(args, r, f"{msg}; state {r.get('state', r.get('loop_state', '-'))}"
                        if "state" in r or "loop_state" in r else msg)
            return EXIT_OK
        return run_op(args, self.op, body)


PAUSE = SimpleOp("pause", "feed hold: decelerate the running program to rest on its path", "paused")
RESUME = SimpleOp("resume", "resume a paused program (also after M0/M1)", "resumed")
STOP = SimpleOp("stop", "controlled stop: decelerate along the path within limits, abandon the program",
                "stopped")
RESET = SimpleOp("reset", "clear a fault and enable the drives", "reset")
ENABLE = SimpleOp("enable", "enable the drives (machine on)", "drives enabled")
DISABLE = SimpleOp("disable", "controlled stop, then disable the drives (machine off)", "drives disabled")
TAKE = SimpleOp("take", "take control of the machine from the client holding it (it is told)", "control taken")
HOME = SimpleOp("home", "reference the struts ([homing] method: absolute encoders or CiA 402 homing)",
                "referenced")


@dataclass
class OverrideOp:
    key: str
    HELP: str
    hi: float

    def configure(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("percent", type=float, help=f"override in percent (0 .. {self.hi * 100:g})")
        add_common(parser)

    def main(self, args: argparse.Namespace) -> int:
        import math
        p = args.percent
        if not math.isfinite(p) or not 0.0 <= p <= self.hi * 100.0:
            print(f"hexacnc {self.key}: {p:g} % is outside 0 .. {self.hi * 100:g} %", file=sys.stderr)
            return EXIT_REFUSED

        def body(client) -> int:
            r = client.call("override", **{self.key: p / 100.0})
            print_reply(args, r, f"feed {100 * r['feed']:g} %  rapid {100 * r['rapid']:g} %")
            return EXIT_OK
        return run_op(args, self.key, body)


FEED = OverrideOp("feed", "feed override in percent (0 .. [planner] max_feed_override x 100)", 2.0)
RAPID = OverrideOp("rapid", "rapid override in percent (0 .. 100): acts on G0 moves only", 1.0)


@dataclass
class SwitchOp:
    """An operator's panel switch, a boolean field of the ``override`` op."""
    name: str
    key: str
    HELP: str

    def configure(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("switch", nargs="?", choices=("on", "off"), help="on or off (none: show it)")
        add_common(parser)

    def main(self, args: argparse.Namespace) -> int:
        def body(client) -> int:
            kw = {} if args.switch is None else {self.key: args.switch == "on"}
            r = client.call("override", **kw)
            print_reply(args, r, f"{self.name.replace('-', ' ')} {'on' if r.get(self.key) else 'off'}")
            return EXIT_OK
        return run_op(args, self.name, body)


OPTIONAL_STOP = SwitchOp("optional-stop", "optional_stop",
                         "show or set the optional-stop switch: on, M1 pauses a program as M0 does")
BLOCK_DELETE = SwitchOp("block-delete", "block_delete",
                        "show or set the block-delete switch: on, lines starting with '/' are skipped "
                        "(programs sent after it)")


class MdiOp:
    HELP = "execute G-code lines now (MDI), in the modal state the last program left"

    def configure(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("text", help="G-code, e.g. \"G1 X10 F600\" (several lines: separate by newlines)")
        parser.add_argument("--no-wait", action="store_true", help="return once queued")
        add_common(parser)

    def main(self, args: argparse.Namespace) -> int:
        def body(client) -> int:
            r = client.call("mdi", text=args.text, reply_timeout_s=120.0)
            if args.no_wait or not r.get("duration_s"):
                print_reply(args, r, f"MDI accepted ({r.get('blocks', 0)} blocks, {r.get('duration_s', 0):.2f} s)")
                return EXIT_OK
            st = client.call("wait", timeout_s=max(30.0, 3 * float(r["duration_s"])))
            if st.get("state") == "fault":
                print(f"hexacnc mdi: fault: {(st.get('fault') or {}).get('message')}", file=sys.stderr)
                return EXIT_FAULT
            prog = st.get("program") or {}
            if prog.get("stopped") or prog.get("aborted"):
                print(f"hexacnc mdi: stopped before the end ({prog.get('aborted') or 'stop'})", file=sys.stderr)
                return EXIT_STOPPED
            print_reply(args, st, f"MDI done ({r.get('duration_s', 0):.2f} s)")
            return EXIT_OK
        return run_op(args, "mdi", body)


MDI = MdiOp()
