"""``hexacnc jog``: move one axis by hand.

    hexacnc jog z +0.1                      # incremental: 0.1 mm along base z
    hexacnc jog a -0.5 --frame tool         # 0.5 deg about the tool frame's x axis, through the pivot
    hexacnc jog 3 +1                        # strut 3 one mm longer (other struts fixed to first order)
    hexacnc jog --continuous x +            # until Enter / Ctrl-C / --for S (deadman: confirmed every 20 ms)
    hexacnc jog --pivot 0,0,-300            # rotations about this platform point ("tip": the tool tip)
    hexacnc jog --interactive               # keys: axis x y z a b c 1-6, + / - one step, > / < continuous,
                                            # [ ] step /10 x10, f frame, space stop, q quit

An incremental jog past a limit is refused (exit 3) naming the limit and how far it could go;
a continuous jog comes to rest at the first limit on its way.  A terminal cannot see a key being
released, so in the interactive mode a continuous jog runs until the next key: the deadman is
this process confirming every 20 ms (its end, a lost connection or a stalled terminal stop it).
"""
from __future__ import annotations

import argparse
import select
import sys
import time

from .machine import EXIT_LOCAL, EXIT_OK, EXIT_REFUSED, add_common, print_reply, run_op

HELP = "jog one axis or strut (incremental, continuous with deadman, or interactive)"
CONFIRM_S = 0.02
AXES = ("x", "y", "z", "a", "b", "c", "1", "2", "3", "4", "5", "6")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("axis", nargs="?", help="x y z a b c (Cartesian) or 1..6 (strut)")
    parser.add_argument("amount", nargs="?", help="signed step (mm or deg), or + / - with --continuous")
    parser.add_argument("--continuous", action="store_true", help="jog until Enter, Ctrl-C or --for")
    parser.add_argument("--for", dest="for_s", type=float, default=None, metavar="S",
                        help="--continuous: stop after S seconds")
    parser.add_argument("--frame", choices=("base", "tool", "work"), default="base")
    parser.add_argument("--speed", type=float, default=1.0, help="fraction of the [jog] speed (0..1]")
    parser.add_argument("--pivot", default=None, metavar="X,Y,Z|tip",
                        help="set the pivot of rotations (platform frame, mm) or 'tip' (the tool tip)")
    parser.add_argument("--interactive", "-i", action="store_true", help="interactive jog in the terminal")
    parser.add_argument("--step", type=float, default=0.1, help="--interactive: initial step (mm or deg)")
    add_common(parser)


def _pivot(client, spec: str) -> dict:
    if spec.strip().lower() == "tip":
        return client.call("pivot", pivot_mm=[])
    v = [float(x) for x in spec.split(",")]
    return client.call("pivot", pivot_mm=v)


def _wait_still(client, timeout_s: float = 30.0) -> dict:
    return client.call("wait", timeout_s=timeout_s)


def _continuous(client, args, direction: int, stop_on_key: bool) -> int:
    from ..daemon import protocol as P
    r = client.call("jog", axis=args.axis, frame=args.frame, direction=direction, speed=args.speed)
    t0 = time.monotonic()
    why = None
    try:
        while True:
            if args.for_s is not None and time.monotonic() - t0 >= args.for_s:
                break
            if stop_on_key and select.select([sys.stdin], [], [], 0)[0]:
                sys.stdin.readline()
                break
            try:
                client.call("jog", action="confirm", reply_timeout_s=2.0)
            except P.DaemonError as exc:
                why = exc.error.get("message")
                break
            time.sleep(CONFIRM_S)
    finally:
        client.call("jog", action="stop")
    st = _wait_still(client)
    pos = st.get("pose_cmd")
    if why:
        print(f"jog {args.axis} ended before the stop (at the limit: {r.get('limit')}, or stopped by another "
              f"command)", file=sys.stderr)
    print_reply(args, st, f"platform pose {[round(v, 4) for v in pos]}" if pos else "done")
    return EXIT_OK


def main(args: argparse.Namespace) -> int:
    if args.interactive:
        from .jogtty import interactive
        return run_op(args, "jog", lambda client: interactive(client, args))
    if args.axis is None:
        if args.pivot is None:
            print("hexacnc jog: give an axis and a step, --continuous, --pivot or --interactive", file=sys.stderr)
            return EXIT_LOCAL
        def set_pivot(client) -> int:
            r = _pivot(client, args.pivot)
            print_reply(args, r, f"pivot {r.get('pivot')} {r.get('pivot_mm')}")
            return EXIT_OK
        return run_op(args, "jog", set_pivot)
    if str(args.axis).lower() not in AXES:
        print(f"hexacnc jog: unknown axis {args.axis!r} (x y z a b c or 1..6)", file=sys.stderr)
        return EXIT_REFUSED
    amount = args.amount
    if args.continuous:
        if amount not in ("+", "-"):
            print("hexacnc jog: --continuous needs a direction + or -", file=sys.stderr)
            return EXIT_LOCAL
        direction = 1 if amount == "+" else -1
        on_key = args.for_s is None and sys.stdin.isatty()

        def body(client) -> int:
            if args.pivot is not None:
                _pivot(client, args.pivot)
            if on_key:
                print("jogging; Enter stops", file=sys.stderr)
            return _continuous(client, args, direction, on_key)
        return run_op(args, "jog", body)
    try:
        dist = float(amount)
    except (TypeError, ValueError):
        print(f"hexacnc jog: step {amount!r} is not a number (e.g. +0.1)", file=sys.stderr)
        return EXIT_LOCAL

    def body(client) -> int:
        if args.pivot is not None:
            _pivot(client, args.pivot)
        r = client.call("jog", axis=args.axis, frame=args.frame, distance=dist, speed=args.speed)
        st = _wait_still(client)
        if st.get("state") == "fault":
            print(f"hexacnc jog: fault: {(st.get('fault') or {}).get('message')}", file=sys.stderr)
            return 4
        print_reply(args, r, f"jogged {args.axis} {dist:+g} {r.get('unit')} ({args.frame} frame)")
        return EXIT_OK
    return run_op(args, "jog", body)
