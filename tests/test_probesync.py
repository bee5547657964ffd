"""Probe synchronisation of the interpreter (hexacnc.gcode.probesync): stop at an unknown probe,
continue from known results with #5061-#5070 set in program coordinates."""
from __future__ import annotations

import pytest

from hexacnc.daemon.probeprog import has_probe_words
from hexacnc.gcode.probesync import ProbeResult, ProbeSync, make_sync_interpreter, segment_after

TEXT = ("G21 G90 G54\nG10 L2 P1 X10 Y0 Z0\nG1 X0 Y0 Z0 F600\nG38.2 Z-10 F60\nG1 Z[#5063+1]\n"
        "G38.3 X5\nG0 X[#5061] Y[#5070 + 7]\nM2\n")
KW = {"start_pose": [0.0] * 6}


def _sync(known):
    try:
        make_sync_interpreter(known)(TEXT, "t", **KW).run()
    except ProbeSync as exc:
        return exc.interpreter.blocks
    raise AssertionError("no synchronisation at the probe")


def test_stops_at_the_first_unknown_probe():
    seg, probe = segment_after(_sync([]), 0)
    assert [b.kind for b in seg] == ["line"] and probe.kind == "probe" and probe.line == 4
    assert probe.end.tolist() == [10, 0, -10, 0, 0, 0]


def test_known_results_set_the_parameters_and_the_position():
    hit = ProbeResult(True, (10.0, 0.0, -3.5, 0.0, 0.0, 0.0), (10.0, 0.0, -3.6, 0.0, 0.0, 0.0))
    seg, probe = segment_after(_sync([hit]), 1)
    # continues from where the machine stopped; #5063 = -3.5 in G54 (offset X only) -> Z -2.5
    assert [(b.start.tolist(), b.end.tolist()) for b in seg] == [([10, 0, -3.6, 0, 0, 0], [10, 0, -2.5, 0, 0, 0])]
    assert probe.extra["code"] == "G38.3"
    miss = ProbeResult(False, (15.0, 0.0, -2.5, 0.0, 0.0, 0.0), (15.0, 0.0, -2.5, 0.0, 0.0, 0.0))
    it = make_sync_interpreter([hit, miss])(TEXT, "t", **KW)
    prog = it.run()
    seg, probe = segment_after(prog.blocks, 2)
    assert probe is None and it.P[5070] == 0.0 and it.P[5061] == pytest.approx(5.0)
    assert [b.end.tolist() for b in seg if b.kind == "rapid"] == [[15.0, 7.0, -2.5, 0, 0, 0]]


def test_probe_words_are_recognised():
    assert has_probe_words("g38.2 z-1") and has_probe_words("G 38 . 5 X1") and has_probe_words("G038.3Z0")
    assert not has_probe_words("G1 X38.2") and not has_probe_words("G38.1 X1")
