"""Planned time is monotonic in move length (issue 15 item 9, issue 19 item 4): a longer move of the
same shape can always be run at least as fast as a scaled-down copy of it, so a shorter one must never
take longer.  Swept from 1 um to 30 mm, single moves from rest and twelve back-to-back G64 P0.01 moves."""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.gcode.factory import program_from_config
from hexacnc.planner import plan_program
from hexacnc.planner.profile import ETA

LENGTHS = np.geomspace(1e-3, 30.0, 40)
DIRS = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (-1, 0, 1), (0, -1, -1)]


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def _plan(cfg, text):
    return plan_program(program_from_config(text, "t.ngc", cfg).blocks, cfg)


def back_to_back(cfg, d: float, mode: str = "G64 P0.01"):
    lines = ["G21 G91", mode]
    for k in range(12):
        u = np.array(DIRS[k % 6], float)
        u = d * u / np.linalg.norm(u)
        lines.append(f"G1 X{u[0]:.7f} Y{u[1]:.7f} Z{u[2]:.7f} F3000")
    return _plan(cfg, "\n".join(lines) + "\nM2\n")


def _dips(lengths, dur):
    return [(round(a, 5), round(b, 5), ta, tb) for a, b, ta, tb in zip(lengths[:-1], lengths[1:], dur[:-1], dur[1:])
            if tb < ta]


@pytest.mark.parametrize("move", ["X{d:.7f}", "X{h:.7f} Y{h:.7f} Z{h:.7f}"])
def test_single_moves_from_rest(cfg, move):
    dur = [_plan(cfg, f"G21 G91\nG1 {move.format(d=d, h=d / np.sqrt(3))} F6000\nM2\n").duration_s for d in LENGTHS]
    assert not _dips(LENGTHS, dur)


def test_a_model_violation_the_table_does_not_have_slows_nothing(cfg):
    """Twelve 0.847 mm moves: the model pass put the jerk at 0.975 of the limit on a corner blend where
    the table measures 0.74; before the verification measured such samples exactly, that slowed the plan
    (1.141 s, 0.8 % longer than twelve 0.875 mm moves)."""
    p = back_to_back(cfg, 0.84707)
    assert p.iterations == 2                    # the model pass, then the exact one: no tightening
    assert p.utilisation["jerk"] <= ETA
    assert p.duration_s <= back_to_back(cfg, 0.87545).duration_s * 1.0025


@pytest.mark.xfail(strict=True, reason="the peak caps' plateaus are placed between grid points "
                   "(planner/profile.py _cap_peaks): twelve 0.45 mm moves plan 1.7 % longer than twelve "
                   "0.54 mm ones, 1.08 mm 0.7 % longer than 1.29-1.54 mm")
def test_back_to_back_g64_moves(cfg):
    dur = [back_to_back(cfg, d).duration_s for d in LENGTHS]
    assert not _dips(LENGTHS, dur), _dips(LENGTHS, dur)
