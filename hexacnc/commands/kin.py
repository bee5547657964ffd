"""``hexacnc kin inverse|forward``: kinematics on CSV files.

``L1..L6`` are geometric strut lengths; ``q1..q6`` drive readings, through the
machine's ``[calibration]`` reading-to-length map where it has one
(:mod:`hexacnc.strutmap`; else ``q = L - strut_offset_mm``)."""
from __future__ import annotations

import argparse
import sys

import numpy as np

from ..config import load_config
from ..csvio import format_csv, read_numeric_csv, write_text_atomic
from ..errors import KinematicsError
from ..kinematics import Hexapod
from ..strutmap import strut_map_from_config

HELP = "inverse and forward kinematics on CSV files (poses x,y,z,a,b,c <-> readings q1..q6)"

POSE_COLS = ["x", "y", "z", "a", "b", "c"]
Q_COLS = [f"q{i}" for i in range(1, 7)]
L_COLS = [f"L{i}" for i in range(1, 7)]

#: offline forward kinematics polishes to this strut-length residual (mm)
OFFLINE_TOL_MM = 1e-10


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="kin", metavar="DIRECTION")
    sub.required = True
    inv = sub.add_parser("inverse", help="poses (x,y,z mm, a,b,c deg) -> strut lengths L1..L6 and readings q1..q6")
    inv.add_argument("--config", help="machine description (default: embedded default)")
    inv.add_argument("--poses", required=True, help="CSV with header x,y,z,a,b,c")
    inv.add_argument("--out", default="-", help="output CSV (default: stdout)")
    inv.add_argument("--unchecked", action="store_true",
                     help="do not refuse poses outside strut-length/joint-angle limits")
    inv.set_defaults(_kin=_inverse)
    fwd = sub.add_parser("forward", help="readings q1..q6 (mm) -> pose x,y,z,a,b,c plus iterations")
    fwd.add_argument("--config", help="machine description (default: embedded default)")
    fwd.add_argument("--readings", required=True, help="CSV with header q1..q6")
    fwd.add_argument("--out", default="-", help="output CSV (default: stdout)")
    fwd.add_argument("--unchecked", action="store_true",
                     help="do not refuse solutions outside strut-length/joint-angle limits")
    fwd.set_defaults(_kin=_forward)


def main(args: argparse.Namespace) -> int:
    return args._kin(args)


def _inverse(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    hx = Hexapod(cfg)
    poses, _, ignored = read_numeric_csv(args.poses, POSE_COLS)
    if ignored:
        print(f"hexacnc kin inverse: ignoring column(s) {', '.join(ignored)} of {args.poses}", file=sys.stderr)
    if not args.unchecked:
        bad = np.nonzero(hx.batch_violations(poses))[0]
        for i in bad[:1]:
            raise KinematicsError(f"{args.poses}: data row {i + 1} (line {i + 2}) pose {poses[i].tolist()}: "
                                  + "; ".join(hx.limit_violations(poses[i]))
                                  + f" ({len(bad)} row(s) outside limits; --unchecked computes them anyway)")
    L = hx.inverse_batch(poses)
    # drive readings through the [calibration] reading-to-length map (identity without one)
    q = strut_map_from_config(cfg).drive_from_strut(L) - hx.offset
    rows = np.hstack([L, q])
    write_text_atomic(args.out, format_csv(L_COLS + Q_COLS, rows.tolist()))
    return 0


def _forward(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    hx = Hexapod(cfg)
    q, _, ignored = read_numeric_csv(args.readings, Q_COLS)
    if ignored:
        print(f"hexacnc kin forward: ignoring column(s) {', '.join(ignored)} of {args.readings}", file=sys.stderr)
    out = []
    Lq = strut_map_from_config(cfg).strut_from_drive(q + hx.offset)   # [calibration] map (identity without one)
    for i, qi in enumerate(q):
        res = hx.forward(Lq[i], tol_mm=OFFLINE_TOL_MM, max_iter=max(50, hx.max_iter))
        where = f"{args.readings}: data row {i + 1} (line {i + 2}) readings {qi.tolist()}"
        if res.status != "ok":
            raise KinematicsError(f"{where}: forward kinematics {res.status} after {res.iterations} "
                                  f"iterations (residual {res.residual_mm:.3g} mm, condition {res.condition:.3g})")
        if not args.unchecked:
            v = hx.limit_violations(res.pose)
            if v:
                raise KinematicsError(f"{where}: solution {res.pose.tolist()} " + "; ".join(v))
        out.append(list(res.pose) + [res.iterations, float(res.residual_mm)])
    write_text_atomic(args.out, format_csv(POSE_COLS + ["iterations", "residual_mm"], out))
    return 0

