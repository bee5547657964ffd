"""``hexacnc bus scan``: list every node on the drive bus(es) and whether it matches the config.
``hexacnc bus load``: the worst-case bus time per cycle of the layout, and the layouts that fit.
``hexacnc bus demand``: the bus demand per cycle over simulated seconds (median, p99), as configured
and with the former uniform timers.

The commissioning command to run first: SDO reads only (no NMT command, nothing enabled). With
``[bus] simulate`` the simulated drives are started for the scan (in-process on ``virtual``, as a
process on udp_multicast/socketcan). Exit code 0 when every configured node is found and matches its
description and ``[bus] nodes``, 1 when not, 2 on an error (bus cannot be opened, bad config).
"""
from __future__ import annotations

import argparse
import json
import sys

HELP = ("drive bus commissioning: 'bus scan' lists every node found and whether it matches the config; "
        "'bus load' / 'bus demand' the bus budget")


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bus_command", metavar="SUBCOMMAND")
    sub.required = True
    p = sub.add_parser("scan", help="list the nodes on the bus: identity, device type, modes, versions, "
                                    "heartbeat, match with the config")
    p.add_argument("--config", metavar="F", help="machine description (TOML); default: the embedded default")
    p.add_argument("--channel", help="override [bus] channel")
    p.add_argument("--listen-s", type=float, default=0.5, metavar="S", help="time to collect answers (default 0.5)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p = sub.add_parser("load", help="worst-case bus time per cycle of the layout and the layouts that fit (JSON); "
                                    "exit 1 when over [bus] max_load")
    p.add_argument("--config", metavar="F", help="machine description (TOML); default: the embedded default")
    p.add_argument("--period-s", type=float, metavar="P", help="cycle period (default [cycle] period_s)")
    p = sub.add_parser("demand", help="bus demand per cycle over simulated seconds: median, p99, max (JSON)")
    p.add_argument("--config", metavar="F", help="machine description (TOML); default: the embedded default")
    p.add_argument("--seconds", type=float, default=10.0, metavar="S", help="simulated seconds (default 10)")
    p.add_argument("--torque-sdo-ms", type=float, default=0.0, metavar="MS",
                   help="also with the hot loop's torque sampling: one SDO upload every MS over all drives "
                        "(hexacnc.daemon.torqueread: 8 at rest, 250 in motion); default 0: without")
    p.add_argument("--torque-pdo-every", type=int, default=0, metavar="N",
                   help="also with the drives' torque TPDO3 every N SYNCs (1..240; drivers/torquepdo.py, "
                        "[bus] torque_pdo_every); default 0: without")


def _with_simulation(cfg, channel, fn):
    """Run ``fn(buses)`` with the simulated drives present when ``[bus] simulate``."""
    from drivers.canbus import open_buses

    from ..sim import drives as simdrives

    buses = open_buses(cfg.bus, channel=channel)
    sim = proc = sim_buses = None
    try:
        if cfg.bus.simulate and cfg.bus.interface == "virtual":
            sim_buses = open_buses(cfg.bus, channel=channel)
            sim = simdrives.sim_drives(cfg, sim_buses).start()
        elif cfg.bus.simulate:
            proc = simdrives.spawn(cfg.path, interface=cfg.bus.interface, channel=channel or cfg.bus.channel)
        return fn(buses)
    finally:
        if sim is not None:
            sim.stop()
        if proc is not None:
            proc.terminate()
            proc.wait(5)
        for b in buses + (sim_buses or []):
            b.shutdown()


def _load(args: argparse.Namespace) -> int:
    from drivers.busload import load_report

    from ..config import load_config
    from ..errors import HexacncError

    try:
        cfg = load_config(args.config)
        period = args.period_s if args.period_s is not None else cfg.cycle.period_s
        if not 1e-5 <= period <= 1.0:
            raise HexacncError(f"--period-s {period} must be 1e-05..1")
        rep = load_report(cfg.bus, period)
    except HexacncError as exc:
        print(f"hexacnc bus load: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(rep, indent=1))
    return 0 if rep["fits"] else 1


def _demand(args: argparse.Namespace) -> int:
    from drivers.busdemand import demand_report
    from drivers.description import bus_period_s

    from ..config import load_config
    from ..errors import HexacncError

    if not 0.01 <= args.seconds <= 600:
        print(f"hexacnc bus demand: --seconds {args.seconds} must be 0.01..600", file=sys.stderr)
        return 2
    if not (args.torque_sdo_ms == 0 or 0.5 <= args.torque_sdo_ms <= 60000):
        print(f"hexacnc bus demand: --torque-sdo-ms {args.torque_sdo_ms} must be 0 or 0.5..60000", file=sys.stderr)
        return 2
    if not 0 <= args.torque_pdo_every <= 240:
        print(f"hexacnc bus demand: --torque-pdo-every {args.torque_pdo_every} must be 0..240", file=sys.stderr)
        return 2
    try:
        cfg = load_config(args.config)
        out = demand_report(cfg.bus, bus_period_s(cfg.bus, cfg.cycle.period_s), args.seconds,
                            sdo_gap_s=args.torque_sdo_ms * 1e-3, torque_pdo_every=args.torque_pdo_every)
    except HexacncError as exc:
        print(f"hexacnc bus demand: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(out, indent=1))
    return 0


def main(args: argparse.Namespace) -> int:
    if args.bus_command == "load":
        return _load(args)
    if args.bus_command == "demand":
        return _demand(args)
    return _scan(args)


def _scan(args: argparse.Namespace) -> int:
    from drivers.scan import format_scan, scan

    from ..config import load_config
    from ..errors import HexacncError

    if not 0.05 <= args.listen_s <= 60:
        print(f"hexacnc bus scan: --listen-s {args.listen_s} must be 0.05..60", file=sys.stderr)
        return 2
    try:
        cfg = load_config(args.config)
        result = _with_simulation(cfg, args.channel, lambda buses: scan(buses, cfg.bus, listen_s=args.listen_s))
    except HexacncError as exc:
        print(f"hexacnc bus scan: {exc}", file=sys.stderr)
        return 2
    if cfg.bus.simulate:
        result["simulated"] = cfg.bus.simulate_profile
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        if cfg.bus.simulate:
            print(f"(simulated drives, profile {cfg.bus.simulate_profile!r}: [bus] simulate = true)")
        print(format_scan(result))
    return 0 if result["all_match"] else 1
