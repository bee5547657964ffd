"""``hexacnc health``: is the machine model still right?  From a recording or the live daemon.

Reads a recording of ``hexacnc record`` (``--recording``) or records ``--duration``
seconds from the running daemon (``--live``), then separates the following-error
and torque patterns by cause (:mod:`hexacnc.calib.health`): payload changed (sag
model wrong, with a proposed ``[carrier]`` update and its effect on sag), thermal
growth not compensated, one strut's friction or stiffness changed.  Prints the
status and the warnings; ``--json`` writes the whole report (atomically).
Exit 0 (status ok or warning), 2 on bad input, 6 when the daemon cannot be reached.
"""
from __future__ import annotations

import argparse
import sys
import types

from ..errors import DataError
from .send import EXIT_CONNECTION, add_connection_args

HELP = "model health from a recording or the live daemon: payload, thermal, friction and stiffness drift"


def configure(p: argparse.ArgumentParser) -> None:
    add_connection_args(p)   # --config is also the machine description the model is checked against
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--recording", help="recording of hexacnc record (.npz or .csv)")
    src.add_argument("--live", action="store_true", help="record from the running daemon first")
    p.add_argument("--duration", type=float, default=60.0, help="--live: seconds to record (default 60)")
    p.add_argument("--rate", type=float, default=50.0, help="--live: samples per second (default 50)")
    p.add_argument("--reference", help="recording of the healthy machine (no payload): the tare for the torque "
                                       "offsets and the reference for friction and stiffness")
    p.add_argument("--force-per-permille", type=float, default=10.0, metavar="N",
                   help="strut force per per-mille of rated drive torque (N; screw lead, gear and rated torque)")
    p.add_argument("--friction-n", type=float, default=20.0,
                   help="static friction left at rest (N), part of the torque noise model")
    p.add_argument("--noise-permille", type=float, default=1.0, help="torque reading noise (per mille, 1 sigma)")
    p.add_argument("--assumed-payload-kg", type=float, default=None,
                   help="payload the sag model assumes (default: the recording's payload_kg, else 0)")
    p.add_argument("--json", help="write the report as JSON (atomic)")


def main(args: argparse.Namespace) -> int:
    from ..calib.health import analyse
    from ..calib.output import write_json
    from ..calib.payload import DriveTorqueModel
    from ..calib.recording import load
    from ..config import load_config
    for nm in ("force_per_permille", "noise_permille"):
        if not getattr(args, nm) > 0:
            raise DataError(f"--{nm.replace('_', '-')} must be positive, got {getattr(args, nm)}")
    if args.friction_n < 0:
        raise DataError(f"--friction-n must be >= 0, got {args.friction_n}")
    cfg = load_config(args.config)
    if args.live:
        rec = _live(args)
        if rec is None:
            return EXIT_CONNECTION
    else:
        rec = load(args.recording)
        rec.meta.setdefault("path", args.recording)
    ref = None
    if args.reference:
        ref = load(args.reference)
        ref.meta.setdefault("path", args.reference)
    model = DriveTorqueModel(args.force_per_permille, args.noise_permille, args.friction_n)
    rep = analyse(cfg, rec, model, ref, args.assumed_payload_kg)
    if args.json:
        write_json(args.json, rep)
    print(f"status: {rep['status']}")
    for w in rep["warnings"]:
        print(f"  warning: {w}")
    p = rep["payload"]
    pm = p.get("in_motion") or {}
    if pm.get("available"):
        print(f"  payload in motion: {pm['mass_kg']:.2f} +- {pm['mass_std_kg']:.2f} kg from {pm['samples']} samples "
              "(drive torque TPDO3)")
    if p.get("available"):
        print(f"  payload: {p['mass_kg']:.2f} +- {p['mass_std_kg']:.2f} kg (model assumes {p['assumed_kg']:g} kg)")
        if "proposed_update" in p:
            print("  proposed:\n" + "".join("    " + ln + "\n" for ln in p["proposed_update"]["toml"].splitlines()))
    sys.stdout.flush()
    return 0


def _live(args):
    from ..calib.recorder import Recorder, Trigger
    from ..daemon import protocol as P
    from .record import record
    from .send import connect
    if not 0.1 <= args.rate <= 1000.0 or not args.duration > 0:
        raise DataError("--rate must be within 0.1..1000 Hz and --duration positive")
    rec = Recorder(Trigger("none"), int(args.rate * args.duration) + 1)
    try:
        client = connect(args, "hexacnc health")
    except (P.ConnectionLost, P.DaemonError) as exc:
        print(f"hexacnc health: {exc}", file=sys.stderr)
        return None
    with client:
        ns = types.SimpleNamespace(rate=args.rate, duration=args.duration, timeout=args.duration + 10.0)
        meta = record(client, ns, rec)
    meta["source"] = "hexacnc health --live"
    return rec.recording(meta)
