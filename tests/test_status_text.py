"""The status texts an operator reads (``hexacnc status``, ``--watch``): lines of at most 80 characters,
numbers in their columns, nested fields as indented text, no Python reprs."""
from __future__ import annotations

import math

from hexacnc.commands.status import format_status
from hexacnc.commands.statusview import HEIGHT, WIDTH, format_compact


def _status() -> dict:
    pose = [6.9e-07, -2.3e-18, -1150.004147, 3.4e-20, 1.04e-08, -179.9996]
    return {
        "state": "running", "drives_enabled": True, "referenced": True, "controller": "client 7 (uid 1000)",
        "why_idle": None, "line": 12, "pose_cmd": [0.0, -1e-19, -900.004, 0.0, 0.0, 0.0],
        "pose_act": [0.0, 0.0, -900.0041, 0.0, 0.0, 0.0], "struts_cmd_mm": [1012.957] * 6,
        "struts_act_mm": [1012.957] * 6, "tool_tip": {"machine": pose, "work": [0.0, 0.0, 29.996, 0, 0, 0]},
        "work_offset": {"name": "G54"}, "tool": {"number": 2, "length_mm": 120.0},
        "feed": {"programmed_mm_min": 600.0, "actual_mm_s": 9.99}, "overrides": {"feed": 1.2, "rapid": 0.5},
        "cycle": {"period_s": 0.0005, "lateness_us": {"median": 1.0, "p99": 23.0, "max": 5875.506},
                  "compute_phases_us": {"poll": {"mean": 19.27, "max": 2034.07}},
                  "privileges": {"sched_fifo": False, "messages": ["memory locked (mlockall)", "pinned to CPU 1",
                                                                   "SCHED_FIFO not requested " * 3]}},
        "following_error_max_mm": [5.350784704e-09] * 6, "waiting": None, "dropped_programs": [],
        "thermal": {"source": "socket", "strut_mean_C_est": [math.nan] * 6, "probes_C": None,
                    "offsets_mm": [0.0] * 6},
        "queue": [{"name": "part.ngc", "lines": 1200}, {"name": "b.ngc", "lines": 3}],
    }


def test_compact_view_fits_and_keeps_its_columns():
    text = format_compact(_status())
    lines = text.splitlines()
    assert len(lines) <= HEIGHT and max(map(len, lines)) <= WIDTH, text
    machine = next(ln for ln in lines if ln.startswith("machine"))
    assert machine.split()[1:] == ["0.000", "0.000", "-1150.004", "0.000", "0.000", "-180.000"], machine
    header = lines[lines.index(machine) - 1]
    for col in ("x", "y", "z", "a", "b", "c"):      # each number ends under its axis letter
        ends = header.index(col) + 1
        assert machine[ends - 1].isdigit() and machine[ends:ends + 1] in (" ", ""), (header, machine)
    assert "-0.000" not in text


def test_details_are_indented_text_within_80_columns():
    text = format_status(_status())
    lines = text.splitlines()
    assert max(map(len, lines)) <= WIDTH, max(lines, key=len)
    for raw in ("{'", "['", "None", "True", "False", "np.float64"):
        assert raw not in text, (raw, text)
    assert "  lateness_us:" in lines and "    max: 5875.51" in lines
    assert "    sched_fifo: no" in lines
    assert any(ln.startswith("following_error_max_mm: 5.35078e-09, ") for ln in lines)
    assert "  strut_mean_C_est: -, -, -, -, -, -" in lines
    assert "  [0]:" in lines and "    name: part.ngc" in lines
    assert "dropped_programs: -" in lines and "waiting: -" in lines
    # a long list wraps, its continuation under the first value
    msg = next(i for i, ln in enumerate(lines) if ln.strip().startswith("messages:"))
    col = lines[msg].index(":") + 2
    assert lines[msg + 1].startswith(" " * col) and lines[msg + 1][col] != " ", lines[msg:msg + 3]
