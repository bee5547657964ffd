"""Interactive jog in the terminal (``hexacnc jog --interactive``); see :mod:`.jog`."""
from __future__ import annotations

import select
import sys
import termios
import time
import tty

from .machine import EXIT_LOCAL, EXIT_OK

KEYS = "x y z a b c 1-6: axis | + -: one step | > <: continuous (any key stops) | [ ]: step /10 x10 | " \
       "f: frame | space: stop | q: quit"


def _line(client, axis: str, frame: str, step: float, note: str = "") -> None:
    st = client.call("status")
    tip = (st.get("tool_tip") or {}).get("machine") or st.get("pose_cmd") or []
    pos = " ".join(f"{v:9.3f}" for v in tip)
    sys.stdout.write(f"\r\x1b[K{axis} {frame:<4} step {step:g} | tip {pos} | {st.get('state')} {note}"[:79])
    sys.stdout.flush()


def _key(timeout_s: float) -> str | None:
    if select.select([sys.stdin], [], [], timeout_s)[0]:
        return sys.stdin.read(1)
    return None


def interactive(client, args) -> int:
    from ..daemon import protocol as P
    if not sys.stdin.isatty():
        print("hexacnc jog: --interactive needs a terminal", file=sys.stderr)
        return EXIT_LOCAL
    axis, frame, step = (args.axis or "x").lower(), args.frame, float(args.step)
    frames = ("base", "tool", "work")
    print(KEYS)
    old = termios.tcgetattr(sys.stdin)
    tty.setcbreak(sys.stdin.fileno())
    note = ""
    try:
        while True:
            _line(client, axis, frame, step, note)
            k = _key(0.2)
            note = ""
            if k is None:
                continue
            if k == "q":
                break
            if k.lower() in "xyzabc123456" and k.strip():
                axis = k.lower()
            elif k == "f":
                frame = frames[(frames.index(frame) + 1) % 3]
            elif k == "[":
                step = max(1e-4, step / 10)
            elif k == "]":
                step = min(100.0, step * 10)
            elif k in "+=-":
                try:
                    client.call("jog", axis=axis, frame=frame, distance=step if k != "-" else -step)
                    client.call("wait", timeout_s=30.0)
                except P.DaemonError as exc:
                    note = exc.error.get("message", str(exc))
            elif k in "<>":
                try:
                    client.call("jog", axis=axis, frame=frame, direction=1 if k == ">" else -1, speed=args.speed)
                    while _key(0.0) is None:
                        client.call("jog", action="confirm")
                        _line(client, axis, frame, step, "continuous")
                        time.sleep(0.02)
                except P.DaemonError as exc:
                    note = exc.error.get("message", str(exc))
                finally:
                    client.call("jog", action="stop")
                    client.call("wait", timeout_s=30.0)
    finally:
        try:
            client.call("jog", action="stop")
        finally:
            termios.tcsetattr(sys.stdin, termios.TCSADRAIN, old)
            print()
    return EXIT_OK
