"""``hexacnc bench NAME``: benchmarks that print one JSON object of measured figures."""
from __future__ import annotations

import argparse
import importlib

HELP = "run a benchmark and print its figures as JSON"

#: benchmark name -> module in hexacnc.bench (HELP, configure(parser), main(args) -> int)
BENCHES: dict[str, str] = {
    "model": "hexacnc.bench.model",
    "loop": "hexacnc.bench.loop",
    "interp": "hexacnc.bench.interp",
    "plan": "hexacnc.bench.plan",
    "calib": "hexacnc.bench.calib",
    "diagnose": "hexacnc.bench.diagnose",
    "simulate": "hexacnc.bench.simulate",
    "hold": "hexacnc.bench.hold",
    "arch": "hexacnc.bench.arch",
    "operator": "hexacnc.bench.operator",
    "homing": "hexacnc.bench.homing",
    "calib-cycle": "hexacnc.bench.calibcycle",
    "faults": "hexacnc.bench.faults",
    "stream": "hexacnc.bench.stream",
    "estimate": "hexacnc.bench.estimate",
}


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bench", metavar="NAME")
    sub.required = True
    for name, modname in BENCHES.items():
        try:
            mod = importlib.import_module(modname)
        except ModuleNotFoundError as exc:
            if exc.name == modname:
                continue
            raise
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.configure(p)
        p.set_defaults(_bench_main=mod.main)


def main(args: argparse.Namespace) -> int:
    return args._bench_main(args)
