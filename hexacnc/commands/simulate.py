"""``hexacnc simulate thermal|dynamics|controller``: the machine simulator, JSON figures and PNG plots."""
from __future__ import annotations

import argparse
import json
import os
import sys

from ..config import load_config
from ..errors import DataError

HELP = "simulate thermal drift and its compensation, strut/carrier dynamics, controller structures"


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="sim", metavar="WHAT")
    sub.required = True

    def common(p):
        p.add_argument("--config", help="machine description (default: embedded default)")
        p.add_argument("--out", default="sim-out", help="output directory for JSON and PNG (default: sim-out)")
        p.add_argument("--no-plot", action="store_true", help="write the JSON only")

    th = sub.add_parser("thermal", help="thermal drift from cold with and without compensation (figure 6)")
    common(th)
    th.add_argument("--hours", type=float, default=2.5, help="machine time (default 2.5)")
    th.add_argument("--rate-hz", type=float, default=10.0, help="observer rate, as in the daemon (default 10)")
    th.add_argument("--heat", type=float, default=None,
                    help="true heat per strut speed, W per mm/s (default: calibrate to --target-um)")
    th.add_argument("--target-um", type=float, default=45.0, help="uncompensated peak z drift to calibrate to")
    th.add_argument("--model-error", type=float, default=1.15,
                    help="true heat input / the observer's modelled heat input (default 1.15)")
    th.add_argument("--seed", type=int, default=1)
    th.add_argument("--source", choices=("auto", "planner", "exact-stop"), default="auto",
                    help="strut speed profile: look-ahead planner (auto: if available) or exact-stop profile")
    th.set_defaults(_sim=_thermal)

    dy = sub.add_parser("dynamics", help="eigenfrequencies over the workspace, path simulation along a program")
    common(dy)
    dy.add_argument("--lines", type=int, default=1000, help="lines of the synthetic program (default 1000)")
    dy.add_argument("--grid", type=int, default=5, help="grid points per axis x, y, z (default 5)")
    dy.add_argument("--seed", type=int, default=1)
    dy.add_argument("--source", choices=("auto", "planner", "exact-stop"), default="auto",
                    help="strut commands: look-ahead planner (auto: if available) or exact-stop profile")
    dy.add_argument("--no-ringdown", action="store_true", help="skip the nonlinear ring-down check")
    dy.set_defaults(_sim=_dynamics)

    dt = sub.add_parser("daemon-thermal", help="thermal drift with/without compensation on the running daemon "
                                               "(simulated drives and thermal plant, accelerated)")
    common(dt)
    dt.add_argument("--hours", type=float, default=2.5, help="plant time (default 2.5)")
    dt.add_argument("--scale", type=float, default=300.0, help="plant seconds per wall second (default 300)")
    dt.add_argument("--rate-hz", type=float, default=2.0, help="probe readings per wall second (default 2)")
    dt.add_argument("--lines", type=int, default=300, help="lines of the synthetic program (default 300)")
    dt.add_argument("--seed", type=int, default=1)
    dt.set_defaults(_sim=_daemon_thermal)

    co = sub.add_parser("controller", help="cascade vs coupled state controller, step at the worst position (figure 7)")
    common(co)
    co.add_argument("--step-um", type=float, default=50.0, help="tool step along z (default 50 um)")
    co.add_argument("--grid", type=int, default=5, help="grid points per axis for the worst position")
    co.set_defaults(_sim=_controller)


def main(args: argparse.Namespace) -> int:
    return args._sim(args)


def _outdir(args) -> str:
    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as exc:
        raise DataError(f"--out {args.out}: cannot create the output directory: {exc.strerror or exc}") from exc
    return args.out


def _public(res: dict) -> dict:
    return {k: v for k, v in res.items() if not k.startswith("_")}


def _positive(name: str, v: float) -> None:
    if not (v > 0 and v == v and v != float("inf")):
        raise DataError(f"{name} must be a positive number, got {v!r}")


def _thermal(args) -> int:
    from ..sim import report
    _positive("--hours", args.hours)
    _positive("--rate-hz", args.rate_hz)
    _positive("--model-error", args.model_error)
    if args.heat is not None and not args.heat >= 0:
        raise DataError(f"--heat must be >= 0, got {args.heat!r}")
    cfg = load_config(args.config)
    out = _outdir(args)
    res = report.run_thermal(cfg, duration_s=args.hours * 3600.0, dt_s=1.0 / args.rate_hz,
                             heat_per_speed_W_s_mm=args.heat, target_drift_um=args.target_um,
                             truth_heat_ratio=args.model_error, seed=args.seed, trajectory_source=args.source)
    report.write_json(res, os.path.join(out, "thermal.json"))
    if not args.no_plot:
        report.plot_thermal(res, os.path.join(out, "thermal.png"))
    summary = {k: v for k, v in res.items() if k != "series"}
    json.dump(summary, sys.stdout, indent=1)
    print()
    return 0


def _dynamics(args) -> int:
    from ..sim import report
    if args.lines < 2:
        raise DataError(f"--lines must be at least 2, got {args.lines}")
    if args.grid < 2:
        raise DataError(f"--grid must be at least 2, got {args.grid}")
    cfg = load_config(args.config)
    out = _outdir(args)
    res = report.run_dynamics(cfg, lines=args.lines, n_grid=args.grid, seed=args.seed,
                              ringdown_check=not args.no_ringdown, source=args.source)
    report.write_json({**_public(res), "series": res["_series"]}, os.path.join(out, "dynamics.json"))
    tmp = os.path.join(out, "program.ngc.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(res["_gcode"])
    os.replace(tmp, os.path.join(out, "program.ngc"))
    if not args.no_plot:
        report.plot_dynamics(res, os.path.join(out, "dynamics_eigen.png"), os.path.join(out, "dynamics_path.png"))
    pub = _public(res)
    pub["eigen"] = {k: v for k, v in pub["eigen"].items() if not isinstance(v, list) or len(v) <= 12}
    json.dump(pub, sys.stdout, indent=1)
    print()
    return 0


def _controller(args) -> int:
    from ..sim import report
    _positive("--step-um", args.step_um)
    cfg = load_config(args.config)
    out = _outdir(args)
    res = report.run_controller(cfg, step_um=args.step_um, n_grid=args.grid)
    report.write_json({**_public(res), "series": res["_series"]}, os.path.join(out, "controller.json"))
    if not args.no_plot:
        report.plot_controller(res, os.path.join(out, "controller.png"))
    json.dump(_public(res), sys.stdout, indent=1)
    print()
    return 0


def _daemon_thermal(args) -> int:
    from ..daemon import thermalrun as daemonthermal
    from ..sim import report
    _positive("--hours", args.hours)
    _positive("--rate-hz", args.rate_hz)
    if not (1.0 <= args.scale <= 1e5):
        raise DataError(f"--scale must be in [1, 100000], got {args.scale!r}")
    if args.lines < 2:
        raise DataError(f"--lines must be at least 2, got {args.lines}")
    cfg = load_config(args.config)
    out = _outdir(args)
    res = daemonthermal.run(cfg, hours=args.hours, scale=args.scale, rate_hz=args.rate_hz, lines=args.lines,
                            seed=args.seed)
    report.write_json(res, os.path.join(out, "daemon_thermal.json"))
    if not args.no_plot:
        daemonthermal.plot(res, os.path.join(out, "daemon_thermal.png"))
    json.dump({k: v for k, v in res.items() if k != "series"}, sys.stdout, indent=1)
    print()
    return 0
