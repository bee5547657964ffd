"""The LinuxCNC corpus (../shared/data/gcode) and random input."""
from __future__ import annotations

import random
import re
from pathlib import Path

import numpy as np
import pytest

from hexacnc.errors import GcodeError
from hexacnc.gcode import parse_program, program_from_config

CORPUS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "gcode"


def corpus(name: str) -> str:
    path = CORPUS / name
    if not path.exists():
        pytest.skip(f"corpus file {path} is absent (shared data not checked out next to the repository)")
    return path.read_text()


def test_tort_runs_with_helical_arcs_in_all_planes():
    text = corpus("tort.ngc")
    p = parse_program(text, "tort.ngc")
    arcs = [b for b in p.blocks if b.kind == "arc"]
    # independent count: lines with a G2/G3 word or, in an arc mode, axis words only
    assert len(arcs) == len(re.findall(r"(?im)^\s*G1[789]\s+G[23]\b", text))
    assert {tuple(b.normal) for b in arcs} == {(0, 0, 1), (0, 1, 0), (1, 0, 0)}
    for b in arcs:
        n, c = b.normal, b.center
        r0 = np.linalg.norm((b.start[:3] - c) - ((b.start[:3] - c) @ n) * n)
        r1 = np.linalg.norm((b.end[:3] - c) - ((b.end[:3] - c) @ n) * n)
        assert abs(r0 - r1) < 1e-4
    assert p.blocks[0].kind == "rapid" and [b.kind for b in p.blocks].count("pause") >= 1
    assert p.messages and p.messages[0][0] == 3
    assert p.end_reason == "M2"


def test_arcspiral_inch_modal_r_arcs():
    text = corpus("arcspiral.ngc")
    p = parse_program(text, "arcspiral.ngc")
    arcs = [b for b in p.blocks if b.kind == "arc"]
    assert len(arcs) == len(re.findall(r"(?im)^\s*(?:g2\s*)?r-?[\d.]+", text))
    assert len(arcs) > 900
    first = next(b for b in p.blocks if b.kind == "rapid" and b.end[0] != 0)
    assert first.end[:2] == pytest.approx([1.724638 * 25.4, -1.012731 * 25.4])
    for b in arcs:
        assert b.clockwise and tuple(b.normal) == (0, 0, 1)
        r_prog = np.linalg.norm(b.start[:2] - b.center[:2])
        assert np.linalg.norm(b.end[:2] - b.center[:2]) == pytest.approx(r_prog, rel=1e-9, abs=1e-9)
    assert arcs[0].feed_mm_s == pytest.approx(24 * 25.4 / 60)


def test_3d_chips_matches_an_independent_reading():
    text = corpus("3D_Chips.ngc")
    p = parse_program(text, "3D_Chips.ngc")
    # independent evaluation: every move word is [#<axscale>*number] with scale 1.0
    pos = {"X": 0.0, "Y": 0.0, "Z": 0.0}
    expected = []
    for line in text.split("\n"):
        words = dict((a, float(v)) for a, v in re.findall(r"([XYZ])\[#<[xyz]scale>\*(-?[\d.]+)\]", line))
        if not words:
            continue
        new = dict(pos, **words)
        if new != pos:
            expected.append([new["X"], new["Y"], new["Z"]])
        pos = new
    got = np.array([b.end[:3] for b in p.blocks if b.kind in ("rapid", "line")])
    assert got.shape == (len(expected), 3)
    assert np.allclose(got, np.array(expected), rtol=0, atol=1e-9)
    kinds = [b.kind for b in p.blocks]
    assert kinds[:3] == ["tool_change", "coolant", "spindle"] and kinds[-1] == "end"
    assert p.blocks[2].spindle_rpm == 1600
    line_blocks = [b for b in p.blocks if b.kind == "line"]
    assert line_blocks[0].blend_tolerance_mm == pytest.approx(0.1)


def test_3d_chips_for_the_default_machine():
    from hexacnc.config import load_config
    cfg = load_config()
    p = program_from_config(corpus("3D_Chips.ngc"), "3D_Chips.ngc", cfg)
    first = next(b for b in p.blocks if b.kind == "rapid")
    # the program starts at the tool reference point of the home pose
    home = cfg.home_pose
    assert first.start[:3] == pytest.approx(home[:3] + np.asarray(cfg.tool.tip_platform_mm))
    assert first.end[2] == pytest.approx(10.0 + cfg.planner.work_offset_mm[2])


def test_impeller_is_refused_for_its_user_m_code():
    text = corpus("impeller-7bl-xyzac.ngc")
    with pytest.raises(GcodeError) as ei:
        parse_program(text, "impeller")
    e = ei.value
    assert (e.line, e.column, e.code) == (4, 1, "unsupported")
    assert "M428" in str(e)


def test_impeller_with_its_kinematics_m_codes_as_no_ops_is_refused_for_a_joint_limit():
    """LinuxCNC's M428/M429 switch its TCP kinematics, which a hexapod always has: declared as
    no-ops (``[planner] noop_m_codes``) the program interprets, each one noted in the messages,
    and the planner refuses it for the physical reason - its A down to -72 deg tilts a platform
    joint past its limit - naming the line and the limit, before any motion."""
    import dataclasses
    from hexacnc.config import load_config
    from hexacnc.errors import PlanError
    from hexacnc.planner import plan_program
    text = corpus("impeller-7bl-xyzac.ngc")
    base = load_config(None)
    cfg = base.replace(planner=dataclasses.replace(base.planner, noop_m_codes=(428, 429)))
    prog = program_from_config(text, "impeller", cfg)
    assert [ln for ln, msg in prog.messages if "M428" in msg or "M429" in msg] == [4, 4509]
    with pytest.raises(PlanError) as ei:
        plan_program(prog.blocks, cfg)
    e = ei.value
    assert e.line == 8 and "joint" in e.limit and "max_angle_deg" in e.limit, (e.line, e.limit)
    # without the declaration it stays refused for the undefined M-code
    with pytest.raises(GcodeError) as eg:
        program_from_config(text, "impeller", base)
    assert (eg.value.line, eg.value.code) == (4, "unsupported")
    # a built-in code cannot be declared a no-op through the API either
    with pytest.raises(GcodeError, match="noop_m_codes"):
        parse_program("G0 X1\nM3\n", "api", noop_m_codes=[428, 3])


def test_impeller_without_its_user_m_codes_is_inverse_time_five_axis():
    text = corpus("impeller-7bl-xyzac.ngc")
    stripped = re.sub(r"(?im)^\s*M42[89].*$", "", text)
    p = parse_program(stripped, "impeller")
    lines = [b for b in p.blocks if b.kind == "line"]
    assert len(lines) == len(re.findall(r"(?m)^G1\s", stripped))
    assert all(b.inverse_time_s is not None and b.feed_mm_s is None for b in lines)
    assert min(b.end[3] for b in lines) < -70 and min(b.end[5] for b in lines) < -390


_ALPHABET = "GMXYZABCIJKRFSTPQHLNO#<>[]=+-*/.0123456789 ()%;\n_abcdefghijklmnopqrstuvwxyz,"
_SNIPPETS = ["G0 ", "G1 ", "G2 ", "G3 ", "X1 ", "Y-2.5 ", "Z[1+2] ", "F100 ", "R5 ", "I3 J4 ", "#1=", "#<a>=",
             "[#1*2]", "o1 if [1]\n", "o1 endif\n", "o2 while [#1 LT 3]\n", "#1=[#1+1]\n", "o2 endwhile\n",
             "o<s> sub\n", "o<s> endsub\n", "o<s> call [1]\n", "G20 ", "G91 ", "G93 ", "M3 S100 ", "G43 H1 ",
             "T1 M6 ", "G10 L2 P1 X1 ", "G53 ", "G17 ", "G18 ", "G19 ", "(MSG, x)", "; c", "/", "%\n", "\n",
             "SIN[", "ATAN[1]/[2]", "]", "#<_x>", "EXISTS[#<a>]", "G64 P0.1 ", "G4 P1 ", "M2\n", "G92 X0 "]


def _garbage(rng: random.Random) -> str:
    mode = rng.random()
    if mode < 0.3:
        return "".join(rng.choice(_ALPHABET) for _ in range(rng.randint(0, 80)))
    if mode < 0.4:
        return bytes(rng.randrange(256) for _ in range(rng.randint(0, 60))).decode("latin-1")
    return "".join(rng.choice(_SNIPPETS) for _ in range(rng.randint(1, 30)))


def test_random_garbage_raises_only_gcode_error():
    rng = random.Random(20261121)
    outcomes = {"ok": 0, "error": 0}
    for _ in range(1500):
        text = _garbage(rng)
        try:
            p = parse_program(text, "garbage", tool_table={1: 10.0}, max_lines=5000)
        except GcodeError as exc:
            assert exc.line is None or exc.line >= 1
            assert exc.code
            outcomes["error"] += 1
        else:
            outcomes["ok"] += 1
            for b in p.blocks:
                if b.end is not None:
                    assert np.all(np.isfinite(b.end))
    assert outcomes["ok"] > 50 and outcomes["error"] > 50   # both paths were exercised


def test_mutated_corpus_lines_raise_only_gcode_error():
    text = corpus("tort.ngc") + corpus("3D_Chips.ngc")[:3000]
    lines = text.split("\n")
    rng = random.Random(7)
    for _ in range(400):
        out = list(lines[:60])
        for _k in range(rng.randint(1, 4)):
            i = rng.randrange(len(out))
            s = out[i]
            j = rng.randrange(len(s) + 1)
            op = rng.random()
            if op < 0.4:
                s = s[:j] + rng.choice(_ALPHABET) + s[j:]
            elif op < 0.7:
                s = s[:j] + s[j + 1:]
            else:
                s = s[:j] + rng.choice(_SNIPPETS) + s[j:]
            out[i] = s
        try:
            parse_program("\n".join(out), max_lines=5000)
        except GcodeError:
            pass
