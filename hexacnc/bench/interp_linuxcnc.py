"""``hexacnc bench interp --linuxcnc DIR``: compare with LinuxCNC's canonical output.

LinuxCNC's interpreter tests (``DIR/tests/interp/**``) come with ``expected``
files: the canonical calls its ``rs274`` program printed for a test program.
For every test whose ``test.sh`` runs ``rs274`` on a G-code file (plugins and
python tests are left out), the same file is interpreted here and the motion
compared:

* ``STRAIGHT_TRAVERSE`` / ``STRAIGHT_FEED`` end points, ``ARC_FEED`` end points,
  centres and turns within 1e-4 program units (the canonical output prints
  4 decimals), feeds of feed moves (``SET_FEED_RATE`` in force, G94 only),
  ``DWELL`` seconds and ``MESSAGE`` texts (blanks collapsed);
* outcome per test: ``same``, ``unsupported`` (refused with code
  ``unsupported``: the feature is named), ``refused`` (any other refusal),
  ``differ`` (the first difference is reported); ``refused_as_linuxcnc``: refused
  (not ``unsupported``) where LinuxCNC's output also stops without PROGRAM_END.

A test's program runs from pose zero with zero offsets and its ``-t`` tool
table (in inches: the unit of the standalone ``rs274``'s tool table); the
``-i`` INI file's ``[RS274NGC] SUBROUTINE_PATH`` is searched
for subroutine files.  The tool axis is -Z (a tool hangs below the spindle,
as LinuxCNC's tool length offsets assume).
"""
from __future__ import annotations

import math
import re
import shlex
from pathlib import Path

from ..errors import GcodeError
from ..gcode import parse_program
from ..gcode.state import parse_tool_table

TOL = 1e-4
_CALL = re.compile(r"([A-Z_0-9]+)\((.*)\)\s*$")
_NUM = re.compile(r"[-+]?\d+\.?\d*(?:[eE][-+]?\d+)?")


def find_tests(root: Path) -> list[dict]:
    """Tests with an ``expected`` canonical output: {name, dir, ngc, expected, tbl, ini}."""
    base = root / "tests" / "interp"
    out = []
    for sh in sorted(base.rglob("test.sh")):
        d = sh.parent
        exp = d / "expected"
        if not exp.exists():
            continue
        cmd = next((ln for ln in sh.read_text(errors="replace").splitlines()
                    if re.search(r"\brs274\b", ln) and not ln.lstrip().startswith("#")), None)
        if cmd is None:
            continue
        try:
            words = shlex.split(cmd.split("|")[0].replace("!", " ").replace("{", " "))
        except ValueError:
            continue
        words = words[words.index("rs274") + 1:] if "rs274" in words else words
        opts: dict = {}
        ngc = None
        i = 0
        while i < len(words):
            w = words[i]
            if w in ("-t", "-i", "-p", "-n", "-b", "-s", "-T"):
                opts[w] = words[i + 1] if i + 1 < len(words) else ""
                i += 2
                continue
            if not w.startswith("-") and not w.startswith("2>") and not w.startswith(">"):
                ngc = w
            i += 1
        if "-p" in opts or ngc is None or not (d / ngc).exists():
            continue
        out.append({"name": str(d.relative_to(base)), "dir": d, "ngc": d / ngc, "expected": exp,
                    "tbl": d / opts["-t"] if "-t" in opts else None,
                    "ini": d / opts["-i"] if "-i" in opts else None,
                    "messages_only": "/MESSAGE/" in cmd})   # the test keeps only the MESSAGE lines
    good = base / "good"
    for ngc in sorted(good.glob("*.ngc")) if good.is_dir() else []:
        exp = ngc.with_name(ngc.name + ".expected")
        if exp.exists():
            out.append({"name": f"good/{ngc.name}", "dir": good, "ngc": ngc, "expected": exp,
                        "tbl": None, "ini": None})
    return out


def parse_expected(text: str) -> list[tuple]:
    """Canonical calls -> events in machine mm (and deg).

    ('T'|'F', pose6, unit_mm, feed_mm_s), ('A', end6, unit_mm, centre, rotation, feed_mm_s),
    ('D', seconds), ('M', text); program coordinates are mapped through the G5x, G92 and
    XY-rotation calls in force; zero-length moves are dropped (hexacnc emits no block for them).
    """
    u = 1.0
    feed = 0.0
    plane = "XY"
    ev: list[tuple] = []
    g5x = [0.0] * 6
    g92 = [0.0] * 6
    rot = 0.0
    last = [0.0] * 6

    def machine(prog):   # canonical (program) coordinates -> machine: g5x + R(rot) (prog + g92)
        p = [prog[i] + g92[i] for i in range(6)]
        c, s = math.cos(math.radians(rot)), math.sin(math.radians(rot))
        p[0], p[1] = c * p[0] - s * p[1], s * p[0] + c * p[1]
        return [p[i] + g5x[i] for i in range(6)]

    for raw in text.splitlines():
        s = re.sub(r"^\s*\d*\s*N[.\d]*\s*", "", raw).strip()
        m = _CALL.match(s)
        if not m:
            continue
        name, args = m.group(1), m.group(2)
        if name == "SET_G5X_OFFSET":
            v = [float(x) for x in _NUM.findall(args)]
            g5x = [v[1] * u, v[2] * u, v[3] * u] + v[4:7]
        elif name == "SET_G92_OFFSET":
            v = [float(x) for x in _NUM.findall(args)]
            g92 = [v[0] * u, v[1] * u, v[2] * u] + v[3:6]
        elif name == "SET_XY_ROTATION":
            rot = float(args)
        elif name == "USE_LENGTH_UNITS":
            u = 25.4 if "INCHES" in args else (10.0 if "CM" in args else 1.0)
        elif name == "SELECT_PLANE":
            plane = args.replace("CANON_PLANE_", "").strip()
        elif name == "SET_FEED_RATE":
            feed = float(args)
        elif name in ("STRAIGHT_TRAVERSE", "STRAIGHT_FEED", "STRAIGHT_PROBE"):
            v = [float(x) for x in _NUM.findall(args)][:6]
            pose = machine([v[0] * u, v[1] * u, v[2] * u] + v[3:6])
            if max(abs(a - b) for a, b in zip(pose, last)) < TOL * u:   # (4-decimal output, rotated)
                continue       # LinuxCNC emits zero-length moves; hexacnc emits no block for them
            last = pose
            ev.append(("T" if name == "STRAIGHT_TRAVERSE" else "F", pose, u, feed * u / 60.0))
        elif name == "ARC_FEED":
            v = [float(x) for x in _NUM.findall(args)]
            e1, e2, c1, c2, rot_, ax = v[0] * u, v[1] * u, v[2] * u, v[3] * u, int(v[4]), v[5] * u
            if plane == "XZ":      # first axis Z, second X, axis Y
                end, cen = [e2, ax, e1], (c2, None, c1)
            elif plane == "YZ":    # first Y, second Z, axis X
                end, cen = [ax, e1, e2], (None, c1, c2)
            else:
                end, cen = [e1, e2, ax], (c1, c2, None)
            end = machine(end + v[6:9])
            full = [e if c is None else c for e, c in zip(end[:3], cen)]
            cm = machine(full + [0.0] * 3)
            cen = tuple(None if c is None else cm[i] for i, c in enumerate(cen))
            last = end
            ev.append(("A", end, u, cen, rot_, feed * u / 60.0))
        elif name == "DWELL":
            ev.append(("D", float(args)))
        elif name == "MESSAGE":
            ev.append(("M", _norm(args.strip()[1:-1] if args.strip().startswith('"') else args)))
    return ev


def _norm(t: str) -> str:
    return " ".join(t.split())


def program_events(prog) -> list[tuple]:
    ev: list[tuple] = []
    for b in prog.blocks:
        if b.kind in ("rapid", "line", "probe"):
            ev.append(("T" if b.kind == "rapid" else "F", [float(x) for x in b.end], None,
                       b.feed_mm_s if b.inverse_time_s is None and b.feed_deg_s is None else None))
        elif b.kind == "arc":
            n = [float(x) for x in b.normal]
            w = max(range(3), key=lambda i: abs(n[i]))
            cen = [float(x) for x in b.center]
            cen[w] = None
            rot = (b.turns + 1) * (-1 if b.clockwise else 1)
            ev.append(("A", [float(x) for x in b.end], None, tuple(cen), rot,
                       b.feed_mm_s if b.inverse_time_s is None else None))
        elif b.kind == "dwell":
            ev.append(("D", b.seconds))
    return ev


def _close(a, b, u) -> bool:
    return all(x is None or y is None or abs(x - y) <= TOL * u + 1e-9 for x, y in zip(a, b))


def compare(expected: list[tuple], got: list[tuple], messages: list[str]) -> str | None:
    """None when the same, else the first difference in words."""
    exp_motion = [e for e in expected if e[0] != "M"]
    exp_msgs = [e[1] for e in expected if e[0] == "M"]
    for i, (e, g) in enumerate(zip(exp_motion, got)):
        if e[0] != g[0]:
            return f"event {i}: LinuxCNC {e[0]} {e[1:]}, hexacnc {g[0]} {g[1:]}"
        if e[0] == "D":
            if abs(e[1] - g[1]) > 1e-6:
                return f"event {i}: dwell {e[1]} vs {g[1]}"
            continue
        u = e[2]   # 1e-4 program units
        if not _close(e[1], g[1], u):
            return f"event {i} ({e[0]}): end {[round(x, 4) for x in e[1]]} vs {[round(x, 4) for x in g[1]]}"
        if e[0] == "A":
            if not _close(e[3], g[3], u) or e[4] != g[4]:
                return f"event {i} (arc): centre/turns {e[3]} {e[4]} vs {g[3]} {g[4]}"
        if e[0] != "T" and g[-1] is not None and abs(e[-1] - g[-1]) > 1e-6 * max(1.0, e[-1]):
            return f"event {i} ({e[0]}): feed {e[-1] * 60:g} vs {g[-1] * 60:g} mm/min"
    if len(exp_motion) != len(got):
        return f"{len(exp_motion)} LinuxCNC events, {len(got)} hexacnc events"
    mine = [_norm(m) for m in messages]
    if exp_msgs != mine:
        for a, b in zip(exp_msgs, mine + [None] * len(exp_msgs)):
            if a != b:
                return f"message {a!r} vs {b!r}"
        return f"messages: {len(exp_msgs)} LinuxCNC, {len(mine)} hexacnc"
    return None


def _ini_subpath(ini: Path | None, base: Path) -> list[str]:
    if ini is None or not ini.exists():
        return [str(base)]
    m = re.search(r"(?im)^\s*SUBROUTINE_PATH\s*=\s*(.+)$", ini.read_text(errors="replace"))
    paths = [str(base)]
    if m:
        paths += [str((base / p.strip()).resolve()) for p in m.group(1).split(":") if p.strip()]
    return paths


def run_test(t: dict) -> dict:
    text = t["ngc"].read_text(errors="replace")
    exp = parse_expected(t["expected"].read_text(errors="replace"))
    tools = parse_tool_table(t["tbl"].read_text(errors="replace")) if t["tbl"] else None
    for e in (tools or {}).values():     # rs274 (standalone) reads its tool table in inches
        e.z_offset_mm, e.x_offset_mm, e.y_offset_mm = e.z_offset_mm * 25.4, e.x_offset_mm * 25.4, e.y_offset_mm * 25.4
        e.diameter_mm *= 25.4
    try:
        prog = parse_program(text, t["ngc"].name, tool_table=tools, tool_axis_platform=(0.0, 0.0, -1.0),
                             subroutine_path=_ini_subpath(t["ini"], t["dir"]))
    except GcodeError as exc:
        where = {"line": exc.line, "column": exc.column, "code": exc.code, "message": exc.bare_message}
        if exc.code == "abort":
            msgs = [e[1] for e in exp if e[0] == "M"]
            raw = t["expected"].read_text(errors="replace")
            if _norm(exc.bare_message) in _norm(raw) or _norm(exc.bare_message) in msgs:
                return {"outcome": "same", "aborted": where}
        if exc.code != "unsupported" and "PROGRAM_END()" not in t["expected"].read_text(errors="replace"):
            return {"outcome": "refused_as_linuxcnc", "error": where}   # LinuxCNC stopped with an error too
        return {"outcome": "unsupported" if exc.code == "unsupported" else "refused", "error": where}
    msgs = [text for kind, _ln, text in prog.notes if kind in ("msg", "debug")]
    if t.get("messages_only"):
        exp = [e for e in exp if e[0] == "M"]
    diff = compare(exp, [] if t.get("messages_only") else program_events(prog), msgs)
    return {"outcome": "same"} if diff is None else {"outcome": "differ", "difference": diff}


def run_all(root: Path) -> dict:
    tests = find_tests(root)
    res = {}
    counts = {"same": 0, "refused_as_linuxcnc": 0, "unsupported": 0, "refused": 0, "differ": 0}
    for t in tests:
        r = run_test(t)
        counts[r["outcome"]] += 1
        res[t["name"]] = r
    ran = sum(counts.values())
    return {"linuxcnc": str(root), "tests": ran, "counts": counts,
            "same_fraction": round(counts["same"] / ran, 3) if ran else None,
            "tolerance_program_units": TOL, "results": res}
