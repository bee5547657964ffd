"""Program digital I/O (M62-M66): ``[io]`` config, refusals, placement on the plan's rows, the hot
loop's packing and the simulated drives' 0x60FD/0x60FE objects (no daemon)."""
from __future__ import annotations

import numpy as np
import pytest

from drivers import simdio
from hexacnc.config.load import default_config_path, read_toml
from hexacnc.config.machine import parse_config
from hexacnc.daemon.dioloop import SHIFT, decode, encode, pack_row
from hexacnc.daemon.program import plan_program
from hexacnc.errors import ConfigError, GcodeError
from hexacnc.kinematics import Hexapod
from hexacnc.setpoint import COL_FLAGS, COL_LINE, FLAG_IO


def _cfg(io=None):
    doc = read_toml(default_config_path())
    if io is not None:
        doc["io"] = io
    return parse_config(doc, "m.toml")


IO = {"digital_out_0": [1, 16], "digital_out_1": [2, 17], "digital_in_3": [4, 2]}


def test_io_config_maps_and_range_checks():
    cfg = _cfg(IO)
    assert cfg.io.digital_out == {0: (0, 16), 1: (1, 17)} and cfg.io.digital_in == {3: (3, 2)}
    assert _cfg().io.empty
    bad = [({"digital_out_0": [7, 16]}, "drive 7"), ({"digital_out_0": [1, 3]}, "bit 3"),
           ({"digital_out_0": [1, 16.5]}, "bit 16.5"), ({"digital_in_0": [1, 32]}, "bit 32"),
           ({"digital_out_2000": [1, 16]}, "above 1023"), ({"digital_out_0": [1, 16], "digital_out_1": [1, 16]},
                                                             "already used"),
           ({"analog_out_0": [1, 16]}, "unknown option")]
    for table, what in bad:
        with pytest.raises(ConfigError, match="io") as ei:
            _cfg(table)
        assert what in str(ei.value) and "m.toml" in str(ei.value)


def _home(cfg):
    return np.r_[cfg.home_pose[:3], np.radians(cfg.home_pose[3:])]


def _plan(cfg, text):
    return plan_program(cfg, Hexapod(cfg), text, "t.ngc", _home(cfg), cfg.cycle.period_s)


@pytest.mark.parametrize("io,text,line,what", [
    (IO, "G91 G1 X1 F600\nM64 P7\nM2\n", 2, "M64 P7"),
    (IO, "G91 G1 X1 F600\nG4 P0.1\nM63 P9\nM2\n", 3, "M63 P9"),
    (None, "G91 G1 X1 F600\nM65 P0\nM2\n", 2, "[io] is empty"),
    (IO, "G91\nM66 P3 L3 Q2\nG1 X1 F600\nM2\n", 2, "M66 P3"),
    (IO, "G91\nM68 E0 Q2.5\nG1 X1 F600\nM2\n", 2, "M68 E0"),
])
def test_unmapped_or_unsupported_io_refused_with_line(io, text, line, what):
    cfg = _cfg(io)
    with pytest.raises(GcodeError) as ei:
        _plan(cfg, text)
    assert ei.value.line == line and what in str(ei.value), str(ei.value)


def _rows(src):
    out = []
    while not src.finished:
        out.append(src.next_rows(400).copy())
    return np.vstack(out)


def _changes(rows):
    """[(row, line, x, (drive, bit, value)), ...] from the rows' packed flags."""
    res = []
    for i in np.nonzero(rows[:, COL_FLAGS].astype(np.int64) & FLAG_IO)[0]:
        c = int(rows[i, COL_FLAGS]) >> SHIFT
        while c:
            res.append((int(i), int(rows[i, COL_LINE]), float(rows[i, 0]), decode(c & 1023)))
            c >>= 10
    return res


PROG = "G21 G91 G94\nM64 P0\nG1 X1 F600\nG4 P0.5\nM62 P1\nG1 X4\nM63 P1\nG1 X3\nM65 P0\nM2\n"


def test_outputs_land_on_the_right_rows():
    cfg = _cfg(IO)
    rows = _rows(_plan(cfg, PROG).source)
    x0 = float(rows[0, 0])
    ch = _changes(rows)
    assert [c[3] for c in ch] == [(0, 16, True), (1, 17, True), (1, 17, False), (0, 16, False)]
    (r_on0, _, x_on0, _), (r_on1, l_on1, x_on1, _), (r_off1, l_off1, x_off1, _), (r_off0, _, x_off0, _) = ch
    # M64 before any motion: at the start pose
    assert x_on0 == pytest.approx(x0, abs=1e-9)
    # M62 after the dwell: not before the G1 X4 (line 6) starts: the row before is the dwell's last row,
    # at X+1, and the rows after it move toward X+5
    assert l_on1 == 6 and x_on1 == pytest.approx(x0 + 1, abs=1e-6)
    assert rows[r_on1 - 1, 0] == pytest.approx(x0 + 1, abs=1e-9) and rows[r_on1 + 5, 0] > x0 + 1
    assert r_on1 - r_on0 >= 0.5 / cfg.cycle.period_s        # the whole G4 P0.5 lies between
    # M63 synchronised with G1 X3 (line 8): at X+5 where that move starts
    assert l_off1 == 8 and x_off1 == pytest.approx(x0 + 5, abs=1e-6) and rows[r_off1 + 5, 0] > x0 + 5
    # M65 after the last move: at rest at its end
    assert x_off0 == pytest.approx(x0 + 8, abs=1e-9) and r_off0 > r_off1


def test_rewind_produces_each_change_once():
    cfg = _cfg(IO)
    src = _plan(cfg, PROG).source
    first = src.next_rows(100).copy()
    snap = src.snapshot()
    a = _rows(src)
    src.restore(snap)
    b = _rows(src)
    assert np.array_equal(a[:, COL_FLAGS], b[:, COL_FLAGS])
    assert len(_changes(np.vstack([first, a]))) == 4


def test_packing_round_trip_and_hot_loop_take():
    from hexacnc.daemon.dioloop import DigitalOut
    codes = [encode(0, 16, True), encode(5, 31, True), encode(2, 20, False)]
    f = pack_row(1, codes)
    assert float(f) == f and f & FLAG_IO and f & 1
    assert [decode((f >> (SHIFT + 10 * k)) & 1023) for k in range(3)] == [(0, 16, True), (5, 31, True),
                                                                       (2, 20, False)]

    class _Loop:
        io = object()

        class sh:
            s = np.zeros(96)
    d = DigitalOut(_Loop())
    d.word[2] = 1 << 20
    assert d.take(f) == f
    assert d.word[0] == 1 << 16 and d.word[5] == 1 << 31 and d.word[2] == 0
    assert d.dirty == [True, False, True, False, False, True]


def test_sim_drive_digital_io_objects():
    class _Drive:
        target_inc = 5
        pos_inc = 4

        def __init__(self):
            from drivers.simhooks import OdHooks
            self.hooks = OdHooks()
    dr = _Drive()
    simdio.attach(dr)
    dio = dr.dio
    dr.hooks.write[0x60FE][0](1, (1 << 16) | 1)      # bit 0 (brake) is outside the default mask
    assert dio.physical == 1 << 16 and dr.hooks.read[0x60FE](1) == (1 << 16) | 1
    dr.hooks.sync[0](dr, 0.0)
    dr.hooks.write[0x60FE][0](1, 0)
    assert [e["outputs"] for e in dio.log] == [1 << 16, 0] and dio.log[1]["syncs"] == 1
    dio.inputs = 0b100
    assert dr.hooks.read[0x60FD](0) == 0b100



def test_m66_is_a_synchronisation_point_of_the_interpreter():
    from hexacnc.daemon.probeprog import has_probe_words
    from hexacnc.gcode.probesync import InputResult, ProbeSync, make_sync_interpreter, segment_after
    text = "G21 G90\nG1 X1 F600\nM66 P3 L3 Q2\nG1 X[#5399 * 5 + 10]\nM66 P3 L0\nG1 Y[#5399 * 3]\nM2\n"
    assert has_probe_words(text) and not has_probe_words("M6 T1\nM2\n") and not has_probe_words("M660\n")
    kw = {"start_pose": [0.0] * 6}
    with pytest.raises(ProbeSync) as ei:
        make_sync_interpreter([])(text, "t", **kw).run()
    seg, wait = segment_after(ei.value.interpreter.blocks, 0)
    assert [b.kind for b in seg] == ["line"] and wait.line == 3 and wait.extra["mode"] == "high"
    with pytest.raises(ProbeSync) as ei:
        make_sync_interpreter([InputResult(-1.0)])(text, "t", **kw).run()
    seg, wait = segment_after(ei.value.interpreter.blocks, 1)
    assert seg[0].end[0] == pytest.approx(5.0) and wait.line == 5 and wait.extra["mode"] == "immediate"
    prog = make_sync_interpreter([InputResult(1.0), InputResult(1.0)])(text, "t", **kw).run()
    seg, wait = segment_after(prog.blocks, 2)
    assert wait is None and seg[0].end[:2].tolist() == [15.0, 3.0]


def test_m66_needs_a_mapped_digital_input():
    from hexacnc.daemon.ioprog import check_io
    from hexacnc.gcode import blocks as Bk
    cfg = _cfg(IO)
    b = Bk.Block(Bk.IO, 4, extra={"op": "wait_input", "input": "digital", "index": 2, "mode": "high"})
    with pytest.raises(GcodeError, match="digital input 2 is not mapped") as ei:
        check_io(cfg, [b], waits=True)
    assert ei.value.line == 4
    b.extra["index"] = 3
    check_io(cfg, [b], waits=True)
    with pytest.raises(GcodeError, match="M66 P3"):
        check_io(cfg, [b])
