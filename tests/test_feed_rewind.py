"""The feeder's command rewind (hexacnc.daemon.feeding.FeedMixin._command) on a real shared-memory ring
and a planned program: a pause acts exactly REWIND_LEAD_S after the hot loop's read index - between
two chunk marks, regenerated from the last mark - and the rows from there are those the source gives
when paused at that row; the rows before are untouched."""
from __future__ import annotations

import threading
from collections import deque

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.daemon import shm as S
from hexacnc.daemon.feeding import FEED_CHUNK_ROWS, REWIND_LEAD_S, FeedMixin, Job
from hexacnc.daemon.program import ProgramSource
from hexacnc.gcode.factory import program_from_config
from hexacnc.planner import plan_program

DT = 0.0005


class Feeder(FeedMixin):
    def __init__(self, sh, src):
        self.sh = sh
        self.lock = threading.RLock()
        self.feed_hold = False
        self.rewinds = [0, 0]
        self._rewind_rows = int(round(REWIND_LEAD_S / DT))
        self._ahead_rows = 600
        self._start_rows = 500
        self.current = Job("t", src, np.zeros(6), np.zeros(6), marks=deque())


@pytest.fixture(scope="module")
def plan():
    cfg = load_config(None)
    text = "G21 G90 G64 P0.1\nG53 G0 X-120 Y0 Z-1140\nG53 G1 X120 F6000\nM2\n"
    return plan_program(program_from_config(text, "t.ngc", cfg).blocks, cfg)


def ring_rows(sh, a, b):
    return np.array([[sh.ring[(k % S.RING_ROWS) * S.ROW + j] for j in range(S.ROW)] for k in range(a, b)])


@pytest.mark.parametrize("consumed", [2000, 2000 + FEED_CHUNK_ROWS // 2 + 3, 2000 + FEED_CHUNK_ROWS - 1])
def test_pause_acts_at_the_lead_between_marks_and_continues_the_queued_rows(plan, consumed):
    sh = S.Shared(create=True)
    try:
        src = ProgramSource(plan, DT, "t")
        f = Feeder(sh, src)
        job = f.current
        f._push(job, sh, consumed + 600)
        sh.h[S.H_RING_R] = consumed                    # the hot loop ran this far
        before = ring_rows(sh, 0, sh.h[S.H_RING_W])
        with f.lock:
            assert f._command(src.sampler.pause)
        assert f.rewinds == [1, 0]
        k = consumed + f._rewind_rows                   # the lead point, whatever the marks
        after = ring_rows(sh, 0, sh.h[S.H_RING_W])
        assert np.array_equal(after[:k], before[:k])
        assert not np.allclose(after[k:k + 50, :6], before[k:k + 50, :6], atol=1e-9, rtol=0)
        # the reference: the same program, paused when its row k is next
        ref_src = ProgramSource(plan, DT, "t")
        head = ref_src.next_rows(k)
        assert np.allclose(head, before[:k], atol=1e-9, rtol=0)
        ref_src.sampler.pause()
        ref = ref_src.next_rows(after.shape[0] - k)
        assert np.allclose(after[k:], ref, atol=1e-9, rtol=0)
        # the feeder keeps the queue full from there, and stops where paused
        f._push(job, sh, f._ahead_rows - sh.ring_fill())
        assert sh.ring_fill() >= f._ahead_rows - 1
    finally:
        sh.close()


def test_nothing_left_to_take_back_acts_at_the_end_of_the_queue(plan):
    sh = S.Shared(create=True)
    try:
        src = ProgramSource(plan, DT, "t")
        f = Feeder(sh, src)
        f._push(f.current, sh, 600)
        sh.h[S.H_RING_R] = sh.h[S.H_RING_W] - 3         # fewer rows queued than the lead
        with f.lock:
            assert not f._command(src.sampler.pause)
        assert f.rewinds == [0, 1] and src.sampler.state == "pausing"
    finally:
        sh.close()


def test_feed_ahead_is_a_range_checked_daemon_key_and_jogs_keep_a_short_queue(tmp_path):
    from importlib import resources
    from hexacnc.errors import ConfigError
    from hexacnc.daemon.feeding import FEED_AHEAD_S, JOG_AHEAD_S
    assert load_config(None).daemon.feed_ahead_s == FEED_AHEAD_S
    text = (resources.files("hexacnc") / "data" / "default.toml").read_text()
    p = tmp_path / "m.toml"
    p.write_text(text.replace("[daemon]\n", "[daemon]\nfeed_ahead_s = 2.5\n", 1))
    assert load_config(str(p)).daemon.feed_ahead_s == 2.5
    p.write_text(text.replace("[daemon]\n", "[daemon]\nfeed_ahead_s = 0.01\n", 1))
    with pytest.raises(ConfigError, match=r"\[daemon\] feed_ahead_s"):
        load_config(str(p))
    sh = S.Shared(create=True)
    try:
        f = Feeder(sh, None)
        f.period_s = DT
        f._ahead_rows = int(2.5 / DT)
        assert f._job_ahead_rows(Job("p", None, np.zeros(6), np.zeros(6)), f._ahead_rows) == int(2.5 / DT)
        jog = Job("jog x", None, np.zeros(6), np.zeros(6), ahead_s=JOG_AHEAD_S)
        assert f._job_ahead_rows(jog, f._ahead_rows) == int(JOG_AHEAD_S / DT)
        f._ahead_rows = int(0.1 / DT)       # a daemon queue shorter than a jog's: the shorter
        assert f._job_ahead_rows(jog, f._ahead_rows) == int(0.1 / DT)
    finally:
        sh.close()


def test_time_left_is_at_the_set_override_and_zero_once_stopping(plan):
    """The status' time left: the nominal time at the feed override the operator set, not at the rate of the
    moment (a stop ramps that to 0: 'left 3:26:11' while stopping); 0 once stopping."""
    src = ProgramSource(plan, DT, "t")
    src.next_rows(400)
    _line, _pct, left = src.progress()
    nominal = src.sampler.progress[1]
    assert left == pytest.approx(nominal) and 0 < left < plan.duration_s
    src.set_feed_override(0.5)
    src.next_rows(2)                                   # the rate has barely begun to ramp down
    assert src.progress()[2] == pytest.approx(2 * src.sampler.progress[1])
    src.pause()
    src.next_rows(200)
    assert src.paused and src.progress()[2] == pytest.approx(2 * src.sampler.progress[1])
    src.resume()
    src.next_rows(50)
    src.stop()
    for _ in range(3):
        src.next_rows(2)
        assert src.progress()[2] == 0.0
