"""Small CSV helpers: strict numeric tables in, atomic files out."""
from __future__ import annotations

import csv
import io
import math
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from .errors import DataError


def read_numeric_csv(path: str | os.PathLike, required: list[str], optional: list[str] = (),
                     allow_empty: bool = False) -> tuple[np.ndarray, list[str], list[str]]:
    """Read a CSV with a header; return (rows x required-columns array, header, ignored columns).

    Every required cell must be a finite number; errors name file, row (1-based
    data row, header is row 0... reported as file line) and column.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise DataError(f"{p}: cannot read: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise DataError(f"{p}: not a UTF-8 text file") from exc
    reader = csv.reader(io.StringIO(text))
    try:
        header = next(reader)
    except StopIteration:
        raise DataError(f"{p}: empty file, expected a header with columns {', '.join(required)}") from None
    header = [h.strip() for h in header]
    if len(set(header)) != len(header):
        dup = sorted({h for h in header if header.count(h) > 1})
        raise DataError(f"{p}: duplicate column(s) in header: {', '.join(dup)}")
    missing = [c for c in required if c not in header]
    if missing:
        raise DataError(f"{p}: missing column(s) {', '.join(missing)}; header has {', '.join(header) or 'nothing'}")
    idx = [header.index(c) for c in required]
    ignored = [h for h in header if h not in required and h not in optional]
    rows = []
    for lineno, rec in enumerate(reader, start=2):
        if not rec or all(not c.strip() for c in rec):
            continue
        if len(rec) != len(header):
            raise DataError(f"{p}: line {lineno}: {len(rec)} fields, header has {len(header)}")
        vals = []
        for c, j in zip(required, idx):
            cell = rec[j].strip()
            try:
                v = float(cell)
            except ValueError:
                raise DataError(f"{p}: line {lineno}, column {c}: {cell!r} is not a number") from None
            if not math.isfinite(v):
                raise DataError(f"{p}: line {lineno}, column {c}: {cell!r} is not finite")
            vals.append(v)
        rows.append(vals)
    if not rows and not allow_empty:
        raise DataError(f"{p}: no data rows after the header")
    return np.array(rows, dtype=float).reshape(len(rows), len(required)), header, ignored


def format_csv(header: list[str], rows) -> str:
    """CSV text; floats written with ``repr`` (shortest exact round trip)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in rows:
        w.writerow([repr(float(v)) if isinstance(v, (float, np.floating)) else v for v in r])
    return buf.getvalue()


def atomic_write_bytes(path: str | os.PathLike, data: bytes, make_parents: bool = False) -> None:
    """Write ``data`` to ``path`` through a temp file in the same directory, fsync and ``os.replace``
    (then fsync of the directory): a reader or a crash sees the old file or the new one, never half."""
    p = Path(path)
    d = p.parent if str(p.parent) else Path(".")
    try:
        if make_parents:
            d.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=d)
    except OSError as exc:
        raise DataError(f"{p}: cannot write: {exc.strerror or exc}") from exc
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    try:
        dfd = os.open(str(d), os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass


def write_text_atomic(path: str | os.PathLike | None, text: str) -> None:
    """Write ``text`` to ``path`` atomically (temp file + rename); ``None`` or ``-``: stdout."""
    if path is None or str(path) == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    atomic_write_bytes(path, text.encode("utf-8"))
