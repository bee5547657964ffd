"""ReferenceWatch (hexacnc.daemon.reference) on a plain header: which events drop the reference."""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.daemon import shm as S
from hexacnc.daemon.faults import F_EMCY, F_FOLLOWING, F_HOMING, F_NMT
from hexacnc.daemon.homecodes import E_HOMING_ERROR
from hexacnc.daemon.reference import ReferenceWatch


def header():
    h = np.zeros(S.N_HEADER, dtype=np.int64)
    h[S.H_STATE] = S.ST_IDLE
    h[S.H_BOOTUPS] = 6                       # the drives' own boot at start
    return h


def fault(h, code, strut, arg):
    h[S.H_FAULT], h[S.H_FAULT_STRUT], h[S.H_FAULT_ARG] = code, strut, arg
    h[S.H_STATE] = S.ST_FAULT


def clear(h):
    h[S.H_FAULT] = 0
    h[S.H_STATE] = S.ST_IDLE


@pytest.mark.parametrize("method,code,arg,lost", [
    ("cia402", F_FOLLOWING, 3000, True), ("cia402", F_EMCY, 0x2310, True), ("cia402", F_NMT, 0, True),
    ("absolute", F_FOLLOWING, 3000, False), ("absolute", F_EMCY, 0x2310, False), ("absolute", F_NMT, 0, False),
    ("absolute", F_EMCY, 0x7305, True), ("cia402", F_EMCY, 0x7320, True), ("cia402", F_HOMING, E_HOMING_ERROR, True)])
def test_faults(method, code, arg, lost):
    h = header()
    w = ReferenceWatch(method, False)
    w.baseline(h)
    assert not w.poll(h)
    w.mark(h)
    assert w.poll(h)
    h[S.H_FAULT], h[S.H_STATE] = code, S.ST_STOPPING    # latched, still stopping: not yet disabled
    assert w.poll(h)
    fault(h, code, 2, arg)
    assert w.poll(h) is (not lost)
    clear(h)
    assert w.poll(h) is (not lost)
    if lost:
        assert w.lost["reason"]
        w.mark(h)                          # homed again
        assert w.poll(h) and w.lost is None


def test_bootups_and_encoder_errors_in_any_state():
    h = header()
    inc, ab = ReferenceWatch("cia402", False), ReferenceWatch("absolute", True)
    for w in (inc, ab):
        w.baseline(h)
    inc.mark(h)
    h[S.H_STATE] = S.ST_DISABLED
    h[S.H_BOOTUPS] += 1                      # a drive power-cycled while disabled
    assert not inc.poll(h) and "power-cycled" in inc.lost["reason"]
    assert ab.poll(h)                        # absolute encoders keep their position
    h[S.H_ENCODER_ERRORS] += 1
    assert not ab.poll(h) and "encoder" in ab.lost["reason"]


def test_a_fault_before_homing_does_not_drop_the_next_reference():
    h = header()
    w = ReferenceWatch("cia402", False)
    w.baseline(h)
    fault(h, F_FOLLOWING, 1, 5000)
    assert not w.poll(h)
    clear(h)
    w.poll(h)
    w.mark(h)
    assert w.poll(h)
