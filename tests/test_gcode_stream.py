"""Streaming interpretation (``iter_blocks``, ``iter_text_blocks``): what the first pass notes, the lines
read window by window, the blocks and errors compared with the whole-program interpreter, and the bounded
cache of parsed lines.  The expected notes are computed here line by line from the raw bytes."""
from __future__ import annotations

import json

import numpy as np
import pytest

from hexacnc.errors import GcodeError
from hexacnc.gcode import iter_blocks, parse_program
from hexacnc.gcode import stream as S
from hexacnc.gcode.flow import _O_LINE_ONE
from hexacnc.gcode.textstream import _TextLines, iter_text_blocks

TEXTS = [
    b"",
    b"G1 X1 F100",                                               # no final newline
    b"%\nG1 X1 F100\no100 sub\nG1 X2\no100 endsub\no100 call\n%\n",
    b"  \n\n\xc2\xa0\nO1 call\n",                                # blank lines (one a no-break space)
    b" % \r\n(comment o)\r\nG0 Z5\r\n%%\r\n",                    # CRLF
    b"G0 X1 (\xff\xfe bad bytes)\n(o100 in a comment)\n  o<x> sub\n/N10 O2 endsub\nM2\n",
    b"\n".join(b"G1 X%d Y%d" % (i, -i) for i in range(40)) + b"\no1 if [1]\nM2\n",
]


def reference_notes(data: bytes, window: int) -> dict:
    """The first pass's notes computed line by line from the bytes."""
    raw = data.split(b"\n")
    if data.endswith(b"\n") or not data:
        raw.pop()
    text = [r.decode("utf-8", errors="replace") for r in raw]
    starts = np.cumsum([0] + [len(r) + 1 for r in raw])[:-1].tolist() if raw else []
    blank = [k for k, t in enumerate(text) if t.strip()]
    return {"n": len(raw), "offsets": starts[::window],
            "owords": {k: t for k, t in enumerate(text) if _O_LINE_ONE.match(t)},
            "percent": [k for k, t in enumerate(text) if t.strip() == "%"],
            "first_nonblank": (blank[0], text[blank[0]].strip()) if blank else None,
            "lines": text}


def notes(fl) -> dict:
    return {"n": fl.n, "offsets": fl.offsets, "owords": fl.owords, "percent": fl.percent,
            "first_nonblank": fl.first_nonblank, "lines": [fl[i] for i in range(fl.n)]}


@pytest.mark.parametrize("chunk", [1, 5, 1 << 20])
@pytest.mark.parametrize("data", TEXTS)
def test_first_pass_notes_what_each_line_says(tmp_path, monkeypatch, data, chunk):
    """File and text in memory, read in chunks of any size (lines cut across chunks), windows of 3 lines."""
    monkeypatch.setattr(S, "SCAN_CHUNK_BYTES", chunk)
    f = tmp_path / "p.ngc"
    f.write_bytes(data)
    want = reference_notes(data, 3)
    assert notes(S._FileLines(f, 3)) == want
    assert notes(_TextLines(data, 3)) == want


def test_lines_read_in_any_order_across_windows(tmp_path):
    data = "".join(f"G1 X{i} (line {i} \u00b5m)\n" for i in range(300)).encode()
    f = tmp_path / "p.ngc"
    f.write_bytes(data)
    fl = S._FileLines(f, 64)
    order = list(range(299, -1, -7)) + list(range(0, 300, 5))
    assert [fl[i] for i in order] == [f"G1 X{i} (line {i} \u00b5m)" for i in order]
    assert fl.size == len(data)


LOOP = ["G21 G90 F600", "#<_i> = 0", "o<w> sub", "G1 X[#<_i>] Y[#<_i> * 2]", "o<w> endsub",
        "o100 while [#<_i> LT 150]", "#<_i> = [#<_i> + 1]", "o<w> call", "o100 endwhile"]


def _same(got, whole) -> None:
    assert [(b.kind, b.line) for b in got] == [(b.kind, b.line) for b in whole]
    assert all(b.end is None and a.end is None or np.array_equal(a.end, b.end) for a, b in zip(got, whole))


def test_loop_jumping_back_windows_and_the_cache_bound(tmp_path):
    # the loop body lies windows behind the loop's end; the cache of parsed lines never exceeds 2 windows
    pad = [f"G1 X{i % 17} Y{i % 13}" for i in range(200)]
    text = "\n".join(LOOP[:5] + pad + LOOP[5:] + pad + ["M2"]) + "\n"
    f = tmp_path / "loop.ngc"
    f.write_text(text)
    whole = parse_program(text)
    s = iter_blocks(str(f), window_lines=64)
    peak = 0
    got = []
    for b in s:
        got.append(b)
        peak = max(peak, len(s.interpreter.parsed))
    _same(got, whole.blocks)
    assert 0 < peak <= 128 and s.program.lines_executed == whole.lines_executed
    it = iter_text_blocks(text, "loop.ngc", window_lines=64)
    _same(list(it), whole.blocks)


def test_lines_before_any_o_word_are_not_kept(tmp_path):
    # a program without O-words runs each line once: no parsed line is kept after it ran
    text = "".join(f"G1 X{i + 1} Y{i % 7} F100\n" for i in range(500)) + "M2\n"
    s = iter_text_blocks(text, "plain.ngc", window_lines=64)
    first = next(s)
    assert first.line == 1 and len(s.interpreter.parsed) == 0
    rest = list(s)
    assert [b.line for b in rest] == list(range(2, 502)) and rest[-1].kind == "end"    # M2 on line 501
    assert len(s.interpreter.parsed) == 0
    # with a subroutine at the end, only the lines from its O-word on are kept
    text2 = text.replace("M2\n", "o<w> call\nM2\no<w> sub\nG0 Z5\no<w> endsub\n")
    s = iter_text_blocks(text2, "sub.ngc", window_lines=64)
    list(s)
    assert s.interpreter.parsed and min(s.interpreter.parsed) >= 500


def test_error_after_the_blocks_before_it_and_then_the_end(tmp_path):
    # blocks are handed over in batches of 4096: those of the batches before the bad line arrive first
    text = "".join(f"G1 X{i} F100\n" for i in range(1, 5000)) + "G1 X[1/0]\nG1 X2\n"
    f = tmp_path / "bad.ngc"
    f.write_text(text)
    for s in (iter_blocks(str(f), window_lines=64), iter_text_blocks(text, "bad.ngc", window_lines=64)):
        got = []
        with pytest.raises(GcodeError) as ei:
            for b in s:
                got.append(b)
        assert (ei.value.line, ei.value.code) == (5000, "expression")
        assert len(got) >= 4096 and [b.line for b in got] == list(range(1, len(got) + 1))
        with pytest.raises(StopIteration):        # the stream is over (no hang on a dead thread)
            next(s)


def test_o_word_line_behind_the_window_after_the_cache_was_cleared():
    # the loop's O-word lines are re-read after the cache of 2 windows was cleared (it failed with an
    # IndexError: the O-word line was taken from the notes without loading its window)
    pad = [f"G1 X{i % 17} Y{i % 13}" for i in range(300)]
    text = "\n".join(["F600", "#<n> = 0", "o1 do"] + pad + ["#<n> = [#<n> + 1]", "o1 while [#<n> LT 3]"]
                     + pad + ["M2"]) + "\n"
    whole = parse_program(text)
    _same(list(iter_text_blocks(text, "do.ngc", window_lines=64)), whole.blocks)


def test_next_and_for_share_one_stream():
    text = "".join(f"G1 X{i} F100\n" for i in range(1, 11)) + "M2\n"
    s = iter_text_blocks(text, "p.ngc", window_lines=64)
    a = next(s)
    rest = [b.line for b in s]
    assert a.line == 1 and rest == list(range(2, 12))
    assert s.program.end_reason == "M2"


def test_bench_reports_cpu_rates_of_stream_and_parse():
    from hexacnc.bench import interp as I
    out = I.stream_rss(300, runs=1)
    for mode in ("stream", "stream_text", "parse_program"):
        r = out[mode]
        assert r["blocks"] == 298 and r["end_reason"] == "M2", r
        assert r["cpu_lines_per_s"] >= r["median_cpu_lines_per_s"] > 0 and r["peak_rss_mb"] > 0
    assert out["stream"]["stream_vs_parse_cpu"] > 0
    json.dumps(out)
