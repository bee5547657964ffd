"""``hexacnc record``: record the cycle's signals from the running daemon into a .npz or .csv file.

Client side of the socket protocol (docs/protocol.md): one ``subscribe`` stream at
``--rate`` Hz; each stream message is a status sample (the cycle's signals
decimated to that rate: the daemon's status is sampled, not averaged).  Signals
and file layout: :mod:`hexacnc.calib.recording`.  The file is written atomically
when the count or duration is reached, or on Ctrl-C (what was recorded so far).
Exit 0 on success, 2 on bad input or nothing recorded, 6 when the daemon cannot
be reached.
"""
from __future__ import annotations

import argparse
import sys
import time

from ..errors import DataError
from .send import EXIT_CONNECTION, add_connection_args, connect

HELP = "record the cycle's signals (struts, following errors, torques, temperatures) to .npz/.csv"


def configure(p: argparse.ArgumentParser) -> None:
    add_connection_args(p)
    p.add_argument("--out", required=True, help="recording file: .npz (numpy.load) or .csv (pandas.read_csv, "
                                                "comment='#')")
    p.add_argument("--rate", type=float, default=100.0, metavar="HZ",
                   help="samples per second from the daemon's status stream (0.1-1000, default 100): the cycle's "
                        "signals decimated to this rate")
    p.add_argument("--duration", type=float, default=10.0, metavar="S",
                   help="seconds to record after the trigger (default 10)")
    p.add_argument("--count", type=int, default=None, metavar="N", help="stop after N samples")
    p.add_argument("--trigger", default="none",
                   help="start condition: none, state=NAME (e.g. state=running), following_error>MM, temperature>C")
    p.add_argument("--pretrigger", type=float, default=0.0, metavar="S",
                   help="also keep this many seconds before the trigger")
    p.add_argument("--timeout", type=float, default=60.0, metavar="S",
                   help="give up when the trigger has not fired after this many seconds (default 60)")


def check_args(args) -> None:
    if not 0.1 <= args.rate <= 1000.0:
        raise DataError(f"--rate must be within 0.1..1000 Hz, got {args.rate}")
    if not args.duration > 0:
        raise DataError(f"--duration must be positive, got {args.duration}")
    if args.pretrigger < 0 or args.timeout <= 0:
        raise DataError("--pretrigger must be >= 0 and --timeout positive")
    if not str(args.out).endswith((".npz", ".csv")):
        raise DataError(f"--out {args.out}: recording files end in .npz or .csv")


def record(client, args, recorder, clock=time.monotonic) -> dict:
    """Fill ``recorder`` from a subscription; returns the meta data (rate, counts, stop reason)."""
    first = client.call("subscribe", rate_hz=float(args.rate))
    sub = first.get("sub", first.get("id"))
    t_start = clock()
    msg: dict | None = first
    reason = "count"
    dropped = 0
    try:
        while True:
            now = clock()
            if msg is not None and msg.get("id") == sub and msg.get("ok") and "state" in msg:
                dropped = int(msg.get("dropped", dropped) or 0)
                if recorder.add(msg, now):
                    break
            if recorder.triggered_at is None and now - t_start > args.timeout:
                reason = "trigger_timeout"
                break
            if recorder.triggered_at is not None and now - recorder.triggered_at >= args.duration:
                reason = "duration"
                break
            msg = client.next_message(1.0)
    except KeyboardInterrupt:
        reason = "interrupted"
    try:
        client.call("unsubscribe", sub=sub, check=False)
    except Exception:   # noqa: BLE001 - the recording matters more than a clean unsubscribe
        pass
    return {"rate_hz": float(first.get("rate_hz", args.rate)), "stop": reason, "dropped": dropped,
            "decimation": "status stream sampled at rate_hz from the cycle (not averaged)"}


def main(args: argparse.Namespace) -> int:
    from ..calib.recorder import Recorder, parse_trigger
    from ..calib.recording import save
    from ..daemon import protocol as P
    check_args(args)
    trig = parse_trigger(args.trigger)
    count = args.count if args.count is not None else int(round(args.rate * args.duration)) + 1
    rec = Recorder(trig, count, int(round(args.pretrigger * args.rate)))
    try:
        client = connect(args, "hexacnc record")
    except (P.ConnectionLost, P.DaemonError) as exc:
        print(f"hexacnc record: {exc}", file=sys.stderr)
        return EXIT_CONNECTION
    with client:
        try:
            meta = record(client, args, rec)
        except (P.ConnectionLost, P.DaemonError) as exc:
            print(f"hexacnc record: {exc}", file=sys.stderr)
            if not rec.rows:
                return EXIT_CONNECTION
            meta = {"rate_hz": args.rate, "stop": f"connection lost: {exc}"}
    meta.update({"source": "hexacnc record", "path": str(args.out)})
    r = rec.recording(meta)
    save(args.out, r)
    print(f"recorded {r.n} samples ({meta['stop']}) at {meta['rate_hz']:g} Hz -> {args.out}")
    return 0
