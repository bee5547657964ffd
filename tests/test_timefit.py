"""The time left of a streamed program (hexacnc/planner/timefit.py): the least-squares fit of planned seconds
per line against nominal seconds and blocks, and the estimate it gives after every prefix of planned windows
of real plans, against the whole program's planned time."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hexacnc.bench.camgen import cam_program
from hexacnc.config import load_config
from hexacnc.gcode import program_from_config
from hexacnc.bench.estimate import measure, planned_windows, replay, validator_counts
from hexacnc.planner.timefit import Counted, Planned, add_sums, fit, line_sums, rest_from_counted, rest_s, unplanned_s
from hexacnc.planner.window import FIRST_WINDOW_BLOCKS


def test_line_sums_count_the_rows_of_each_line_and_sum_its_blocks():
    dt = 0.001
    line_tab = np.array([3] * 10 + [4] * 30 + [9] * 5)          # line 9 has no block in the window
    s = line_sums([3, 4, 4, 7], [0.5, 0.25, 0.25, 0.0], line_tab, dt)
    # line 3: n 0.5, m 1, t 0.010; line 4: n 0.5, m 2, t 0.030; line 7: n 0, m 1, t 0
    want = (0.5, 1.5, 6.0, 0.5 * 0.010 + 0.5 * 0.030, 0.010 + 2 * 0.030, 0.010 ** 2 + 0.030 ** 2)
    assert np.allclose(s, want, rtol=1e-12, atol=0)
    assert add_sums((), s) == s and np.allclose(add_sums(s, s), 2 * np.array(want))
    # a line far from the others (a subroutine's body called from the top): the same counts
    far = line_sums([3, 4, 4, 7, 10 ** 7], [0.5, 0.25, 0.25, 0.0, 1.0], np.concatenate([line_tab, [10 ** 7] * 7]), dt)
    assert np.allclose(far, np.array(want) + [1.0, 1.0, 1.0, 0.007, 0.007, 0.007 ** 2], rtol=1e-12, atol=0)
    assert line_sums([], [], np.zeros(0, dtype=np.int32), dt) == (0.0,) * 6


def test_the_fit_recovers_both_terms_and_never_goes_negative():
    rng = np.random.default_rng(7)
    n, m = rng.uniform(0, 2, 50), rng.integers(1, 4, 50).astype(float)
    t = 1.7 * n + 0.009 * m
    sums = tuple(float(v) for v in (n @ n, n @ m, m @ m, n @ t, m @ t, t @ t))
    a, b = fit(sums)
    assert a == pytest.approx(1.7, rel=1e-9) and b == pytest.approx(0.009, rel=1e-7)
    assert rest_s(sums, 3.0, 100) == pytest.approx(1.7 * 3.0 + 0.009 * 100, rel=1e-7)
    # the best two-term fit has a negative blocks term: the better one-term fit instead
    t2 = 2.0 * n - 0.2 * m
    s2 = tuple(float(v) for v in (n @ n, n @ m, m @ m, n @ t2, m @ t2, t2 @ t2))
    a2, b2 = fit(s2)
    assert a2 >= 0 and b2 >= 0 and (a2 == 0 or b2 == 0)
    # nominal seconds all zero (feeds no machine follows): by blocks alone
    assert fit(tuple(float(v) for v in (0.0, 0.0, m @ m, 0.0, m @ (0.01 * m), (0.01 * m) @ (0.01 * m)))) == \
        pytest.approx((0.0, 0.01))
    assert fit(()) is None and rest_s((), 1.0, 1) is None and fit((0.0,) * 6) is None


def _windows(text, first_blocks=0):
    base = load_config(None)
    cfg = base.replace(planner=dataclasses.replace(base.planner, window_blocks=60))
    prog = program_from_config(text, "cam.ngc", cfg)
    return planned_windows(prog, cfg, first_blocks), validator_counts(prog, cfg), text.count("\n") + 1


def _fast_raster():
    return cam_program(800, feed_scale=1000)


def test_the_estimate_of_nothing_planned_is_zero_and_by_lines_without_counts():
    assert unplanned_s(Planned(), 100, None) == 0.0
    p = Planned(seconds=2.0, nominal_s=1.0, blocks=10, last_line=20, sums=())
    assert unplanned_s(p, 100, None) == pytest.approx(8.0)                      # 2 s per 20 lines
    assert unplanned_s(p, 100, Counted(10, 0.5, 5, False)) == pytest.approx(8.0)   # the validator behind
    assert unplanned_s(p, 100, Counted(100, 5.0, 50, True)) == pytest.approx(8.0)  # no fit: by blocks


@pytest.mark.slow
@pytest.mark.parametrize("fast, bound", [(True, 0.12), (False, 0.12)])
def test_the_estimate_after_every_prefix_of_windows_is_near_the_planned_time(fast, bound):
    """A CAM raster in windows of 60 blocks whose first window holds the rapid approach from home, at its
    feeds and at feeds 1000x what the struts follow (as 3D_Chips.ngc): after each prefix of planned windows
    the planned seconds plus the estimate the daemon gives (:func:`unplanned_s`, validated program) are
    within ``bound`` of the whole program's planned seconds (the older mix of the ratios of planned to
    nominal seconds and to blocks was 37 % over after the first window of the fast raster)."""
    text = _fast_raster() if fast else cam_program(800)
    ws, counts, total_lines = _windows(text)
    assert len(ws) > 10
    total_s = sum(w.plan.duration_s for w in ws)
    if fast:
        assert total_s > 2.5 * counts[-1][1]          # the feeds (capped at the rapid feed) say little of the time
    errs = replay(ws, counts, total_lines, validated=True)
    assert max(abs(e) for e in errs) <= bound, np.round(errs, 3).tolist()
    # the sums of all windows, fitted: the rest of nothing is nothing
    p = Planned()
    for w in ws:
        p.add(w)
    assert p.seconds == pytest.approx(total_s) and unplanned_s(p, total_lines, Counted(*counts[-1], True)) < 1e-9


@pytest.mark.slow
def test_before_the_validation_ends_the_validators_counts_beat_the_lines():
    """``start_before_validated`` (a first window of FIRST_WINDOW_BLOCKS, then doubling): after the first
    window the rest by the program's lines is 84 % over on the fast raster (the approach from home counts as
    typical); with the validator's counts where it is 4x as far: within 30 %, and within 12 % from the second
    window on."""
    ws, counts, total_lines = _windows(_fast_raster(), FIRST_WINDOW_BLOCKS)
    by_lines = replay(ws, counts, total_lines, validated=False, ahead=1.0)
    by_counts = replay(ws, counts, total_lines, validated=False, ahead=4.0)
    assert by_lines[0] > 0.5                             # the estimate this replaces
    assert abs(by_counts[0]) <= 0.30, np.round(by_counts, 3).tolist()
    assert max(abs(e) for e in by_counts[1:]) <= 0.12, np.round(by_counts, 3).tolist()
    assert rest_from_counted((1.0,) * 6, 1.0, 1, 0, 0.0, 0, 100) is None


def test_the_bench_reports_both_modes_for_a_small_program():
    cfg = load_config(None)
    r = measure(cam_program(200), "r.ngc", cfg, 60, [1.0, 4.0])
    assert r["windows"] >= 3 and r["blocks"] > 150 and r["planned_s"] > r["nominal_s"] > 0
    assert set(r["validated"]) == {"after_first_pct", "worst_from_second_pct", "worst_from_half_pct"}
    assert set(r["before_validated"]) == {"ahead_1x", "ahead_4x"}
    assert abs(r["validated"]["after_first_pct"]) < 50
