"""Streaming interpretation of program text held in memory (an uploaded program): the same
:class:`~hexacnc.gcode.stream.BlockStream` as a file, over the text's UTF-8 bytes, so that the blocks in use
are bounded by the window (the text itself is ~30 bytes per line)."""
from __future__ import annotations

import io
from pathlib import Path

from ..errors import GcodeError
from .stream import BlockStream, _FileLines


class _TextLines(_FileLines):
    """:class:`~hexacnc.gcode.stream._FileLines` over bytes in memory (the first pass reads them in
    chunks too, so that its temporary arrays stay small whatever the program's length)."""

    def __init__(self, data: bytes, window: int):
        self.data = data
        super().__init__(Path("<text>"), window)

    def _open(self):
        return io.BytesIO(self.data)

    def _read(self, lo: int, hi: int) -> bytes:
        return self.data[lo:hi]


def iter_text_blocks(text: str, name: str, *, window_lines: int = 4096, queue_batches: int = 4,
                     prepare=None, **kw) -> BlockStream:
    """Stream the blocks of program ``text`` (keywords of :func:`~hexacnc.gcode.parse_program`); errors are
    raised from ``next()`` where they happen, after the blocks before them.  ``prepare``: called with the
    interpreter before it starts (a modal state carried over from an earlier program)."""
    if not 64 <= int(window_lines) <= 10_000_000:
        raise GcodeError(f"window_lines {window_lines} must be 64..10000000", None, None, "value")
    data = text.encode("utf-8") if isinstance(text, str) else bytes(text)
    if data and not data.endswith(b"\n"):
        data += b"\n"
    lines = _TextLines(data, int(window_lines))
    return BlockStream(Path(name), name, int(window_lines), int(queue_batches), kw, lines=lines, prepare=prepare)
