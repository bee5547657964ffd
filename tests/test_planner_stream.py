"""Windowed planning (hexacnc/planner/window.py) and the sampler over windows (chain.py): a program shorter
than the window plans exactly as a whole; a longer one is planned window by window with every strut limit
met across the handovers (measured from the rows by exact inverse kinematics and finite differences); a
program bad far past its start moves up to the last good window and ends at rest before the bad line."""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.bench.camgen import cam_program
from hexacnc.config import load_config
from hexacnc.errors import PlanError
from hexacnc.gcode import iter_blocks, program_from_config
from hexacnc.gcode.factory import machine_defaults
from hexacnc.planner import FLAG_END, plan_program
from hexacnc.planner.chain import ChainSampler, IterFeed
from hexacnc.planner.window import plan_windows
from hexacnc.setpoint import ROW
from test_planner_motion import run, utilisation


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def _blocks(cfg, text):
    return program_from_config(text, "cam.ngc", cfg).blocks


def _chain(cfg, blocks, window_blocks, **kw):
    feed = IterFeed(plan_windows(iter(blocks), cfg, window_blocks=window_blocks, **kw))
    return ChainSampler(feed, cfg.cycle.period_s), feed


def test_program_shorter_than_the_window_plans_as_a_whole(cfg):
    blocks = _blocks(cfg, cam_program(160))
    whole = plan_program(blocks, cfg)
    ws = list(plan_windows(iter(blocks), cfg, window_blocks=10_000))
    assert len(ws) == 1 and ws[0].last and not ws[0].forced_stop
    np.testing.assert_allclose(ws[0].plan.rows(), whole.rows(), rtol=0, atol=1e-9)
    assert ws[0].plan.duration_s == whole.duration_s
    chain, _ = _chain(cfg, blocks, 10_000)
    a, b = run(chain), run(whole.sampler())
    assert a.shape == b.shape
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)


def test_program_larger_than_the_window_is_planned_window_by_window(cfg):
    text = cam_program(420)
    blocks = _blocks(cfg, text)
    ws = list(plan_windows(iter(blocks), cfg, window_blocks=60))
    assert len(ws) >= 5 and ws[-1].last and not any(w.last for w in ws[:-1])
    assert sum(w.blocks for w in ws) == len(blocks)          # nothing dropped, nothing repeated
    for a, b in zip(ws[:-1], ws[1:]):                         # each window starts where the previous ended
        np.testing.assert_allclose(a.plan.end_pose_platform, b.plan.start_pose_platform, atol=1e-9)
    chain, _ = _chain(cfg, iter_blocks(text, "cam.ngc", **machine_defaults(cfg)), 60)
    rows = run(chain)
    dt = cfg.cycle.period_s
    assert chain.error is None and chain.done
    flags = rows[:, 7].astype(int)
    assert ((flags & FLAG_END) != 0).sum() == 1 and flags[-1] & FLAG_END
    np.testing.assert_allclose(rows[-1, :6], ws[-1].plan.end_pose_platform, atol=1e-9)
    assert np.all(np.diff(rows[:, 6]) >= -1)                  # program lines in order (a hold names its event line)
    assert {int(v) for v in rows[:, 6]} >= {int(b.line) for b in blocks if b.kind == "line"}
    uv, ua, uj = utilisation(cfg, rows, dt)
    assert uv <= 1.0 and ua <= 1.0 and uj <= 1.0
    total = sum(w.plan.duration_s for w in ws)
    assert abs((len(rows) - 1) * dt - total) < 0.01 * total   # the windows' rows, no waiting in between


def test_error_far_past_the_start_stops_before_the_bad_line(cfg):
    text = cam_program(420, bad_line=380)
    kw = machine_defaults(cfg)
    with pytest.raises(PlanError) as exc:
        plan_program(_blocks(cfg, text), cfg)
    assert exc.value.line == 380
    chain, feed = _chain(cfg, iter_blocks(text, "cam.ngc", **kw), 60)
    rows = run(chain)
    assert isinstance(chain.error, PlanError) and chain.error.line == 380
    assert rows[:, 6].max() < 380 and rows[:, 6].max() > 200        # moved far, stopped before the bad line
    np.testing.assert_allclose(rows[-1, :6], chain._win.plan.end_pose_platform, atol=1e-9)   # a window's end:
    assert np.max(np.abs(rows[-1, :3] - rows[-2, :3])) < 1e-6                                  # at rest
    uv, ua, uj = utilisation(cfg, rows, cfg.cycle.period_s)
    assert max(uv, ua, uj) <= 1.0


def test_validation_error_found_ahead_stops_on_the_path_at_once(cfg):
    blocks = _blocks(cfg, cam_program(420))
    chain, _ = _chain(cfg, blocks, 60)
    out = np.empty((400, ROW))
    moved = [out[:chain.next_rows(out)].copy() for _ in range(4)]
    chain.fail(PlanError("bad ahead", line=400, limit="length"))
    rest = run(chain)
    rows = np.vstack(moved + [rest])
    assert chain.done and chain.error.line == 400
    assert len(rest) < 0.3 / cfg.cycle.period_s                  # a jerk-limited stop, not the program
    uv, ua, uj = utilisation(cfg, rows, cfg.cycle.period_s)
    assert max(uv, ua, uj) <= 1.0


def test_rewind_across_a_window_handover_repeats_the_same_rows(cfg):
    blocks = _blocks(cfg, cam_program(300))
    chain, _ = _chain(cfg, blocks, 60)
    w0 = chain._win.plan.s_tab.shape[0]
    out = np.empty((w0 - 40, ROW))
    chain.next_rows(out)
    snap = chain.snapshot()
    first = np.empty((200, ROW))
    n1 = chain.next_rows(first)
    assert chain._i >= 1                                          # crossed into the next window
    chain.restore(snap)
    again = np.empty((200, ROW))
    n2 = chain.next_rows(again)
    assert n1 == n2 == 200
    np.testing.assert_array_equal(first, again)


@pytest.mark.parametrize("text", ["%\nG1 X1 F100\no100 sub\nG1 X2\no100 endsub\no100 call\n%\n", "  \n\nO1 call\n",
                                  "G1 X1 F100", " % \n(comment o)\nG0 Z5\n%%\n", ""])
def test_text_lines_note_what_the_file_lines_note(tmp_path, text):
    """The in-memory program (uploads) and a file give the interpreter the same structure."""
    from hexacnc.gcode.stream import _FileLines
    from hexacnc.gcode.textstream import _TextLines
    data = (text if not text or text.endswith("\n") else text + "\n").encode()
    f = tmp_path / "p.ngc"
    f.write_bytes(data)
    a, b = _TextLines(data, 64), _FileLines(f, 64)
    assert (a.n, a.offsets, a.owords, a.percent, a.first_nonblank) == \
           (b.n, b.offsets, b.owords, b.percent, b.first_nonblank)
    assert [a[i] for i in range(a.n)] == [b[i] for i in range(b.n)]


def test_streamed_text_gives_the_blocks_of_the_whole_text(cfg):
    from hexacnc.gcode.textstream import iter_text_blocks
    text = cam_program(700)
    whole = _blocks(cfg, text)
    streamed = list(iter_text_blocks(text, "cam.ngc", window_lines=64, **machine_defaults(cfg)))
    assert [(b.kind, b.line) for b in streamed] == [(b.kind, b.line) for b in whole]
    for a, b in zip(streamed, whole):
        if b.end is not None:
            np.testing.assert_array_equal(a.end, b.end)
