"""Motion, modes, offsets, tool length and errors of the RS274NGC interpreter."""
from __future__ import annotations


import numpy as np
import pytest

from hexacnc.errors import GcodeError
from hexacnc.gcode import Block, parse_program
from hexacnc.gcode import blocks as B
from hexacnc.pose import matrix_from_euler


def moves(p):
    return [b for b in p.blocks if b.kind in B.MOTION_KINDS]


def err(text, **kw) -> GcodeError:
    with pytest.raises(GcodeError) as ei:
        parse_program(text, **kw)
    return ei.value


def check_arc(b: Block):
    """Independent arc checks: equal radii in the plane, unit normal, centre on the start's plane."""
    n = np.asarray(b.normal)
    assert np.linalg.norm(n) == pytest.approx(1.0)
    c = np.asarray(b.center)
    s, e = np.asarray(b.start[:3]), np.asarray(b.end[:3])
    rs = (s - c) - ((s - c) @ n) * n
    re_ = (e - c) - ((e - c) @ n) * n
    assert np.linalg.norm(rs) == pytest.approx(np.linalg.norm(re_), abs=1e-6)
    assert (s - c) @ n == pytest.approx(0.0, abs=1e-9)
    return float(np.linalg.norm(rs))


# -- linear motion, modes -----------------------------------------------------------
def test_modal_motion_absolute_incremental_and_feed():
    p = parse_program("G21 G90 F600\nG1 X10\nY5\nG91 X1 Y1\nG0 Z2\nZ2\n")
    m = moves(p)
    assert [b.kind for b in m] == ["line", "line", "line", "rapid", "rapid"]
    assert m[0].end.tolist() == [10, 0, 0, 0, 0, 0]
    assert m[1].end.tolist() == [10, 5, 0, 0, 0, 0]
    assert m[2].end.tolist() == [11, 6, 0, 0, 0, 0]
    assert m[4].end.tolist() == [11, 6, 4, 0, 0, 0]
    assert m[0].feed_mm_s == pytest.approx(10.0) and m[3].feed_mm_s is None
    for a, b in zip(m, m[1:]):          # every move starts where the previous ended
        assert np.array_equal(a.end, b.start)
    assert [b.line for b in m] == [2, 3, 4, 5, 6]


def test_inch_units_scale_lengths_feed_but_not_angles():
    p = parse_program("G20 G1 X1 A10 F10\nG21 X1\n")
    m = moves(p)
    assert m[0].end.tolist() == pytest.approx([25.4, 0, 0, 10, 0, 0])
    assert m[0].feed_mm_s == pytest.approx(10 * 25.4 / 60)
    assert m[1].feed_mm_s == pytest.approx(10 * 25.4 / 60)   # F is converted with the units
    assert m[1].end[0] == pytest.approx(1.0)
    assert parse_program("G1 X1 F1\n", units_default="inch").blocks[0].end[0] == pytest.approx(25.4)


def test_rotary_only_feed_is_degrees_per_minute():
    b = parse_program("G20 G1 A30 F120\n").blocks[0]
    assert b.feed_deg_s == pytest.approx(2.0) and b.feed_mm_s == pytest.approx(2.0)


def test_inverse_time_feed():
    p = parse_program("G93 G1 X10 F2\nX20 F0.5\nG0 X0\nG94 G1 X5 F60\n")
    m = moves(p)
    assert m[0].inverse_time_s == pytest.approx(30.0) and m[0].feed_mm_s is None
    assert m[1].inverse_time_s == pytest.approx(120.0)
    assert m[3].inverse_time_s is None and m[3].feed_mm_s == pytest.approx(1.0)
    e = err("G93 G1 X10 F2\nX20\n")
    assert (e.code, e.line) == ("feed", 2)
    e = err("G1 X1 F100\nG93 G1 X10 F2\nG94 G1 X20\n")   # leaving G93 needs a new F
    assert (e.code, e.line) == ("feed", 3)


def test_zero_feed_is_an_error():
    e = err("G0 X1\nG1 X2\n")
    assert (e.code, e.line, e.column) == ("feed", 2, 1)


def test_path_control_and_dwell_and_stops():
    p = parse_program("G64 P0.05 F60\nG1 X1\nG61\nG1 X2\nG4 P1.5\nM0\nM1\nG64\nG1 X3\nM2\nG1 X99\n")
    m = moves(p)
    assert m[0].blend_tolerance_mm == pytest.approx(0.05) and not m[0].exact_stop
    assert m[1].exact_stop and m[2].blend_tolerance_mm is None and not m[2].exact_stop
    kinds = [b.kind for b in p.blocks]
    assert kinds == ["line", "line", "dwell", "pause", "optional_pause", "line", "end"]
    assert p.blocks[2].seconds == 1.5
    assert p.end_reason == "M2" and p.end_line == 10


def test_spindle_coolant_tool_blocks():
    p = parse_program("S1000 M3\nM4\nS500\nM5\nM8\nM7\nM9\nT3 M6\n", tool_table={3: 40.0})
    got = [(b.kind, b.spindle_rpm, b.coolant, b.tool) for b in p.blocks]
    assert got == [("spindle", 1000, "off", 0), ("spindle", -1000, "off", 0), ("spindle", -500, "off", 0),
                   ("spindle", 0, "off", 0), ("coolant", 0, "flood", 0), ("coolant", 0, "mist", 0),
                   ("coolant", 0, "off", 0), ("tool_change", 0, "off", 3)]


def test_comments_messages_block_delete_percent_n_words():
    text = "%\n(MSG, hello there)\nN10 G0 X1 ; trailing\n/G0 X5\nN20G0(inline)Y2\n%\nthis is not gcode\n"
    p = parse_program(text)
    assert p.messages == [(2, "hello there")]
    assert [b.end[:2].tolist() for b in moves(p)] == [[1, 0], [1, 2]]
    assert p.end_reason == "percent" and p.end_line == 6
    p2 = parse_program(text, block_delete=False)
    assert [b.end[0] for b in moves(p2)] == [1, 5, 5]


# -- arcs -----------------------------------------------------------------------------
def test_arc_center_format_all_planes():
    p = parse_program("G17 G2 X10 Y0 I5 J0 F60\nG0 X0 Y0 Z0\nG18 G2 X10 Z0 I5 K0\nG0 X0\n"
                      "G19 G3 Y10 Z0 J5 K0\n")
    a = [b for b in p.blocks if b.kind == "arc"]
    assert a[0].center.tolist() == [5, 0, 0] and a[0].normal.tolist() == [0, 0, 1] and a[0].clockwise
    assert a[1].center.tolist() == [5, 0, 0] and a[1].normal.tolist() == [0, 1, 0]
    assert a[2].center.tolist() == [0, 5, 0] and a[2].normal.tolist() == [1, 0, 0] and not a[2].clockwise
    for b in a:
        assert check_arc(b) == pytest.approx(5.0)


@pytest.mark.parametrize("g, r, center", [
    ("G3", "10", [0, 10]),      # CCW short arc: centre left of the chord
    ("G3", "-10", [10, 0]),     # negative R: the long way round
    ("G2", "10", [10, 0]),
    ("G2", "-10", [0, 10]),
])
def test_arc_radius_format(g, r, center):
    b = parse_program(f"F60 {g} X10 Y10 R{r}\n").blocks[0]
    assert b.center[:2].tolist() == pytest.approx(center, abs=1e-9)
    assert check_arc(b) == pytest.approx(10.0)


def test_helical_full_circle_with_turns():
    b = parse_program("F60 G0 X5\nG17 G3 X5 Y0 Z-6 I-5 J0 P3\n").blocks[1]
    assert b.kind == "arc" and b.turns == 2 and b.end.tolist() == [5, 0, -6, 0, 0, 0]
    assert b.center.tolist() == [0, 0, 0]


def test_arc_absolute_center_mode_with_offset():
    p = parse_program("G90.1 G0 X0 Y0\nG2 X10 Y0 I5 J0 F60\n", work_offsets={"G54": [100, 0, 0]})
    b = p.blocks[1]
    assert b.center.tolist() == [105, 0, 0] and b.end[0] == 110


def test_modal_r_arcs_without_g_word():
    p = parse_program("G20 F10 G2 X1 Y0 R0.5\nX2 R0.5\n")
    a = moves(p)
    assert [b.kind for b in a] == ["arc", "arc"]
    assert a[1].center[0] == pytest.approx(1.5 * 25.4)


@pytest.mark.parametrize("text, code, col", [
    ("F60 G2 X10 Y0 I4 J0\n", "arc", 15),         # end radius differs
    ("F60 G2 X10 Y0\n", "arc", 5),                # no centre
    ("F60 G2 X0 Y0 R5\n", "arc", 14),             # R full circle
    ("F60 G2 X30 Y0 R5\n", "arc", 15),            # R too small
    ("F60 G2 X10 I5 K1\n", "word", 15),           # K in the XY plane
    ("F60 G1 X1 I5\n", "word", 11),               # I without an arc
])
def test_arc_errors(text, code, col):
    e = err(text)
    assert (e.code, e.line, e.column) == (code, 1, col), str(e)


# -- work offsets, G10, G92, G53 ----------------------------------------------------
def test_work_offsets_g10_l2_l20_and_g53():
    wo = {"G54": [100, 0, 0, 0, 0, 5], "G55": [0, 200, 0]}
    p = parse_program("G0 X1 C1\nG55 G0 X1 Y0\nG10 L2 P2 X50\nG0 X1\nG53 G0 X5 Y5\nG0 Y0\n"
                      "G54 G0 X0\nG10 L20 P1 X7\nG0 X8\n", work_offsets=wo)
    ends = [b.end.tolist() for b in moves(p)]
    assert ends[0] == [101, 0, 0, 0, 0, 6]
    assert ends[1] == [1, 200, 0, 0, 0, 6]
    assert ends[2] == [51, 200, 0, 0, 0, 6]
    assert ends[3] == [5, 5, 0, 0, 0, 6]           # G53: machine coordinates
    assert ends[4] == [5, 200, 0, 0, 0, 6]
    assert ends[5] == [100, 200, 0, 0, 0, 6]
    assert ends[6] == [101, 200, 0, 0, 0, 6]        # current X (100) became X7: X8 is 101


def test_g92_offset():
    p = parse_program("G0 X10\nG92 X0\nG0 X5\nG92.1\nG0 X5\n")
    assert [b.end[0] for b in moves(p)] == [10, 15, 5]


def test_g53_errors():
    assert err("G91 G53 G0 X1\n").code == "modal"
    assert err("G53 G2 X1 I1 F1\n").code == "modal"


# -- tool length -------------------------------------------------------------------------
@pytest.mark.parametrize("abc", [(0, 0, 0), (90, 0, 0), (12, -7, 33)])
def test_g43_shifts_tool_tip_along_tool_axis_platform_stays(abc):
    axis = np.array([0.0, 0.0, -1.0])
    start = [10, 20, 30, *abc]
    p = parse_program("T2 M6\nG43 H2\nG0 X12\nG49\nG0 X11\n", start_pose=start, tool_table={2: 50.0},
                      tool_axis_platform=axis)
    m = moves(p)
    R = matrix_from_euler(*np.radians(abc))
    # platform reference point = tip - R (L axis): unchanged by G43 (the platform does not move)
    plat_before = np.array(start[:3])
    plat_after = m[0].start[:3] - R @ (50.0 * axis)
    assert plat_after == pytest.approx(plat_before, abs=1e-9)
    assert m[0].tool_length_mm == 50.0 and m[1].tool_length_mm == 0.0
    assert m[1].start[:3] == pytest.approx(m[0].end[:3] - R @ (50.0 * axis), abs=1e-9)


def test_tool_errors():
    assert err("G43 H1\n").code == "tool"                       # no tool table
    assert err("T5 M6\n", tool_table={1: 10.0}).code == "tool"  # not in the table
    assert err("G43 H1\n", tool_table={2: 10.0}).code == "tool"
    p = parse_program("T1 M6 G43\nG0 X1\n", tool_table={1: 10.0})   # G43 without H: current tool
    assert moves(p)[0].tool_length_mm == 10.0


# -- O-words ----------------------------------------------------------------------------
def test_subroutines_locals_params_and_recursion():
    text = """#<v> = 1
#1 = 42
o<fact> sub
  o10 if [#1 LE 1]
    o<fact> return [1]
  o10 endif
  #<v> = 99
  o<fact> call [#1 - 1]
  o<fact> return [#1 * #<_value>]
o<fact> endsub
o<fact> call [5]
G0 X#<_value> Y#<v> Z#1
M2
"""
    b = moves(parse_program(text))[0]
    assert b.end[:3].tolist() == [120, 1, 42]


def test_loops_if_chain_repeat_break_continue():
    text = """#1 = 0
#2 = 0
o1 while [#1 LT 10]
  #1 = [#1 + 1]
  o2 if [[#1 MOD 2] EQ 0]
    o1 continue
  o2 elseif [#1 GT 7]
    o1 break
  o2 else
    #2 = [#2 + #1]
  o2 endif
o1 endwhile
o3 repeat [3]
  #2 = [#2 + 100]
o3 endrepeat
#3 = 0
o4 do
  #3 = [#3 + 1]
o4 while [#3 LT 0]
G0 X#2 Y#3
"""
    b = moves(parse_program(text))[0]
    assert b.end[:2].tolist() == [1 + 3 + 5 + 7 + 300, 1]


@pytest.mark.parametrize("text, line, code", [
    ("o1 if [1]\nG0 X1\n", 1, "flow"),
    ("o1 call\n", 1, "flow"),
    ("o1 endwhile\n", 1, "flow"),
    ("o1 while [1]\n o2 break\no1 endwhile\n", 2, "flow"),
    ("o1 return\n", 1, "flow"),
    ("o1 foo\n", 1, "unsupported"),
])
def test_oword_errors(text, line, code):
    e = err(text)
    assert (e.line, e.code) == (line, code), str(e)


def test_endless_loop_is_stopped():
    e = err("o1 while [1]\no1 endwhile\n", max_lines=10_000)
    assert e.code == "runaway"


# -- refused input ---------------------------------------------------------------------------
@pytest.mark.parametrize("text, line, col, code", [
    ("G0 X1\n  G5.2 X2 P1 L3\n", 2, 3, "unsupported"),      # NURBS (G5, G5.1 are supported)
    ("G0 X1\nM428\n", 2, 1, "unsupported"),
    ("G33 Z-1 K1\n", 1, 1, "unsupported"),
    ("G76 P1 Z-1 R1\n", 1, 1, "unsupported"),
    ("M100\n", 1, 1, "unsupported"),
    ("G0 U1\n", 1, 4, "unsupported"),
    ("G0 X1 D1\n", 1, 7, "word"),
    ("G1 X1 G0 Y1\n", 1, 7, "modal"),
    ("M3 M4\n", 1, 4, "modal"),
    ("G0 X1 X2\n", 1, 7, "word"),
    ("X1\n", 1, 1, "word"),
    ("G0 I1 X1\n", 1, 4, "word"),
    ("G0 X1.2.3\n", 1, 8, "syntax"),
    ("G0 X1 (unclosed\n", 1, 7, "syntax"),
    ("G0 X1 )\n", 1, 7, "syntax"),
    ("G0 X1 $\n", 1, 7, "unsupported"),
    ("G4\n", 1, 1, "word"),
    ("G10 L3 P1 Z1\n", 1, 5, "unsupported"),
    ("G0 X\n", 1, 5, "syntax"),
    ("G0.5 X1\n", 1, 1, "unsupported"),
    ("%\nG0 X1\n", 2, 1, "syntax"),
    ("G0 X1 N5\n", 1, 7, "unsupported"),
])
def test_refusals_name_line_column_code(text, line, col, code):
    e = err(text)
    assert (e.line, e.column, e.code) == (line, col, code), str(e)
    assert f"line {line}" in str(e)


def test_g92_family_and_system_parameters():
    text = "G0 X10 Y4\nG92 X0\n#1 = #5211\n#2 = #5420\nG92.2\n#3 = #5420\nG92.3\n#4 = #<_x>\nG0 X1\n"
    from hexacnc.gcode.interp import Interpreter
    it = Interpreter(text)
    p = it.run(text)
    assert it.P[1:5] == [10.0, 0.0, 10.0, 0.0]
    assert moves(p)[-1].end[0] == 11.0


def test_debug_message_substitutes_parameters():
    p = parse_program("#1 = 2.5\n#<d> = 3\n(DEBUG, one=#1 d=#<d> nope=#<zz>)\n")
    assert p.messages == [(3, "one=2.500000 d=3.000000 nope=######")]


def test_r_arc_in_xz_plane_and_helical_in_yz():
    b = parse_program("F60 G18 G3 X10 Z10 R10\n").blocks[0]
    # G18: rotation about +Y takes Z to X; CCW short arc from (x0,z0) to (x10,z10) has centre x=10, z=0
    assert b.center.tolist() == pytest.approx([10, 0, 0]) and b.normal.tolist() == [0, 1, 0]
    b = parse_program("F60 G19 G2 Y0 Z0 X5 J5 K0 P2\n").blocks[0]   # full helix along X
    assert b.turns == 1 and b.end[0] == 5 and b.center.tolist() == [0, 5, 0]


def test_program_from_config_with_tool_table(tmp_path):
    import tomllib
    from hexacnc.config import default_config_path, parse_config
    from hexacnc.gcode import program_from_config
    doc = tomllib.loads(default_config_path().read_text())
    doc["tools"] = {"length_mm": {"1": 62.5}}
    doc.setdefault("planner", {})["work_offset_mm"] = [5.0, -5.0, -1100.0]
    cfg = parse_config(doc)
    with pytest.raises(GcodeError) as ei:
        program_from_config("T1 M6 G43 H1\nG0 X0 Y0 Z0\nT2\n", "t", cfg)
    assert (ei.value.line, ei.value.code) == (3, "tool")
    p = program_from_config("T1 M6 G43 H1\nG0 X0 Y0 Z0 A1\n", "t", cfg)
    b = moves(p)[0]
    assert b.tool_length_mm == 62.5
    assert b.end.tolist() == pytest.approx([5.0, -5.0, -1100.0, 1.0 + cfg.home_pose[3], cfg.home_pose[4],
                                            cfg.home_pose[5]])
    # the platform did not move between the start and the G43 shift
    axis = np.asarray(cfg.tool.axis_platform)
    tip0 = np.asarray(cfg.tool.tip_platform_mm)
    R = matrix_from_euler(*np.radians(cfg.home_pose[3:]))
    plat = b.start[:3] - R @ (tip0 + 62.5 * axis)
    assert plat == pytest.approx(cfg.home_pose[:3], abs=1e-9)


def test_g28_g30_stored_positions():
    home = [1.0, 2.0, 3.0, 0.0, 0.0, 5.0]
    p = parse_program("G0 X10 Y10 Z10\nG28\nG0 X20\nG28 Z15\nG30.1\nG0 X0 Y0 Z0\nG91 G30 X1\n",
                      g28_pose=home)
    ends = [b.end.tolist() for b in moves(p)]
    assert ends[1] == home                                  # all axes home
    assert ends[3] == [20, 2, 15, 0, 0, 5]                  # intermediate point Z15 ...
    assert ends[4] == [20, 2, 3, 0, 0, 5]                   # ... then only Z to its stored value
    assert ends[6] == [1, 0, 0, 0, 0, 5]                    # G91: intermediate X+1
    assert ends[7] == [20, 0, 0, 0, 0, 5]                   # G30 position stored by G30.1 (X only)
    assert all(b.kind == "rapid" for b in moves(p))
    assert err("G28.1 X1\n").code == "word"


def test_call_depth_limit_and_return_from_inside_a_loop():
    e = err("o<r> sub\n  o<r> call\no<r> endsub\no<r> call\n")
    assert (e.code, e.line) == ("runaway", 2)
    text = """o<find> sub
  #<i> = 0
  o1 while [#<i> LT 100]
    #<i> = [#<i> + 1]
    o2 if [#<i> * #<i> GT #1]
      o<find> return [#<i>]
    o2 endif
  o1 endwhile
o<find> endsub
o<find> call [50]
G0 X#<_value>
o<find> call [10]
G0 Y#<_value>
"""
    b = moves(parse_program(text))
    assert b[0].end[0] == 8 and b[1].end[1] == 4
