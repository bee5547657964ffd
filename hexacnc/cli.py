"""The ``hexacnc`` console command: a thin dispatcher over :mod:`hexacnc.commands`."""
from __future__ import annotations

import argparse
import importlib
import sys

from . import __version__
from .errors import HexacncError

#: subcommand -> module (each with HELP, configure(parser), main(args) -> int)
COMMANDS: dict[str, str] = {
    "run": "hexacnc.commands.run",
    "send": "hexacnc.commands.send",
    "status": "hexacnc.commands.status",
    "kin": "hexacnc.commands.kin",
    "plan": "hexacnc.commands.plan",
    "calib": "hexacnc.commands.calib",
    "diagnose": "hexacnc.commands.diagnose",
    "record": "hexacnc.commands.record",
    "health": "hexacnc.commands.health",
    "simulate": "hexacnc.commands.simulate",
    "bench": "hexacnc.commands.bench",
    # operator control (module:object with HELP, configure, main)
    "pause": "hexacnc.commands.machine:PAUSE",
    "resume": "hexacnc.commands.machine:RESUME",
    "stop": "hexacnc.commands.machine:STOP",
    "reset": "hexacnc.commands.machine:RESET",
    "enable": "hexacnc.commands.machine:ENABLE",
    "disable": "hexacnc.commands.machine:DISABLE",
    "take": "hexacnc.commands.machine:TAKE",
    "home": "hexacnc.commands.machine:HOME",
    "feed": "hexacnc.commands.machine:FEED",
    "rapid": "hexacnc.commands.machine:RAPID",
    "optional-stop": "hexacnc.commands.machine:OPTIONAL_STOP",
    "block-delete": "hexacnc.commands.machine:BLOCK_DELETE",
    "mdi": "hexacnc.commands.machine:MDI",
    "jog": "hexacnc.commands.jog",
    "offsets": "hexacnc.commands.offsets:OFFSETS",
    "tools": "hexacnc.commands.offsets:TOOLS",
    "bus": "hexacnc.commands.bus",
    "reload": "hexacnc.commands.reload",
}


def _load(modname: str):
    modname, _, attr = modname.partition(":")
    try:
        mod = importlib.import_module(modname)
        return getattr(mod, attr) if attr else mod
    except ModuleNotFoundError as exc:
        if exc.name == modname:
            return None
        raise


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hexacnc", description=__doc__.split(":")[0] if __doc__ else None)
    parser.add_argument("--version", action="version", version=f"hexacnc {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, modname in COMMANDS.items():
        if only is not None and name != only:
            # cheap placeholder so that `hexacnc --help` lists everything without importing all
            sub.add_parser(name, add_help=False)
            continue
        mod = _load(modname)
        if mod is None:
            continue
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.configure(p)
        p.set_defaults(_main=mod.main)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    first = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(first if first in COMMANDS else None)
    if first not in COMMANDS:
        parser = build_parser()
    args = parser.parse_args(argv)
    try:
        rc = args._main(args)
    except HexacncError as exc:
        print(f"hexacnc {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return 0
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
