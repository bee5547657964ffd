"""``hexacnc plan``: JSON summary of a program that fits, first violation (line, limit) of one that does not."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)

REPO = Path(__file__).resolve().parents[1]


def _config(tmp_path: Path) -> Path:
    """The default machine with G54 at the home tool tip (z = -1150)."""
    text = (REPO / "config" / "default.toml").read_text()
    line = "work_offset_mm = [0.0, 0.0, -1150.0]"
    if "[planner]" in text:
        text = re.sub(r"(?m)^work_offset_mm\s*=.*$", "", text).replace("[planner]", "[planner]\n" + line, 1)
    else:
        text += "\n[planner]\n" + line + "\n"
    p = tmp_path / "machine.toml"
    p.write_text(text)
    return p


def _run(*args):
    return subprocess.run([sys.executable, "-m", "hexacnc", "plan", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=120)


def test_plan_json_summary(tmp_path):
    prog = tmp_path / "ok.ngc"
    prog.write_text("G21 G90 G64 P0.05\nG0 X0 Y0 Z0\nG1 X30 F3000\nG1 Y30 A5\nG2 X0 Y30 I-15 J0\n"
                    "G1 X0 Y0 B3\nG4 P0.5\nM2\n")
    r = _run(prog, "--config", _config(tmp_path), "--json", "--lines")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["ok"] is True
    for k in ("velocity", "acceleration", "jerk"):
        assert 0 < s["utilisation"][k] <= 1.0
    assert s["duration_s"] > 0.5 + 90.0 / 50.0 * 0.5       # dwell plus motion
    assert s["min_joint_margin_deg"] > 0
    assert set(s["lines"]) >= {"3", "4", "5", "6", "7"}
    a, b = s["lines"]["7"]
    assert b - a >= 0.5                                     # the dwell line holds 0.5 s


def test_plan_reports_first_violation(tmp_path):
    prog = tmp_path / "bad.ngc"
    prog.write_text("G21 G90\nG0 X0 Y0 Z0\nG1 X10 F600\n(far out)\nG1 X10 Y0 Z-600\nG1 X0\nM2\n")
    r = _run(prog, "--config", _config(tmp_path), "--json")
    assert r.returncode == 1
    s = json.loads(r.stdout)
    assert s["ok"] is False
    assert s["error"]["line"] == 5
    assert s["error"]["limit"].endswith("max_length_mm")
    r = _run(prog, "--config", _config(tmp_path))
    assert r.returncode == 1
    assert "line 5" in r.stderr and "max_length_mm" in r.stderr


def test_plan_refuses_bad_gcode_with_line(tmp_path):
    prog = tmp_path / "syntax.ngc"
    prog.write_text("G21\nG1 X10 F100\nG5 X1\n")
    r = _run(prog, "--config", _config(tmp_path), "--json")
    assert r.returncode == 2
    s = json.loads(r.stdout)
    assert s["error"]["line"] == 3


@pytest.mark.parametrize("name", ["tort.ngc", "impeller-7bl-xyzac.ngc"])
def test_corpus_programs_plan_or_are_refused_for_a_named_reason(name):
    corpus = REPO.parent / "shared" / "data" / "gcode"
    if not (corpus / name).exists():
        pytest.skip(f"G-code corpus file {name} not found in {corpus}")
    r = _run(corpus / name, "--json")
    s = json.loads(r.stdout)
    if r.returncode == 0:
        assert s["ok"] and max(s["utilisation"].values()) <= 1.0
    else:
        # refused before motion, naming the line and the reason (limit or unsupported code)
        assert r.returncode in (1, 2) and not s["ok"]
        assert s["error"]["line"] is not None and s["error"]["message"]
