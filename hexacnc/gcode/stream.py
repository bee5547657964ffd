"""Streaming interpretation: blocks of a file of any length with bounded memory.

``iter_blocks(source, name, window_lines=..., **parse_program_keywords)``
returns a :class:`BlockStream`, an iterator of :class:`~hexacnc.gcode.blocks.Block`
in program order.  The file is read twice: a first pass notes where every
``window_lines`` lines start (byte offsets), the O-word lines (kept, so that
loops and subroutines can jump back) and the ``%`` wrappers; then the
interpreter runs in a helper thread and hands over blocks in batches through
a queue of ``queue_batches`` batches, so the memory in use is proportional to
the window and the queue, not to the file.  Lines executed again (loops,
subroutines) are re-read from the file window by window.

After the iterator is exhausted, ``stream.program`` is the
:class:`~hexacnc.gcode.interp.Program` with everything but the blocks
(``blocks`` is empty; ``messages``, ``end_reason``, ``final_pose``,
``final_state`` ...).  An interpretation error is raised from ``next()`` at the
point it happens: after the blocks of the batches handed over before it (the
blocks of the batch in progress, at most 4096, are not delivered).

Parsed lines are kept only where a line can run again (from the first O-word
line on; see :class:`_Parsed`): the lines of a plain CAM file are freed as soon
as they have run.
"""
from __future__ import annotations

import os
import queue
import threading
import time
from pathlib import Path

import numpy as np

from ..errors import GcodeError
from .flow import _O_LINE_ONE
from .interp import Interpreter, Program
from .lexer import Presplit, parse_line

_DONE = object()


#: bytes read at a time by the first pass over a file
SCAN_CHUNK_BYTES = 1 << 20


class _FileLines:
    """Random access to the lines of a file through a window of ``window`` lines."""

    def __init__(self, path: Path, window: int):
        self.path = path
        self.window = window
        self.offsets: list[int] = []      # byte offset of line k * window
        self.owords: dict[int, str] = {}  # O-word lines (structure), kept
        self.extra: list[str] = []        # lines of subroutine files appended behind the program
        self.n = 0
        self.size = 0                     # bytes of the program
        self.first_nonblank: tuple[int, str] | None = None
        self.percent: list[int] = []
        self._lo = 0
        self._cur: list[str] = []
        self._text = ""
        self._pre = None
        self._scan()

    def _open(self):
        """The program's bytes as a binary file (a subclass may serve them from memory)."""
        return open(self.path, "rb")

    def _read(self, lo: int, hi: int) -> bytes:
        """Bytes ``lo``..``hi`` of the program."""
        with self._open() as f:
            f.seek(lo)
            return f.read(hi - lo)

    def _scan(self) -> None:
        """First pass: the file read ``SCAN_CHUNK_BYTES`` at a time, its whole lines noted by :meth:`_note`
        (a line cut by a chunk's end waits for the next chunk)."""
        rest: list[bytes] = []
        with self._open() as f:
            while True:
                data = f.read(SCAN_CHUNK_BYTES)
                if not data:
                    break
                cut = data.rfind(b"\n") + 1
                if not cut:
                    rest.append(data)
                    continue
                head = data[:cut] if cut < len(data) else data
                self._note(b"".join(rest + [head]) if rest else head)
                rest = [data[cut:]] if cut < len(data) else []
        if rest:                          # a last line without a newline
            self._note(b"".join(rest) + b"\n")
            self.size -= 1

    def _note(self, buf: bytes) -> None:
        """Note the lines of ``buf`` (whole lines, each ending with a newline), which follow the lines
        noted so far: window offsets, ``%`` lines, O-word lines (kept), the first non-blank line.  Array
        operations find the candidates; only lines with a ``%``, an ``o`` or an ``O`` are decoded."""
        arr = np.frombuffer(buf, dtype=np.uint8)
        nl = np.flatnonzero(arr == 10)
        starts = np.empty(nl.size, dtype=np.int64)
        starts[:1] = 0
        starts[1:] = nl[:-1] + 1
        first = (-self.n) % self.window
        self.offsets.extend((starts[first::self.window] + self.size).tolist())

        def line(k: int) -> str:
            return buf[int(starts[k]):int(nl[k])].decode("utf-8", errors="replace")

        for k in np.unique(np.searchsorted(nl, np.flatnonzero(arr == 37))).tolist():     # '%'
            if line(k).strip() == "%":
                self.percent.append(self.n + k)
        for k in np.unique(np.searchsorted(nl, np.flatnonzero((arr == 111) | (arr == 79)))).tolist():  # o O
            text = line(k)
            if _O_LINE_ONE.match(text):
                self.owords[self.n + k] = text
        if self.first_nonblank is None:
            for k in range(nl.size):
                t = line(k).strip()
                if t:
                    self.first_nonblank = (self.n + k, t)
                    break
        self.n += int(nl.size)
        self.size += len(buf)

    def __len__(self) -> int:
        return self.n + len(self.extra)

    def extend(self, lines) -> None:
        self.extra.extend(lines)

    def __getitem__(self, idx: int) -> str:
        if idx >= self.n:
            return self.extra[idx - self.n]
        k = idx - self._lo
        if 0 <= k < len(self._cur):
            return self._cur[k]
        o = self.owords.get(idx)
        if o is not None:
            return o
        self._load(idx // self.window)
        return self._cur[idx - self._lo]

    def _load(self, chunk: int) -> None:
        """Make window ``chunk`` the current one: its bytes read at once and decoded as a whole."""
        lo = self.offsets[chunk]
        hi = self.offsets[chunk + 1] if chunk + 1 < len(self.offsets) else self.size
        text = self._read(lo, hi).decode("utf-8", errors="replace")
        if text.endswith("\n"):
            text = text[:-1]
        self._lo, self._cur, self._text, self._pre = chunk * self.window, text.split("\n"), text, None

    def parsed_line(self, idx: int):
        """Parsed line ``idx`` of the program (shapes split per window, as the whole-text path does)."""
        if idx >= self.n:
            return parse_line(self.extra[idx - self.n], idx + 1)
        k = idx - self._lo
        if not 0 <= k < len(self._cur):     # (not through __getitem__: an O-word line comes from self.owords)
            self._load(idx // self.window)
            k = idx - self._lo
        if self._pre is None:
            self._pre = Presplit(self._text, self._cur, self._lo)
        return self._pre.line(k)


class _Parsed(dict):
    """Parsed lines of a streamed program for the run loop: a dict, so that its lookup stays in C, which
    parses a missing line itself (:meth:`__missing__`).  Only lines that can run again are kept (those
    from the first O-word line on, subroutine files included: loops and calls jump back to O-word lines
    only), up to ``limit`` lines, then it is cleared; a program without O-words keeps none, so its
    lines are freed as soon as they have run."""

    def __init__(self, lines: _FileLines, limit: int, parse_other):
        super().__init__()
        self.lines = lines
        self.limit = limit
        self.main_n = lines.n
        self.parse_other = parse_other          #: parsed line of a subroutine file (index >= main_n)
        self.keep_from = min(lines.owords) if lines.owords else lines.n

    def __missing__(self, idx: int):
        fl = self.lines
        k = idx - fl._lo
        pre = fl._pre
        if pre is not None and 0 <= k < len(fl._cur):
            ln = pre.line(k)
        elif idx < self.main_n:
            ln = fl.parsed_line(idx)
        else:
            ln = self.parse_other(idx)
        if idx >= self.keep_from:
            self[idx] = ln
        return ln

    def __setitem__(self, idx: int, ln) -> None:
        if len(self) >= self.limit:
            self.clear()
        dict.__setitem__(self, idx, ln)

    def extend(self, _items) -> None:
        """(The whole-program interpreter's list grows with a subroutine file; nothing to do here.)"""


class _StreamInterpreter(Interpreter):
    def _parse_other(self, idx: int):
        """Parsed line ``idx`` of a subroutine file (numbered in its own file)."""
        return parse_line(self.lines[idx], self._num(idx))

    def _find_end(self):
        fl = self.lines
        self.percent_start = None
        if fl.first_nonblank is not None and fl.first_nonblank[1] == "%":
            self.percent_start = fl.first_nonblank[0]
            later = [i for i in fl.percent if i > self.percent_start]
            if not later:
                raise GcodeError("program starts with '%' but has no closing '%' line", fl.n or 1, 1, "syntax")
            return later[0]
        return fl.percent[0] if fl.percent else None


class BlockStream:
    """Iterator of the blocks of a streamed program (see the module docstring)."""

    def __init__(self, path: Path, name: str, window_lines: int, queue_batches: int, kw: dict, lines=None,
                 prepare=None):
        """``lines``: a :class:`_FileLines` over the program (default: over the file ``path``);
        ``prepare``: called with the interpreter before it starts (e.g. to set a modal state)."""
        lines = lines if lines is not None else _FileLines(path, window_lines)
        self._it = _StreamInterpreter(None, name, lines=lines, **kw)
        self._it.parsed = _Parsed(lines, 2 * window_lines, self._it._parse_other)
        if prepare is not None:
            prepare(self._it)
        self._q: queue.Queue = queue.Queue(maxsize=queue_batches)
        self._stop = False
        self.program: Program | None = None
        self._blocks = self._delivered()
        self._thread = threading.Thread(target=self._run, name=f"gcode-stream {name}", daemon=True)
        self._thread.start()

    def _put(self, item) -> None:
        while True:
            if self._stop:
                raise _Stopped()
            try:
                self._q.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def _run(self) -> None:
        it = self._it
        try:
            it.percent_start = None
            it.stop_at = it._find_end()
            it.jump, it.subs, it.do_end, it.fsubs = {}, {}, set(), {}
            it._match(sorted(it.lines.owords), it.main_n if it.stop_at is None else it.stop_at)
            reason, end_line, executed = it._loop(it.lines.parsed_line,
                                                  lambda blocks: self._put(list(blocks)))
            self.program = Program(name=it.name, blocks=[], line_count=it.main_n, lines_executed=executed,
                                   messages=it.messages, end_line=end_line, end_reason=reason,
                                   final_pose=None, units="mm" if it.u == 1.0 else "inch", notes=it.notes,
                                   final_state=it.final_state())
            self.program.final_pose = np.array(it.pos)
            self._put(_DONE)
        except _Stopped:
            return
        except Exception as exc:  # noqa: BLE001 - every failure reaches the consumer, never a hang
            if not isinstance(exc, GcodeError):
                exc = GcodeError(f"internal error while streaming: {type(exc).__name__}: {exc}", None, None,
                                 "internal")
            try:
                self._put(exc)
            except _Stopped:
                return

    def wait_program(self, timeout_s: float = 10.0) -> Program | None:
        """The :class:`Program` summary (messages, final state), waiting for the interpreter thread to
        set it: it does so just before its end marker, so a consumer that stopped at the program's end
        (M2) without taking the marker can ask before it is there. None if the thread ended without it
        (an error) or ``timeout_s`` passed."""
        t_end = time.monotonic() + timeout_s
        while self.program is None and self._thread.is_alive() and time.monotonic() < t_end:
            time.sleep(0.001)
        return self.program

    @property
    def interpreter(self) -> Interpreter:
        """The interpreter (its modal state after the end, once the iterator is exhausted)."""
        return self._it

    def _delivered(self):
        """The blocks of the batches the interpreter thread hands over (a generator: a block costs
        one resumption, the batch is walked in C)."""
        q = self._q
        while True:
            item = q.get()
            if item is _DONE:
                self._thread.join()
                return
            if isinstance(item, GcodeError):
                self._thread.join()
                raise item
            yield from item

    def __iter__(self):
        return self._blocks

    def __next__(self):
        return next(self._blocks)

    def close(self) -> None:
        """Stop the interpreter thread (when not iterating to the end)."""
        self._stop = True
        self._thread.join()

    def __del__(self):
        self._stop = True


class _Stopped(Exception):
    pass


def iter_blocks(source, name: str | None = None, *, window_lines: int = 16384, queue_batches: int = 4,
                **kw) -> BlockStream:
    """Stream the blocks of the program file ``source`` (a path) with memory bounded by the window.

    Keywords are those of :func:`~hexacnc.gcode.parse_program`.  A ``str`` that is
    not an existing file path is taken as program text (written to no file:
    it is interpreted as a whole, then streamed).
    """
    if not 64 <= int(window_lines) <= 10_000_000:
        raise GcodeError(f"window_lines {window_lines} must be 64..10000000", None, None, "value")
    if not 1 <= int(queue_batches) <= 1000:
        raise GcodeError(f"queue_batches {queue_batches} must be 1..1000", None, None, "value")
    if isinstance(source, (str, os.PathLike)) and ("\n" not in str(source)) and Path(source).is_file():
        path = Path(source)
        return BlockStream(path, name or path.name, int(window_lines), int(queue_batches), kw)
    if isinstance(source, str):
        from .interp import parse_program
        prog = parse_program(source, name or "<program>", **kw)
        return _ListStream(prog)
    raise GcodeError(f"iter_blocks needs a file path or program text, got {type(source).__name__}",
                     None, None, "value")


class _ListStream:
    """The same interface over an already interpreted program (text sources)."""

    def __init__(self, prog: Program):
        self.program = Program(**{**vars(prog), "blocks": []})
        self._it = iter(prog.blocks)

    def __iter__(self):
        return self

    def __next__(self):
        return next(self._it)

    def wait_program(self, timeout_s: float = 10.0) -> Program:
        return self.program

    def close(self) -> None:
        pass
