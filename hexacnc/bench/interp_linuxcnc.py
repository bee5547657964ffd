"""``hexacnc bench interp --linuxcnc DIR``: compare with LinuxCNC's canonical output.

LinuxCNC's interpreter tests (``DIR/tests/interp/**``) come with ``expected``
files: the canonical calls its ``rs274`` program printed for a test program.
For every test whose ``test.sh`` runs ``rs274`` on a G-code file (plugins and
python tests are left out), the same file is interpreted here and the motion
compared:

* ``STRAIGHT_TRAVERSE`` / ``STRAIGHT_FEED`` end points, ``ARC_FEED`` end points,
  centres and turns within 1e-4 program units (the canonical output prints
  4 decimals), feeds of feed moves (``SET_FEED_RATE`` in force; G93 straight moves as
  length / time, as LinuxCNC prints them; G93 arcs are not compared),
  ``DWELL`` seconds and ``MESSAGE`` texts (blanks collapsed);
* each ``rs274`` command of a test.sh is one run, compared with its part of
  ``expected`` (the parts start at SET_FEED_REFERENCE); PRINT lines too (the
  output's lines that are no canonical call; a test's ``awk '{$1=""}'`` applied);
* outcome per run: where LinuxCNC runs to its end (PROGRAM_END or FINISH, and
  test.sh does not expect a failure with ``!``): ``same``, ``differ`` (the first
  difference is reported), ``unsupported`` (refused with code ``unsupported``:
  the feature is named), ``refused`` (any other refusal); where LinuxCNC stops
  with an error: ``refused_as_linuxcnc``, ``unsupported_where_linuxcnc_stops``
  or ``accepted``; a test is ``same``
  when each of its runs is same or refused as LinuxCNC, else its worst run;
* left out, with the reason: tests without ``expected``, interpreter plug-ins
  (``-p``), embedded Python (``[PYTHON]`` in the INI), program names computed by
  the shell; tests with an ``xfail`` file are reported apart, not counted.

A run's program starts at pose zero with zero offsets, its ``-t`` tool table
(else rs274's default ``configs/sim/sim.tbl``; in inches, as rs274 reads it),
its ``-v`` parameter file and ``machine_units="inch"`` (the standalone rs274
is an inch machine unless the INI's ``[TRAJ] LINEAR_UNITS`` is mm); the ``-i`` INI file's ``[RS274NGC] SUBROUTINE_PATH``,
``DISABLE_FANUC_STYLE_SUB`` and ``DISABLE_G92_PERSISTENCE`` are honoured.  The
tool axis is -Z (a tool hangs below the spindle, as LinuxCNC's tool length
offsets assume).  :func:`run_examples` interprets the example programs
(``nc_files``) and lists every refusal that is not ``unsupported``.
"""
from __future__ import annotations

import math
import re
import shlex
from pathlib import Path

from ..errors import GcodeError
from ..gcode import parse_program
from ..gcode.expr import LENGTH_PARAMETERS
from ..gcode.state import MachineState, parse_tool_table

TOL = 1e-4
_CALL = re.compile(r"([A-Z_0-9]+)\((.*)\)\s*$")
_NUM = re.compile(r"[-+]?\d+\.?\d*(?:[eE][-+]?\d+)?")


_RS274 = re.compile(r"\brs274\b")
_OPTS = ("-t", "-i", "-p", "-n", "-b", "-s", "-T", "-v")


def _run_of(line: str, d: Path) -> dict | None:
    """One ``rs274`` invocation of a test.sh line: its program and options (None: not one)."""
    m = _RS274.search(line)
    if m is None:
        return None
    try:
        words = shlex.split(line[m.end():].split("|")[0].replace("{", " ").replace("}", " ")
                            .replace(";", " "))
    except ValueError:
        return {"skip": f"cannot read the command {line.strip()!r}"}
    opts: dict = {}
    ngc = None
    i = 0
    while i < len(words):
        w = words[i]
        if w in _OPTS:
            opts[w] = words[i + 1] if i + 1 < len(words) else ""
            i += 2
            continue
        if w in ("then", "||", "&&", "&", "exit"):
            break
        if not w.startswith("-") and not w.startswith("2>") and not w.startswith(">"):
            ngc = w
        i += 1
    if "-p" in opts:
        return {"skip": "runs an interpreter plug-in (-p)"}
    if "-i" in opts and (d / opts["-i"]).exists() and re.search(
            r"(?m)^\s*\[PYTHON\]", (d / opts["-i"]).read_text(errors="replace")):
        return {"skip": "needs LinuxCNC's embedded Python (a [PYTHON] section in its INI file)"}
    if ngc is None or "$" in ngc or not (d / ngc).exists():
        return {"skip": f"program {ngc!r} is not a file of the test"}
    return {"ngc": d / ngc, "tbl": d / opts["-t"] if "-t" in opts else None,
            "ini": d / opts["-i"] if "-i" in opts else None, "var": d / opts["-v"] if "-v" in opts else None,
            "fails": "!" in line[:m.start()],          # the test expects rs274 to fail on it
            "continue_on_error": opts.get("-n") == "0",  # rs274 -n 0: go on after an error
            "messages_only": "/MESSAGE/" in line,       # the test keeps only the MESSAGE lines
            "awk_first": "$1=\"\"" in line}             # awk '{$1=""; print}' drops each first word


_LOOP = re.compile(r"(?ms)^[ \t]*for\s+(\w+)\s+in\s+\$(\w+)\s*;\s*do[ \t]*\n(.*?)^[ \t]*done[ \t]*$")
#: a loop body that calls a zero exit status of rs274 an error: its programs must fail
_EXPECTS_FAILURE = re.compile(r'test\s+"\$res"\s*=\s*0\s*;\s*then\s*\n[^\n]*Error')


def _expand_loops(text: str) -> str:
    """``for t in $LIST; do ... done`` over a ``LIST="..."`` of the script, unrolled; a body that
    expects rs274 to fail gets a '!' before each rs274."""
    lists = dict(re.findall(r'(?m)^\s*(\w+)="([^"]*)"', text))

    def unroll(m):
        var, body = m.group(1), m.group(3)
        if _EXPECTS_FAILURE.search(body):
            body = _RS274.sub("! rs274", body)
        return "\n".join(body.replace("${%s}" % var, v).replace("$%s" % var, v)
                         for v in lists.get(m.group(2), "").split())
    return _LOOP.sub(unroll, text)


def find_tests(root: Path) -> tuple[list[dict], dict]:
    """Tests with an ``expected`` canonical output, and the tests left out with the reason.

    A test is {name, dir, expected, runs: [{ngc, tbl, ini, var, fails, messages_only}], xfail}:
    one run per ``rs274`` command of its test.sh, in order (their outputs follow each other
    in ``expected``).
    """
    base = root / "tests" / "interp"
    out = []
    left: dict = {}
    for sh in sorted(base.rglob("test.sh")):
        d = sh.parent
        name = str(d.relative_to(base))
        exp = d / "expected"
        if not exp.exists():
            left[name] = "no expected output"
            continue
        text = _expand_loops(sh.read_text(errors="replace").replace("\\\n", " "))
        runs = [_run_of(ln, d) for ln in text.splitlines()
                if not ln.lstrip().startswith(("#", "echo"))]
        runs = [r for r in runs if r is not None]
        echoed = [_norm(e) for e in re.findall(r'(?m)^\s*echo\s+"([^"]*)"', text)]
        for r in runs:
            r["echoed"] = echoed    # the test's own echo lines in its output (not PRINT)
        bad = next((r["skip"] for r in runs if "skip" in r), None)
        if not runs or bad:
            left[name] = bad or "test.sh runs no rs274"
            continue
        out.append({"name": name, "dir": d, "expected": exp, "runs": runs, "xfail": (d / "xfail").exists()})
    good = base / "good"
    for ngc in sorted(good.glob("*.ngc")) if good.is_dir() else []:
        exp = ngc.with_name(ngc.name + ".expected")
        if exp.exists():
            out.append({"name": f"good/{ngc.name}", "dir": good, "expected": exp, "xfail": False,
                        "runs": [{"ngc": ngc, "tbl": None, "ini": None, "var": None, "fails": False,
                                  "messages_only": False, "awk_first": False}]})
    return out, left


def split_runs(text: str, n: int) -> list[str] | None:
    """The canonical output of ``n`` runs, one text each (each run starts with one SET_FEED_REFERENCE)."""
    if n == 1:
        return [text]
    lines = text.splitlines()
    starts = [i for i, ln in enumerate(lines) if "SET_FEED_REFERENCE(" in ln]
    if len(starts) != n:
        return None
    starts[0] = 0
    return ["\n".join(lines[a:b]) for a, b in zip(starts, starts[1:] + [len(lines)])]


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
            feed = b.feed_mm_s if b.inverse_time_s is None and b.feed_deg_s is None else None
            if b.inverse_time_s is not None and b.start is not None:    # G93: LinuxCNC prints length / time
                d = math.dist(b.start[:3], b.end[:3])
                feed = d / b.inverse_time_s if d > 0 else None
            ev.append(("T" if b.kind == "rapid" else "F", [float(x) for x in b.end], None, feed))
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


_CANON_LINE = re.compile(r"^\s*(\d+\s+)?N[.\d]+\s+[A-Z_0-9]+\(")


def expected_prints(text: str, echoed=()) -> list[str]:
    """The (PRINT,...) lines of a run's output: its lines that are no canonical call (nor echo)."""
    return [_norm(ln) for ln in text.splitlines()
            if ln.strip() and not _CANON_LINE.match(ln) and ln.strip() != "executing"
            and _norm(ln) not in echoed]


def _machine_units(run: dict) -> str:
    """rs274's machine (external) length unit: inch unless the INI's [TRAJ] LINEAR_UNITS is mm."""
    ini = run.get("ini")
    if ini is not None and ini.exists():
        m = re.search(r"(?im)^\s*LINEAR_UNITS\s*=\s*(\S+)", ini.read_text(errors="replace"))
        if m and m.group(1).lower() in ("mm", "metric", "millimeter"):
            return "mm"
    return "inch"


def _tools(run: dict, root: Path):
    """The run's tool table (rs274's -t, else its default sim.tbl), in the machine unit as rs274 reads it."""
    tbl = run["tbl"] or root / "configs" / "sim" / "sim.tbl"
    if not tbl.exists():
        return None
    tools = parse_tool_table(tbl.read_text(errors="replace"))
    k = 25.4 if _machine_units(run) == "inch" else 1.0
    for e in tools.values():
        e.z_offset_mm, e.x_offset_mm, e.y_offset_mm = e.z_offset_mm * k, e.x_offset_mm * k, e.y_offset_mm * k
        e.diameter_mm *= k
    return tools


def _ini_flag(ini: Path | None, key: str) -> bool:
    if ini is None or not ini.exists():
        return False
    m = re.search(rf"(?im)^\s*{key}\s*=\s*(\d+)", ini.read_text(errors="replace"))
    return bool(m and int(m.group(1)))


def _var_state(run: dict) -> MachineState | None:
    """rs274's -v parameter file as a starting state (inch lengths to mm; G92 dropped when the INI
    sets DISABLE_G92_PERSISTENCE, as LinuxCNC does at start)."""
    var = run["var"]
    if var is not None and not var.exists():     # test.sh copies it from its template first
        var = var.with_name(var.name + ".template")
    if var is None or not var.exists():
        return None
    params = {}
    for ln in var.read_text(errors="replace").splitlines():
        parts = ln.split()
        if len(parts) == 2 and parts[0].isdigit():
            k, v = int(parts[0]), float(parts[1])
            params[k] = v * 25.4 if k in LENGTH_PARAMETERS and _machine_units(run) == "inch" else v
    if _ini_flag(run["ini"], "DISABLE_G92_PERSISTENCE"):
        params = {k: v for k, v in params.items() if not 5210 <= k <= 5219}
    return MachineState(parameters=params)


def run_one(run: dict, canon: str, root: Path) -> dict:
    """One rs274 run compared with its canonical output ``canon``."""
    text = run["ngc"].read_text(errors="replace")
    # (a test keeping only MESSAGE lines does not show the end: it is taken as run to its end)
    ran_to_end = not run["fails"] and ("PROGRAM_END()" in canon or "FINISH()" in canon or run["messages_only"])
    exp = parse_expected(canon)
    try:
        prog = parse_program(text, run["ngc"].name, tool_table=_tools(run, root),
                             tool_axis_platform=(0.0, 0.0, -1.0),
                             subroutine_path=_ini_subpath(run["ini"], run["ngc"].parent),
                             fanuc_subs=not _ini_flag(run["ini"], "DISABLE_FANUC_STYLE_SUB"),
                             machine_units=_machine_units(run), initial_state=_var_state(run),
                             require_end=True)     # rs274 refuses a file without M2/M30/%
    except GcodeError as exc:
        where = {"line": exc.line, "column": exc.column, "code": exc.code, "message": exc.bare_message}
        if exc.code == "abort" and not ran_to_end:
            msgs = [e[1] for e in exp if e[0] == "M"]
            if _norm(exc.bare_message) in _norm(canon) or _norm(exc.bare_message) in msgs:
                return {"outcome": "refused_as_linuxcnc", "aborted": where}
            return {"outcome": "differ", "difference": f"abort text {exc.bare_message!r} not LinuxCNC's"}
        if not ran_to_end:      # LinuxCNC stopped with an error too
            return {"outcome": "unsupported_where_linuxcnc_stops" if exc.code == "unsupported"
                    else "refused_as_linuxcnc", "error": where}
        out = {"outcome": "unsupported" if exc.code == "unsupported" else "refused", "error": where}
        if run.get("continue_on_error") and exc.code != "unsupported":
            out["note"] = "LinuxCNC ran this with -n 0 (continue after errors): its output does not show errors"
        return out
    if not ran_to_end:
        return {"outcome": "accepted", "difference": "LinuxCNC stops with an error, hexacnc runs it to its end"}
    msgs = [text for kind, _ln, text in prog.notes if kind in ("msg", "debug")]
    if run["messages_only"]:
        exp = [e for e in exp if e[0] == "M"]
    diff = compare(exp, [] if run["messages_only"] else program_events(prog), msgs)
    if diff is None and not run["messages_only"]:
        mine = [_norm(t) for kind, _ln, t in prog.notes if kind == "print"]
        if run.get("awk_first"):        # the test's awk '{$1=""}' drops each line's first word
            mine = [_norm(" ".join(t.split()[1:])) for t in mine]
        theirs = expected_prints(canon, run.get("echoed", ()))
        if mine != theirs:
            diff = f"PRINT output {theirs[:3]}... vs {mine[:3]}..."
    return {"outcome": "same"} if diff is None else {"outcome": "differ", "difference": diff}


_RANK = ("differ", "accepted", "refused", "unsupported", "unsupported_where_linuxcnc_stops",
         "refused_as_linuxcnc", "same")
_STOPS = ("refused_as_linuxcnc", "unsupported_where_linuxcnc_stops")


def run_test(t: dict, root: Path) -> dict:
    canons = split_runs(t["expected"].read_text(errors="replace"), len(t["runs"]))
    if canons is None:
        return {"outcome": "not_compared", "reason": "expected output does not split into the test's runs"}
    res = [run_one(r, c, root) for r, c in zip(t["runs"], canons)]
    outs = [r["outcome"] for r in res]
    if all(o in _STOPS for o in outs):
        out = min(outs, key=_RANK.index)
    elif all(o == "same" or o in _STOPS for o in outs):
        out = "same"
    else:
        out = min(outs, key=_RANK.index)
    r = dict(res[outs.index(out)]) if out in outs else {"outcome": out}
    r["outcome"] = out
    if len(res) > 1:
        r["runs"] = outs
    return r


def run_examples(root: Path) -> dict:
    """LinuxCNC's example programs (``nc_files``, no canonical output to compare): interpreted with
    rs274's default tool table and every example directory on the subroutine path; counts of
    ``ok`` / ``unsupported`` and each other refusal (to read: a wrong reason would show here)."""
    base = root / "nc_files"
    files = sorted(base.rglob("*.ngc")) if base.is_dir() else []
    path = sorted({str(f.parent) for f in files})
    tools = _tools({"tbl": None, "ini": None}, root)
    counts = {"ok": 0, "unsupported": 0, "refused": 0}
    refused = {}
    for f in files:
        try:
            parse_program(f.read_text(errors="replace"), f.name, tool_table=tools, tool_axis_platform=(0.0, 0.0, -1.0),
                          subroutine_path=[str(f.parent)] + path, max_lines=2_000_000, machine_units="inch")
            counts["ok"] += 1
        except GcodeError as exc:
            key = "unsupported" if exc.code == "unsupported" else "refused"
            counts[key] += 1
            if key == "refused":
                refused[str(f.relative_to(base))] = f"{exc.code}: {exc}"
    return {"programs": len(files), "counts": counts, "refused": refused}


def run_all(root: Path) -> dict:
    """Every test compared; counts over the tests LinuxCNC runs to their end (xfail ones apart)."""
    tests, left = find_tests(root)
    res = {}
    keys = ("same", "differ", "unsupported", "refused", "refused_as_linuxcnc", "unsupported_where_linuxcnc_stops",
            "accepted")
    counts = dict.fromkeys(keys, 0)
    xfail = {}
    for t in tests:
        r = run_test(t, root)
        if r["outcome"] == "not_compared":
            left[t["name"]] = r["reason"]
            continue
        if t["xfail"]:
            xfail[t["name"]] = r     # LinuxCNC's own suite expects this test to fail: not counted
            continue
        counts[r["outcome"]] += 1
        res[t["name"]] = r
    to_end = counts["same"] + counts["differ"] + counts["unsupported"] + counts["refused"]
    return {"linuxcnc": str(root), "tests": sum(counts.values()), "counts": counts,
            "linuxcnc_runs_to_end": to_end,
            "same_fraction_of_runs_to_end": round(counts["same"] / to_end, 3) if to_end else None,
            "target_same_fraction": 0.75,
            "tolerance_program_units": TOL, "results": res, "xfail_not_counted": xfail,
            "examples": run_examples(root),
            "left_out": left,
            "rules": "counts: tests LinuxCNC runs to its end (PROGRAM_END/FINISH, not expected to fail) "
                     "are same / differ / unsupported / refused; tests where LinuxCNC stops with an error "
                     "are refused_as_linuxcnc (hexacnc refuses too), unsupported_where_linuxcnc_stops or accepted "
                     "(hexacnc runs them); a test "
                     "of several rs274 runs is same when each run is same or refused as LinuxCNC"}
