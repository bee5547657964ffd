"""Memory and time of planning bounded whatever a program asks: a block longer than ``[planner] max_block_s``
(a 16 h move or dwell needed 17-24 GB of table rows) and a path needing more than ``grid.MAX_GRID_POINTS``
limit-check samples (a 692,689 deg rotation over 1.3 mm: 17.5 GB) are refused before anything large is
allocated, naming the line."""
from __future__ import annotations

import dataclasses
import resource
import time

import pytest

from hexacnc.config import load_config
from hexacnc.errors import ConfigError, PlanError
from hexacnc.gcode.factory import program_from_config
from hexacnc.planner import plan_program
from hexacnc.planner.window import plan_windows, validate_windows


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def _plan(cfg, text):
    return plan_program(program_from_config(text, "bounds.ngc", cfg).blocks, cfg)


def _refused_quickly(fn, line: int, limit: str):
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.process_time()
    with pytest.raises(PlanError) as ei:
        fn()
    assert ei.value.line == line and ei.value.limit == limit, (ei.value.line, ei.value.limit, str(ei.value))
    assert time.process_time() - t0 < 5.0
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 300 * 1024      # kB: nothing large
    return str(ei.value)


@pytest.mark.parametrize("body,line,what", [
    ("G1 X10 F0.01\n", 3, "move"),                     # 60,000 s at its feed
    ("G1 X1 F1000\nG4 P100000\n", 4, "dwell"),
])
def test_a_block_longer_than_max_block_s_is_refused_with_its_line(cfg, body, line, what):
    text = "G21 G91\nG64 P0.01\n" + body + "M2\n"
    msg = _refused_quickly(lambda: _plan(cfg, text), line, "max_block_s")
    assert what in msg and "max_block_s" in msg
    # the same through the window splitter (daemon stream, validation)
    blocks = program_from_config(text, "bounds.ngc", cfg).blocks
    _refused_quickly(lambda: list(plan_windows(iter(blocks), cfg)), line, "max_block_s")
    _refused_quickly(lambda: list(validate_windows(iter(blocks), cfg)), line, "max_block_s")


def test_a_block_within_max_block_s_plans_and_the_bound_is_configurable(cfg):
    text = "G21 G91\nG1 X1 F1000\nG4 P2\nM2\n"
    assert _plan(cfg, text).duration_s > 2.0
    short = cfg.replace(planner=dataclasses.replace(cfg.planner, max_block_s=1.5))
    _refused_quickly(lambda: _plan(short, text), 3, "max_block_s")


def test_max_block_s_is_range_checked(tmp_path):
    from importlib.resources import files
    text = files("hexacnc").joinpath("data/default.toml").read_text()
    assert "max_block_s = 900.0" in text
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("max_block_s = 900.0", "max_block_s = 0.0"), encoding="utf-8")
    with pytest.raises(ConfigError, match="max_block_s"):
        load_config(str(bad))


def test_a_path_needing_too_many_check_samples_is_refused_before_they_exist(cfg):
    """One move turning 692,689 deg about A over 1.3 mm (a mutated CAM line) after fifteen ordinary ones."""
    lines = ["G21 G90"] + [f"G1 X{14.0 - 0.1 * i:.3f} Y{-7.0 - 1.0 * i:.3f} Z20 F159" for i in range(15)]
    lines += ["G1 X12.347 Y-22.011 Z11.647 A-692689 F159", "M2"]
    msg = _refused_quickly(lambda: _plan(cfg, "\n".join(lines) + "\n"), 17, "check_samples")
    assert "limit-check samples" in msg
