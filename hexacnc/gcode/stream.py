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
point it happens (the blocks before it have been delivered).
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


class _FileLines:
    """Random access to the lines of a file through a window of ``window`` lines."""

    def __init__(self, path: Path, window: int):
        self.path = path
        self.window = window
        self.offsets: list[int] = []      # byte offset of line k * window
        self.owords: dict[int, str] = {}  # O-word lines (structure), kept
        self.extra: list[str] = []        # lines of subroutine files appended behind the program
        self.n = 0
        self.first_nonblank: tuple[int, str] | None = None
        self.percent: list[int] = []
        self._lo = 0
        self._cur: list[str] = []
        self._pre = None
        self._scan()

    def _open(self):
        """The program's bytes as a binary file (a subclass may serve them from memory)."""
        return open(self.path, "rb")

    def _scan(self) -> None:
        pos = 0
        with self._open() as f:
            for raw in f:
                if self.n % self.window == 0:
                    self.offsets.append(pos)
                pos += len(raw)
                line = raw.decode("utf-8", errors="replace").rstrip("\n")
                t = line.strip()
                if t:
                    if self.first_nonblank is None:
                        self.first_nonblank = (self.n, t)
                    if t == "%":
                        self.percent.append(self.n)
                    if ("o" in line or "O" in line) and _O_LINE_ONE.match(line):
                        self.owords[self.n] = line
                self.n += 1

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
        chunk = idx // self.window
        with self._open() as f:
            f.seek(self.offsets[chunk])
            cur = []
            for _ in range(self.window):
                raw = f.readline()
                if not raw:
                    break
                cur.append(raw.decode("utf-8", errors="replace").rstrip("\n"))
        self._lo, self._cur, self._pre = chunk * self.window, cur, None
        return self._cur[idx - self._lo]

    def parsed_line(self, idx: int):
        """Parsed line ``idx`` of the program (shapes split per window, as the whole-text path does)."""
        if idx >= self.n:
            return parse_line(self.extra[idx - self.n], idx + 1)
        k = idx - self._lo
        if not 0 <= k < len(self._cur):
            self[idx]
            k = idx - self._lo
        if self._pre is None:
            self._pre = Presplit("\n".join(self._cur), self._cur, self._lo)
        return self._pre.line(k)


class _Parsed:
    """Bounded cache of parsed lines (a dict cleared when full)."""

    def __init__(self, limit: int):
        self.d: dict[int, object] = {}
        self.limit = limit

    def __getitem__(self, idx):
        return self.d.get(idx)

    def get(self, idx):
        return self.d.get(idx)

    def __setitem__(self, idx, ln) -> None:
        if len(self.d) >= self.limit:
            self.d.clear()
        self.d[idx] = ln

    def extend(self, _items) -> None:
        pass


class _StreamInterpreter(Interpreter):
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
        self._it.parsed = _Parsed(2 * window_lines)
        if prepare is not None:
            prepare(self._it)
        self._q: queue.Queue = queue.Queue(maxsize=queue_batches)
        self._stop = False
        self.program: Program | None = None
        self._batch: list = []
        self._i = 0
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

    def __iter__(self):
        return self

    def __next__(self):
        while self._i >= len(self._batch):
            item = self._q.get()
            if item is _DONE:
                self._thread.join()
                raise StopIteration
            if isinstance(item, GcodeError):
                self._thread.join()
                raise item
            self._batch, self._i = item, 0
        b = self._batch[self._i]
        self._i += 1
        return b

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
