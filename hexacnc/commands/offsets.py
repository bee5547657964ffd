"""``hexacnc offsets`` and ``hexacnc tools``: show and edit the persistent work offsets and tool table.

    hexacnc offsets                          # G54..G59.3, G92, G28, G30, active system, tool
    hexacnc offsets G55 x=10 y=-20.5 z=-1180 # set axes of a system (mm, deg); also G92, G28, G30
    hexacnc offsets --select G55             # make G55 the active system
    hexacnc tools                            # the tool table (LinuxCNC tool.tbl beside the config)
    hexacnc tools 3 z=42.5 d=6 p=3 comment="6 mm drill"
    hexacnc tools 3 --delete

Edits are refused while a program runs; they are written atomically at once and survive
programs and daemon restarts.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

from .machine import EXIT_LOCAL, EXIT_OK, add_common, print_reply, run_op

_AXES = "xyzabc"


def _pairs(items: list[str], allowed: dict[str, str], what: str) -> dict:
    out = {}
    for it in items:
        k, sep, v = it.partition("=")
        k = k.strip().lower()
        if not sep or k not in allowed:
            raise ValueError(f"{what}: {it!r} is not KEY=VALUE with KEY one of {', '.join(allowed)}")
        out[allowed[k]] = v
    return out


def _numbers(raw: dict, what: str, ints=(), texts=()) -> dict:
    """The values of KEY=VALUE pairs as numbers (``ints`` as integers, ``texts`` kept), naming a bad one."""
    out = {}
    for k, v in raw.items():
        if k in texts:
            out[k] = v
            continue
        try:
            out[k] = int(v) if k in ints else float(v)
        except ValueError:
            raise ValueError(f"{what}: {k} = {v!r} is not {'an integer' if k in ints else 'a number'}") from None
    return out


def _fmt_offsets(r: dict) -> str:
    names = ["G54", "G55", "G56", "G57", "G58", "G59", "G59.1", "G59.2", "G59.3", "G92", "G28", "G30"]
    lines = [f"{'':6} {'x':>10} {'y':>10} {'z':>10} {'a':>8} {'b':>8} {'c':>8}"]
    for n in names:
        v = r.get(n) or [0.0] * 6
        mark = "*" if r.get("active") == n else " "
        lines.append(f"{n:<5}{mark} " + " ".join(f"{x:10.3f}" for x in v[:3]) + " "
                     + " ".join(f"{x:8.3f}" for x in v[3:6]))
    lines.append(f"active {r.get('active')}  tool T{r.get('tool')} length {r.get('tool_length_mm', 0.0):.3f} mm")
    return "\n".join(lines)


@dataclass
class OffsetsCmd:
    HELP: str = "show or edit the work offsets (G54..G59.3, G92, G28, G30): persistent"

    def configure(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("system", nargs="?", help="G54..G59.3, G92, G28 or G30 to edit")
        parser.add_argument("values", nargs="*", help="AXIS=VALUE (x y z mm, a b c deg)")
        parser.add_argument("--select", metavar="G5x", help="make this system active")
        add_common(parser)

    def main(self, args: argparse.Namespace) -> int:
        try:
            vals = _numbers(_pairs(args.values, {a: a for a in _AXES}, "offsets"), "offsets")
        except ValueError as exc:
            print(f"hexacnc offsets: {exc}", file=sys.stderr)
            return EXIT_LOCAL
        if (vals and not args.system) or (args.system and "=" in args.system):
            print("hexacnc offsets: name the system to edit (e.g. G55 x=10)", file=sys.stderr)
            return EXIT_LOCAL
        fields = {}
        if args.system:
            fields.update(system=args.system.upper(), values=vals)
        if args.select:
            fields["select"] = args.select.upper()

        def body(client) -> int:
            r = client.call("offsets", **fields)
            print_reply(args, r, _fmt_offsets(r))
            return EXIT_OK
        return run_op(args, "offsets", body)


@dataclass
class ToolsCmd:
    HELP: str = "show or edit the tool table (LinuxCNC tool.tbl format): persistent"

    def configure(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("tool", nargs="?", type=int, help="tool number to add or edit")
        parser.add_argument("values", nargs="*", help="z=LENGTH_MM d=DIAMETER_MM p=POCKET comment=TEXT")
        parser.add_argument("--delete", action="store_true", help="remove the tool")
        add_common(parser)

    def main(self, args: argparse.Namespace) -> int:
        keys = {"z": "z_mm", "d": "diameter_mm", "p": "pocket", "comment": "comment"}
        try:
            fields = _numbers(_pairs(args.values, keys, "tools"), "tools", ints=("pocket",), texts=("comment",))
        except ValueError as exc:
            print(f"hexacnc tools: {exc}", file=sys.stderr)
            return EXIT_LOCAL
        if args.tool is None and (fields or args.delete):
            print("hexacnc tools: name the tool to edit or delete (e.g. hexacnc tools 3 z=95.5)", file=sys.stderr)
            return EXIT_LOCAL
        if args.tool is not None:
            fields["tool"] = args.tool
            if args.delete:
                fields["delete"] = True

        def body(client) -> int:
            r = client.call("tools", **fields)
            lines = [f"{'T':>5} {'P':>5} {'Z mm':>10} {'D mm':>8}  comment"]
            for e in r.get("tools", []):
                mark = "*" if e["tool"] == r.get("tool_in_spindle") else " "
                lines.append(f"{e['tool']:>5}{mark}{e['pocket']:>5} {e['z_mm']:10.3f} {e['diameter_mm']:8.3f}  "
                             f"{e['comment']}")
            lines.append(f"file {r.get('file')}")
            print_reply(args, r, "\n".join(lines))
            return EXIT_OK
        return run_op(args, "tools", body)


OFFSETS = OffsetsCmd()
TOOLS = ToolsCmd()
