"""Expressions, functions and parameters of the RS274NGC interpreter."""
from __future__ import annotations

import math
import random

import pytest

from hexacnc.errors import GcodeError
from hexacnc.gcode import parse_program
from hexacnc.gcode.interp import Interpreter


def evaluate(expr: str) -> float:
    """Value of ``expr`` as the interpreter computes it (through parameter #1)."""
    text = f"#1 = {expr}\n"
    it = Interpreter(text)
    it.run(text)
    return it.P[1]


@pytest.mark.parametrize("expr, want", [
    ("[1 + 2 * 3]", 7.0),
    ("[[1 + 2] * 3]", 9.0),
    ("[2 ** 3 ** 2]", 64.0),            # left to right, as LinuxCNC
    ("[2 * 3 ** 2]", 18.0),             # power binds tighter
    ("[7 MOD 3]", 1.0),
    ("[-7 MOD 3]", 2.0),                # LinuxCNC: result made non-negative
    ("[10 / 4]", 2.5),
    ("[1 - -2]", 3.0),
    ("[-[2 + 3]]", -5.0),
    ("[1 + 2 EQ 3]", 1.0),              # comparison below arithmetic
    ("[1 EQ 1.00005]", 1.0),            # EQ tolerance 1e-4
    ("[1 NE 1.001]", 1.0),
    ("[2 GT 1]", 1.0), ("[2 GE 2]", 1.0), ("[1 LT 1]", 0.0), ("[1 LE 1]", 1.0),
    ("[1 AND 0]", 0.0), ("[1 OR 0]", 1.0), ("[1 XOR 1]", 0.0), ("[2 XOR 0]", 1.0),
    ("[1 LT 2 AND 3 GT 2]", 1.0),        # logical lowest
    ("SIN[30]", 0.5), ("COS[60]", 0.5), ("TAN[45]", 1.0),
    ("ASIN[1]", 90.0), ("ACOS[0]", 90.0), ("ATAN[1]/[-1]", 135.0),
    ("ABS[-3.5]", 3.5), ("EXP[1]", math.e), ("LN[EXP[2]]", 2.0), ("SQRT[2]", math.sqrt(2.0)),
    ("FIX[-2.5]", -3.0), ("FUP[-2.5]", -2.0), ("ROUND[2.5]", 3.0), ("ROUND[-2.5]", -3.0),
    ("[sin[30]*2]", 1.0),                # case-insensitive
    ("[ 1 +   2 ]", 3.0),                # spaces anywhere
])
def test_expression_values(expr, want):
    assert evaluate(expr) == pytest.approx(want, abs=1e-12)


def test_random_arithmetic_matches_python():
    rng = random.Random(1234)
    for _ in range(200):
        a, b, c = (round(rng.uniform(-50, 50), 3) for _ in range(3))
        if b == 0:
            continue
        expr = f"[{a} + {b} * [{c} - {a}] / {b}]"
        assert evaluate(expr) == pytest.approx(a + b * (c - a) / b, rel=1e-12, abs=1e-9)


def test_parameters_numbered_named_global_indirect():
    text = """#1 = 5
#<len> = [#1 * 2]
#<_glob> = 3
#[#1 + 1] = 7
##1 = 9
#2 = [#6 + #5 + #<len> + #<_glob>]
#3 = #3000
"""
    it = Interpreter(text)
    it.run(text)
    assert it.P[6] == 7.0 and it.P[5] == 9.0
    assert it.P[2] == 7.0 + 9.0 + 10.0 + 3.0
    assert it.P[3] == 0.0          # unset numbered parameters read as 0


def test_assignments_on_one_line_read_before_set():
    text = "#1 = 1\n#1 = 2 #2 = #1\n"
    it = Interpreter(text)
    it.run(text)
    assert it.P[1] == 2.0 and it.P[2] == 1.0


def test_words_take_expressions_and_parameters():
    p = parse_program("#<x> = 4\nG0 X[#<x> * 2] Y-#<x> Z[SQRT[16]] A#<x>\n")
    assert p.blocks[0].end.tolist() == [8.0, -4.0, 4.0, 4.0, 0.0, 0.0]


def test_predefined_named_parameters():
    text = "G21 G0 X3 Y4\n#1 = #<_x>\n#2 = #<_y>\n#3 = #<_metric>\n#4 = #<_motion_mode>\nG20\n#5 = #<_imperial>\n"
    it = Interpreter(text)
    it.run(text)
    assert it.P[1:6] == [3.0, 4.0, 1.0, 0.0, 1.0]


@pytest.mark.parametrize("text, code, line, col", [
    ("G0 X[1/0]\n", "expression", 1, 4),
    ("G0 X[1/1] Y2 Z[SQRT[-1]]\n", "expression", 1, 14),
    ("#1 = 2 #2 = [1/0]\n", "expression", 1, 8),
    ("G0 X0\nG0 X[SQRT[-1]]\n", "expression", 2, 4),
    ("#1 = [ASIN[2]]\n", "expression", 1, 1),
    ("#1 = [LN[0]]\n", "expression", 1, 1),
    ("#1 = [[-8] ** 0.5]\n", "expression", 1, 1),
    ("#1 = [3 MOD 0]\n", "expression", 1, 1),
    ("G0 X#<undefined>\n", "parameter", 1, 5),
    ("G0 X0\n  G0 Y[#<a> + 1]\n", "parameter", 2, 8),
    ("#1 = [1 + 2\n", "expression", 1, 12),
    ("#1 = [1 FOO 2]\n", "expression", 1, 9),
    ("#1 = [10 ** 400]\n", "expression", 1, 1),
    ("#6000 = 1\n", "parameter", 1, 2),
    ("#1 = #[6000]\n", "expression", 1, 1),
    ("#<_x> = 1\n", "parameter", 1, 2),
    ("#1 G0\n", "parameter", 1, 4),
    ("#1 = SINE[1]\n", "expression", 1, 9),
    ("#1 = ATAN[1]\n", "expression", 1, 13),
])
def test_expression_errors_have_line_column_code(text, code, line, col):
    with pytest.raises(GcodeError) as ei:
        parse_program(text)
    e = ei.value
    assert (e.code, e.line, e.column) == (code, line, col), str(e)


def _full(raw: str, num: int = 1):
    from hexacnc.gcode import lexer
    s, _cols, comments = lexer.strip_with_map(raw, num)
    return lexer._parse_full(raw, num, s, comments)


def _evaluate_line(ln):
    P = [0.0] * 5602
    P[1], P[2] = 3.0, -2.0
    L = {"a": 1.5, "xscale": 0.5, "yscale": 1.0, "zscale": 2.0, "fscale": 3.0, "toolno": 1.0, "rpm": 100.0}
    G = {"_g": 4.0}
    vals = dict(ln.words)
    if ln.fn is not None:
        vals.update(zip(ln.dyn, ln.fn(P, L, G, lambda k: 0.0, ln.k)))
    return vals, list(ln.gs), list(ln.ms), [a for a in ln.axes], ln.delete


SHAPE_LINES = [
    "N120Y[#<yscale>*-56.12]Z[#<zscale>*-27.725]", "G1 X1 Y-2.5 Z.5 F100", "g2 r1.997999 x1.613302 y-1.178668",
    "/G0 X5", "N10 G0 X[1-2] Y[#1--2] Z[2**3**2]", "G1 X-#1 Y+#2 A[SIN[30]*2] F[#<_g>*10]",
    "#1 = [#2 + 3] #<a> = 7 G0 X#1", "G10 L2 P1 X1 Y2", "G64 P0.01 Q.02", "T1 M6 G43 H1", "G4 P1.5",
    "G1 X[ATAN[1]/[1]] Y[#1 MOD 2] Z[#1 GT 2]", "x1y2z3a4b5c6", "G0 X[#[#1 - 2]] Y##1",
]


def test_shaped_lines_equal_full_parse():
    from hexacnc.gcode.lexer import parse_line
    lines = list(SHAPE_LINES)
    from pathlib import Path
    corpus = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "gcode"
    for name in ("3D_Chips.ngc", "arcspiral.ngc", "tort.ngc"):
        if (corpus / name).exists():
            lines += (corpus / name).read_text().split("\n")[:400]
    for i, raw in enumerate(lines * 2):          # twice: the second time from the shape cache
        a = parse_line(raw, i + 1)
        if a.empty or a.oword is not None:
            continue
        b = _full(raw, i + 1)
        assert _evaluate_line(a) == _evaluate_line(b), raw


def test_presplit_lines_equal_full_parse():
    from pathlib import Path

    from hexacnc.gcode.lexer import Presplit
    texts = ["\n".join(SHAPE_LINES) + "\n(comment 12) G0 X1\nG1 X2 ; 3 4\n\tG0\tY1.5\r\n"]
    corpus = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "gcode"
    for name in ("3D_Chips.ngc", "arcspiral.ngc", "tort.ngc", "impeller-7bl-xyzac.ngc"):
        if (corpus / name).exists():
            texts.append((corpus / name).read_text())
    for text in texts:
        lines = text.split("\n")
        pre = Presplit(text, lines)
        assert pre.shapes is not None
        for i, raw in enumerate(lines):
            a = pre.line(i)
            if a.empty or a.oword is not None:
                continue
            try:
                b = _full(raw, i + 1)
            except GcodeError:
                continue   # refused lines (M428) are refused by both paths at execution
            assert a.num == i + 1 and _evaluate_line(a) == _evaluate_line(b), raw
