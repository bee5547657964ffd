"""LinuxCNC semantics added for issue 18 (second round): Fanuc-style subprograms, computed call
labels, DEBUG formats, computed parameter numbers, the machine's parameter unit, cutter
compensation in G93.  Every expectation is derived by hand from LinuxCNC's documentation and
interpreter sources (interp_o_word.cc, interp_convert.cc), not from this interpreter."""
from __future__ import annotations

import math

import pytest

from hexacnc.errors import GcodeError
from hexacnc.gcode import ToolEntry, parse_program
from hexacnc.gcode import blocks as B


def moves(p):
    return [(b.kind[0].upper(), [round(float(v), 6) for v in b.end[:3]]) for b in p.blocks
            if b.kind in B.MOTION_KINDS]


def err(text, **kw) -> GcodeError:
    with pytest.raises(GcodeError) as ei:
        parse_program(text, **kw)
    return ei.value


# -- M98 / M99 ------------------------------------------------------------------------------
FANUC = """F100
G0 X0 Y0 Z5
M98 P1 L3
M30
O1
G91 G0 X10
G90 G1 Z-1
G0 Z5
M99
"""


def test_m98_runs_the_subprogram_l_times_and_m30_stops_before_it():
    p = parse_program(FANUC)
    # each pass: 10 mm further in X (G91), then down to Z-1 and back up to Z5
    exp = [("R", [0, 0, 5])]
    for k in (1, 2, 3):
        exp += [("R", [10 * k, 0, 5]), ("L", [10 * k, 0, -1]), ("R", [10 * k, 0, 5])]
    assert moves(p) == exp
    assert p.end_reason == "M30"


def test_m98_parameters_are_global_and_l0_skips():
    text = ("#1 = 5\n#31 = 1\nM98 P7 L2\n(DEBUG,#1 #31)\nM98 P7 L0\n(DEBUG,#1)\n"
            "o2 call [42]\n(DEBUG,#1)\nM2\n"
            "O7\n#1 = [#1 + 1]\n#31 = [#31 * 2]\nM99\n"
            "o2 sub\n#1 = [#1 * 100]\no2 endsub\n")
    p = parse_program(text)
    # two M98 passes change the caller's #1 (5 -> 7) and #31 (1 -> 4); L0 calls nothing; an o-call
    # sees its argument in #1 (4200 inside) and gives the caller its #1 back
    assert [m for _l, m in p.messages] == ["7.000000 4.000000", "7.000000", "7.000000"]


def test_m98_finds_the_first_o_number_and_a_bare_o_line_is_entered():
    p = parse_program("M98 P0002\nM30\nO0002\nG0 X1\nM99\nO2\nG0 X99\nM99\n")
    assert moves(p) == [("R", [1, 0, 0])]
    # run into from above, a bare O-number is just a program number (LinuxCNC goes on into it)
    p = parse_program("O100 (program number)\nG0 X3\nM2\n")
    assert moves(p) == [("R", [3, 0, 0])]


def test_fanuc_and_oword_styles_do_not_mix():
    assert err("O1 call\nM2\nO1\nG0 X1\nM99\n").code == "flow"            # O... needs M98
    e = err("M98 P1\nM2\nO1 sub\nG0 X1\nO1 endsub\n")                    # O... sub needs O... call
    assert (e.code, e.line) == ("flow", 1)
    e = err("M98 P1\nM2\nO1\nG0 X1\nO1 endsub\n")                       # O... ends with M99
    assert (e.code, e.line) == ("flow", 5)
    e = err("O1 call\nM2\nO1 sub\nG0 X1\nM99\n")    # O... sub ends with endsub: refused before the run
    assert (e.code, e.line) == ("flow", 3) and "never closed" in str(e)
    e = err("O1 call\nM2\nO1 sub\nM99\nO1 endsub\n")                    # M99 met inside O... sub
    assert (e.code, e.line) == ("flow", 4)
    e = err("M98 P5\nM2\n")
    assert (e.code, e.line) == ("flow", 1) and "O5" in str(e)
    assert err("M98 L2\n").code == "word"                                # no P word
    assert err("M98 P1 G0 X1\nO1\nM99\n").code == "word"                 # not alone on its line
    e = err("G0 X1\nM99\n")          # LinuxCNC restarts the main program endlessly: named, refused
    assert (e.code, e.line) == ("unsupported", 2) and "M99" in str(e)
    e = err("M98 P1\nM2\nO1\nM99\n", fanuc_subs=False)                   # DISABLE_FANUC_STYLE_SUB
    assert (e.code, e.line) == ("flow", 1)


def test_computed_call_labels():
    p = parse_program("#2 = 10\nO[#2 * 10] call [3]\nM98 P[5 * 40]\nM2\n"
                      "O100 sub\nG0 X#1\nO100 endsub\nO200\nG0 Y7\nM99\n")
    assert moves(p) == [("R", [3, 0, 0]), ("R", [3, 7, 0])]
    assert err("O[2.5] call\n").code == "word"
    assert err("O[1] if\n").code == "unsupported"


# -- comments, parameter numbers ---------------------------------------------------------------
def test_debug_formats_as_linuxcnc():
    p = parse_program("#<v> = 1.123456789\n#2 = 2.5\n"
                      "(DEBUG,a #<v> %d#<v> b %f#<v> #2 c %.2f#<v>)\n(DEBUG,%d#2 100% sure %.x)\nM2\n")
    # %lf until a format: %d rounds (%.0f: 2.5 -> "2", banker's as C), %f is 4 places and stays in
    # force for the following parameters, %.Nf N places; a lone '%' stays, '%.' drops the '%'
    assert [m for _l, m in p.messages] == ["a 1.123457 1 b 1.1235 2.5000 c 1.12", "2 100% sure .x"]


def test_exists_and_computed_parameter_numbers():
    p = parse_program("#1 = 2\n#2 = 99999\n#<a> = 1\n"
                      "(DEBUG,EXISTS: #<_x>)\nG0 X[EXISTS[##1]] Y[EXISTS[##2]] Z[EXISTS[#<a>] + EXISTS[#<b>]]\n"
                      "#ATAN[1]/[1] = 3\nG0 A#45\nM2\n")
    # ##1 is #2 (exists), ##2 is #99999 (beyond #5601: not), #<a> set, #<b> not; ATAN[1]/[1] = 45 deg
    assert [[round(float(v), 6) for v in b.end] for b in p.motion_blocks] == [[1, 0, 1, 0, 0, 0], [1, 0, 1, 3, 0, 0]]


# -- the machine's unit of stored lengths ------------------------------------------------------
def test_stored_lengths_in_the_machine_unit():
    text = ("G21\nG10 L2 P1 X25.4 Y50.8\n(DEBUG,#5221 #5222)\n#5223 = 1\nG54 G0 X0 Y0 Z0\n"
            "G20\nG92 X1\n(DEBUG,#5211)\nM2\n")
    inch = parse_program(text, machine_units="inch")
    mm = parse_program(text)
    # an inch machine stores and shows the G54 offset as 1, 2 (in) and takes #5223 = 1 as 1 in;
    # G92 X1 at the G54 origin makes that point X1: a G92 offset of -1 in (-25.4 mm)
    assert [m for _l, m in inch.messages] == ["1.000000 2.000000", "-1.000000"]
    assert [m for _l, m in mm.messages] == ["25.400000 50.800000", "-25.400000"]
    assert moves(inch) == [("R", [25.4, 50.8, 25.4])]
    assert moves(mm) == [("R", [25.4, 50.8, 1.0])]
    # the state keeps mm whatever the program saw
    assert inch.final_state.parameters[5221] == pytest.approx(25.4)
    assert inch.final_state.parameters[5223] == pytest.approx(25.4)
    with pytest.raises(GcodeError):
        parse_program("M2\n", machine_units="furlong")


# -- cutter compensation in G93 ------------------------------------------------------------------
def test_cutter_compensation_with_inverse_time():
    tools = {1: ToolEntry(tool=1, pocket=1, diameter_mm=4.0)}
    text = "G0 X0 Y0\nG42 D1\nG93 G1 X10 F6\nY10 F3\nG94 G40 G1 X20 F120\nM2\n"
    p = parse_program(text, tool_table=tools)
    got = [(b.kind[0].upper(), [round(float(v), 6) for v in b.end[:2]],
            None if b.center is None else [round(float(v), 6) for v in b.center[:2]],
            b.feed_mm_s, b.inverse_time_s) for b in p.motion_blocks]
    # r = 2, right side: the entry move ends 2 mm right of X10 (10, -2); its 10 mm programmed length
    # at F6 (1/6 min) is 60 mm/min = 1 mm/s.  The convex corner at (10, 0) gets a CCW arc about it to
    # (12, 0), then the line to (12, 10): both from the 10 mm move at F3, 30 mm/min = 0.5 mm/s.
    # G40: the exit from (12, 10) straight to (20, 10) at F120 = 2 mm/s.
    assert got == [("L", [10, -2], None, 1.0, None),
                   ("A", [12, 0], [10, 0], 0.5, None),
                   ("L", [12, 10], None, 0.5, None),
                   ("L", [20, 10], None, 2.0, None)]
    e = err("G41 D1\nG93 G1 X10\n", tool_table=tools)
    assert e.code == "feed"


def test_g84_off_g17_is_refused_by_name():
    e = err("G18 M3 S100 F100\nG84 X1 Z1 Y-1 R1\n")
    assert e.code == "unsupported" and "G84" in str(e) and e.line == 2
    assert math.isfinite(parse_program("G17 M3 S100 F100\nG0 Z5\nG84 X1 Y1 Z-1 R1\n").final_pose[0])


def test_cutter_compensation_in_g18():
    text = "G18 G0 X0 Y0 Z0\nG42.1 D4\nG1 Z10 F60\nX10\nG40\nG1 Z20\nM2\n"
    p = parse_program(text)
    got = [(b.kind[0].upper(), [round(float(v), 6) for v in b.end[:3]],
            None if b.center is None else [round(float(v), 6) for v in b.center], b.clockwise,
            None if b.normal is None else [float(v) for v in b.normal]) for b in p.motion_blocks]
    # G18 works in (Z, X) with normal +Y (LinuxCNC).  r = 2 on the right of +Z motion is -X: the entry
    # ends at Z10 X-2; turning to +X is a left turn, a convex corner for right compensation: a G3-sense
    # arc (positive about +Y) about the programmed corner Z10 X0 to Z12 X0, then X10 at Z12; after
    # G40 the straight move runs from Z12 X10 to the programmed Z20 X10.
    assert got == [("L", [-2, 0, 10], None, False, None),
                   ("A", [0, 0, 12], [0, 0, 10], False, [0.0, 1.0, 0.0]),
                   ("L", [10, 0, 12], None, False, None),
                   ("L", [10, 0, 20], None, False, None)]
    assert err("G19 G41.1 D1\n").code == "comp"                     # LinuxCNC: XY and XZ planes only
    assert err("G41.1 D1\nG1 X5 F60\nG18\n").code == "comp"         # no plane change while on


def test_arc_after_g40_is_checked_behind_a_modal_line():
    # G40, then a modal G1 line (the interpreter's fast path), then an arc: the line was the move
    # after G40, so the arc is allowed
    p = parse_program("G0 X-5 Y0\nG41.1 D2\nG1 X0 F60\nX5\nG40\nG1 X10 Y0\nG2 X12 Y0 I1\nM2\n")
    assert p.motion_blocks[-1].kind == "arc"


# -- G5 / G5.1 splines ---------------------------------------------------------------------------
def _seg_dist(p, a, b) -> float:
    ax, ay, bx, by = a[0], a[1], b[0], b[1]
    t = max(0.0, min(1.0, ((p[0] - ax) * (bx - ax) + (p[1] - ay) * (by - ay)) / ((bx - ax) ** 2 + (by - ay) ** 2)))
    return math.hypot(ax + t * (bx - ax) - p[0], ay + t * (by - ay) - p[1])


def test_g5_1_parabola_within_the_chord_tolerance():
    # LinuxCNC's example: from X-2 Y4, control point at +(2, -8) = (0, -4), to X2 Y4: the parabola y = x^2
    p = parse_program("G17 F60\nG0 X-2 Y4\nG5.1 X2 I2 J-8\nM2\n")
    segs = [b for b in p.blocks if b.kind == "line"]
    pts = [(float(b.start[0]), float(b.start[1])) for b in segs] + [(float(segs[-1].end[0]), float(segs[-1].end[1]))]
    assert pts[0] == (-2.0, 4.0) and pts[-1] == (2.0, 4.0)
    assert all(abs(y - x * x) < 1e-12 for x, y in pts)            # every vertex on the parabola
    # a chord of y = x^2 over dx lies at most dx^2 / 4 above it (at its middle): within 0.5 um
    assert max((b[0] - a[0]) ** 2 / 4 for a, b in zip(pts, pts[1:])) <= 0.0005
    assert all(b.feed_mm_s == 1.0 and b.line == 3 for b in segs)


def test_g5_cubic_series_continues_tangentially():
    p = parse_program("G17 F60\nG0 X0 Y0\nG5 I0 J3 P0 Q-3 X1 Y1\nG5 P0 Q-3 X2 Y2\nM2\n")
    first = [b for b in p.blocks if b.kind == "line" and b.line == 3]
    second = [b for b in p.blocks if b.kind == "line" and b.line == 4]
    assert [round(float(v), 9) for v in first[-1].end[:3]] == [1, 1, 0]
    assert [round(float(v), 9) for v in second[-1].end[:3]] == [2, 2, 0]
    # the midpoint of the first cubic, (P0 + 3 P1 + 3 P2 + P3) / 8 with P1 = (0, 3), P2 = (1, -2): (0.5, 0.5)
    poly = [(float(b.start[0]), float(b.start[1])) for b in first] + [(1.0, 1.0)]
    assert min(_seg_dist((0.5, 0.5), a, b) for a, b in zip(poly, poly[1:])) < 0.0005
    # the second starts in the direction -(P, Q) of the first = (0, 3): straight up (+Y)
    d = second[0].end[:2] - second[0].start[:2]
    assert abs(math.atan2(float(d[1]), float(d[0])) - math.pi / 2) < 0.05


def test_spline_refusals():
    assert err("F60\nG5 I1 J1 X1 Y1\n").code == "word"              # no P, Q
    assert err("F60\nG5 P1 Q1 X1 Y1\n").code == "word"              # first of a series without I, J
    assert err("F60\nG5 I1 P1 Q1 X1 Y1\n").code == "word"           # I without J
    assert err("F60\nG5.1 X1 Y1 Z1 I1\n").code == "word"            # Z moves no spline
    assert err("F60\nG5.1 X1 Y1 I0 J0\n").code == "word"            # no control point offset
    assert err("F60\nG18 G5.1 X1 Z1 I1\n").code == "unsupported"    # G17 only
    assert err("F60\nG5.2 X1 Y1 P1 L3\n").code == "unsupported"     # NURBS
    assert err("G41.1 D1\nG1 X5 F60\nG5.1 X6 Y1 I1\n").code == "comp"


def test_g7_lathe_diameter_mode_halves_x_words():
    p = parse_program("F60\nG7 G0 X10 Z1\nG1 X20\nG91 X4\nG90\n(DEBUG,#<_lathe_diameter_mode>)\n"
                      "G8 X4\nG7 X4\nG8\nG0 X1\nM2\n")
    # G7: X words are diameters (X10 -> 5, X20 -> 10, G91 X4 -> +2), also on the G7/G8 line itself
    assert moves(p) == [("R", [5, 0, 1]), ("L", [10, 0, 1]), ("L", [12, 0, 1]), ("L", [4, 0, 1]),
                        ("L", [2, 0, 1]), ("R", [1, 0, 1])]
    assert p.messages[0][1] == "1.000000"


def test_streaming_fanuc_subprograms_and_splines(tmp_path):
    from hexacnc.gcode import iter_blocks
    # the subprogram lies windows behind its call (150 comment lines, 64-line windows)
    text = FANUC.replace("M30\n", "G5.1 X40 Y10 I5 J5\nM30\n" + "(pad)\n" * 150)
    f = tmp_path / "f.ngc"
    f.write_text(text)
    whole = parse_program(text)
    streamed = list(iter_blocks(str(f), window_lines=64))
    assert [(b.kind, b.line, [float(v) for v in b.end]) for b in streamed if b.kind in B.MOTION_KINDS] == \
        [(b.kind, b.line, [float(v) for v in b.end]) for b in whole.motion_blocks]


def test_zero_length_probes_as_linuxcnc():
    # G38.3/G38.5 may start at their target (LinuxCNC checks only G38.2/G38.4); no motion is made
    p = parse_program("G0 Z5\nF60\nG38.3 Z5\nM2\n")
    assert [b.kind for b in p.motion_blocks] == ["rapid"] and not any(b.kind == "probe" for b in p.blocks)
    assert err("G0 Z5\nF60\nG38.2 Z5\n").code == "word"
    # after a probe the start is wherever it tripped (run time): a second probe to the same
    # target is not known to be zero-length here
    e = err("G0 Z5\nF60\nG38.2 Z0\nG38.2 Z0\n")
    assert (e.code, e.line) == ("unsupported", 4)
