"""Program text in the supervisor without long holds of the interpreter lock.

A ``stop`` runs on its own thread of the supervisor, which shares one interpreter lock (GIL) with the
thread that takes a program.  A single C call over a whole large program holds that lock for its whole
length (on a 1e6-line, 18 MB program: a regular expression search ~0.4-3 s, a join, ``count`` or
``encode`` 10-70 ms), and the stop waits behind it.  Here every pass over a program works in pieces of at
most :data:`SCAN_CHARS` characters, so the lock changes hands between them (within the interpreter's
switch interval), and the text goes to the planning children in pieces (:func:`pieces`), never pickled
as one object.

* :func:`pieces`: a program (str, or the list of chunks of an upload) as a list of pieces;
* :func:`search`: whether a pattern occurs (pieces scanned with an overlap);
* :func:`count_lines`: lines of the program;
* :class:`TextLines`: line ``k`` of the program by index (the operator status' ``block``), its bytes
  and line offsets built piece by piece.
"""
from __future__ import annotations

import numpy as np

#: characters a single pass handles at once (a regular expression over 64 K characters: ~1-3 ms)
SCAN_CHARS = 1 << 16
#: characters of a piece sent to a planning child
PIECE_CHARS = 1 << 20
#: overlap of two scanned pieces (longer than any word the patterns look for)
OVERLAP = 64


def pieces(text) -> list:
    """``text`` (str, or a list of str: the chunks of an upload) as pieces of at most PIECE_CHARS."""
    parts = [text] if isinstance(text, str) else list(text)
    out = []
    for p in parts:
        if len(p) <= PIECE_CHARS:
            out.append(p)
        else:
            out.extend(p[i:i + PIECE_CHARS] for i in range(0, len(p), PIECE_CHARS))
    return out


def joined(text) -> str:
    """The whole text (for the paths that interpret a program as one: MDI, probing, M62-M68)."""
    return text if isinstance(text, str) else "".join(text)


def _scans(parts):
    """(piece, offset) of at most SCAN_CHARS + OVERLAP characters, each overlapping the one before."""
    tail = ""
    for p in parts:
        for i in range(0, len(p), SCAN_CHARS):
            s = p[i:i + SCAN_CHARS]
            yield tail + s
            tail = s[-OVERLAP:]


def search(pattern, text) -> bool:
    """Does the compiled ``pattern`` (matches shorter than OVERLAP) occur in ``text`` (str or pieces)?"""
    return any(pattern.search(s) is not None for s in _scans(pieces(text)))


def scan(patterns: dict, text, abort=None) -> set:
    """The keys of ``patterns`` that occur in ``text``, in one pass.  A pattern is a compiled regular
    expression, or ``(prefilter, pattern)``: ``prefilter(piece)`` a cheap test that is true wherever the
    pattern can match (e.g. its digits, found by a literal search: ~20x faster than a case-insensitive
    alternation), the pattern tried only there.  ``abort()`` (checked between pieces) true ends the
    pass early with :class:`Aborted`."""
    found: set = set()
    tests = {k: (p if isinstance(p, tuple) else (None, p)) for k, p in patterns.items()}
    for s in _scans(pieces(text)):
        if abort is not None and abort():
            raise Aborted()
        for k, (pre, p) in tests.items():
            if k not in found and (pre is None or pre(s)) and p.search(s) is not None:
                found.add(k)
        if len(found) == len(patterns):
            break
    return found


class Aborted(Exception):
    """:func:`scan` ended early by its ``abort``."""


def count_lines(text) -> int:
    """Lines of ``text`` (str or pieces), a last line without a newline included."""
    n, last = 0, ""
    for p in pieces(text):
        for i in range(0, len(p), SCAN_CHARS):
            s = p[i:i + SCAN_CHARS]
            n += s.count("\n")
            last = s[-1:] or last
    return n + (1 if last and last != "\n" else 0)


class TextLines:
    """Lines of a program's text by index, without a list of a million strings: its UTF-8 bytes (in
    pieces) and the offsets of its line ends (a 1e6-line program: its bytes plus 8 MB)."""

    def __init__(self, text):
        chunks, ends, base = [], [], 0
        for p in pieces(text):
            for i in range(0, len(p), SCAN_CHARS):
                b = p[i:i + SCAN_CHARS].encode("utf-8", errors="replace")
                chunks.append(b)
                ends.append(np.flatnonzero(np.frombuffer(b, dtype=np.uint8) == 10) + base)
                base += len(b)
        self.chunks = chunks
        self.starts = np.cumsum([0] + [len(c) for c in chunks])       # byte offset of each chunk
        self.ends = np.concatenate(ends) if ends else np.zeros(0, dtype=np.int64)
        self.size = base
        last_nl = bool(chunks) and chunks[-1].endswith(b"\n")
        self.n = int(self.ends.size) + (1 if base and not last_nl else 0)

    def __len__(self) -> int:
        return self.n

    def _bytes(self, lo: int, hi: int) -> bytes:
        a = int(np.searchsorted(self.starts, lo, side="right")) - 1
        out = []
        while lo < hi and a < len(self.chunks):
            c0 = int(self.starts[a])
            piece = self.chunks[a][lo - c0:hi - c0]
            out.append(piece)
            lo += len(piece)
            a += 1
        return b"".join(out)

    def __getitem__(self, k: int) -> str:
        if not 0 <= k < self.n:
            raise IndexError(k)
        lo = int(self.ends[k - 1]) + 1 if k > 0 else 0
        hi = int(self.ends[k]) if k < self.ends.size else self.size
        return self._bytes(lo, hi).decode("utf-8", errors="replace")


__all__ = ["pieces", "joined", "search", "scan", "Aborted", "count_lines", "TextLines", "SCAN_CHARS", "PIECE_CHARS"]
