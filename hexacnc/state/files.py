"""The persistent files, in LinuxCNC's formats, written atomically.

* ``tool.tbl``: one tool a line, ``T<n> P<pocket> Z<length mm> D<diameter mm> ;comment`` (other
  LinuxCNC words X Y A B C U V W I J Q are read and ignored).
* ``hexacnc.var``: ``<number><TAB><value>`` a line, sorted (LinuxCNC's var file).

Writing goes to a temporary file in the same directory, fsync, then ``os.replace``: a reader or a
crash sees the old file or the new one, never half of one.  Reading errors name the file and line.
"""
from __future__ import annotations

import math
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

from ..errors import DataError

#: tool numbers accepted (LinuxCNC: 0 is "no tool")
MAX_TOOL = 99999
#: the largest tool table / var file read (bytes): bounded memory whatever is on disk
MAX_FILE_BYTES = 4 * 1024 * 1024
_WORD = re.compile(r"([A-Za-z])\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)")


@dataclass(frozen=True)
class ToolEntry:
    """One tool: length along the tool axis (G43 H), diameter, pocket, comment."""
    tool: int
    pocket: int = 0
    z_mm: float = 0.0
    diameter_mm: float = 0.0
    comment: str = ""


def _read_text(path: Path) -> str | None:
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        return None
    if size > MAX_FILE_BYTES:
        raise DataError(f"{path}: {size} bytes, more than the {MAX_FILE_BYTES} accepted")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read: {exc}") from exc


def atomic_write(path: Path, text: str) -> None:
    """Replace ``path`` by ``text`` atomically (temporary file, fsync, rename, fsync of the directory)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + path.name + ".", suffix=".tmp", dir=str(path.parent))
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    try:
        dfd = os.open(str(path.parent), os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass


def check_tool(e: ToolEntry, where: str = "tool") -> ToolEntry:
    """Raise DataError unless ``e`` is a valid tool entry."""
    if not (isinstance(e.tool, int) and 1 <= e.tool <= MAX_TOOL):
        raise DataError(f"{where}: tool number {e.tool!r} must be an integer 1..{MAX_TOOL}")
    if not (isinstance(e.pocket, int) and 0 <= e.pocket <= MAX_TOOL):
        raise DataError(f"{where}: T{e.tool}: pocket {e.pocket!r} must be an integer 0..{MAX_TOOL}")
    if not (math.isfinite(e.z_mm) and -1000.0 <= e.z_mm <= 1000.0):
        raise DataError(f"{where}: T{e.tool}: length Z {e.z_mm!r} must be in [-1000, 1000] mm")
    if not (math.isfinite(e.diameter_mm) and 0.0 <= e.diameter_mm <= 1000.0):
        raise DataError(f"{where}: T{e.tool}: diameter D {e.diameter_mm!r} must be in [0, 1000] mm")
    if "\n" in e.comment or "\r" in e.comment or len(e.comment) > 200:
        raise DataError(f"{where}: T{e.tool}: comment must be one line of at most 200 characters")
    return e


def parse_tool_table(text: str, where: str) -> dict[int, ToolEntry]:
    out: dict[int, ToolEntry] = {}
    for num, raw in enumerate(text.splitlines(), 1):
        body, _, comment = raw.partition(";")
        body = body.strip()
        if not body:
            continue
        words: dict[str, float] = {}
        pos = 0
        for m in _WORD.finditer(body):
            if body[pos:m.start()].strip():
                raise DataError(f"{where}:{num}: cannot read {body[pos:m.start()].strip()!r}")
            words[m.group(1).upper()] = float(m.group(2))
            pos = m.end()
        if body[pos:].strip():
            raise DataError(f"{where}:{num}: cannot read {body[pos:].strip()!r}")
        if "T" not in words:
            raise DataError(f"{where}:{num}: no T word")
        t, p = words["T"], words.get("P", words["T"])
        if t != int(t) or p != int(p):
            raise DataError(f"{where}:{num}: T and P must be integers")
        e = check_tool(ToolEntry(int(t), int(p), words.get("Z", 0.0), words.get("D", 0.0), comment.strip()),
                       f"{where}:{num}")
        if e.tool in out:
            raise DataError(f"{where}:{num}: tool T{e.tool} listed twice")
        out[e.tool] = e
    return out


def format_tool_table(tools: dict[int, ToolEntry]) -> str:
    lines = []
    for t in sorted(tools):
        e = tools[t]
        lines.append(f"T{e.tool} P{e.pocket} Z{e.z_mm:.6f} D{e.diameter_mm:.6f} ;{e.comment}".rstrip())
    return "\n".join(lines) + ("\n" if lines else "")


def read_tool_table(path: Path) -> dict[int, ToolEntry] | None:
    """The tool table at ``path`` (None when absent)."""
    text = _read_text(Path(path))
    return None if text is None else parse_tool_table(text, str(path))


def write_tool_table(path: Path, tools: dict[int, ToolEntry]) -> None:
    atomic_write(Path(path), format_tool_table(tools))


def parse_var_file(text: str, where: str, allowed) -> dict[int, float]:
    out: dict[int, float] = {}
    for num, raw in enumerate(text.splitlines(), 1):
        s = raw.split(";")[0].strip()
        if not s:
            continue
        parts = s.split()
        if len(parts) != 2:
            raise DataError(f"{where}:{num}: expected '<number> <value>', got {raw.strip()!r}")
        try:
            k, v = int(parts[0]), float(parts[1])
        except ValueError as exc:
            raise DataError(f"{where}:{num}: expected '<number> <value>', got {raw.strip()!r}") from exc
        if not math.isfinite(v) or abs(v) > 1e9:
            raise DataError(f"{where}:{num}: parameter #{k} value {parts[1]!r} is not a finite number")
        if k in allowed:
            out[k] = v
    return out


def read_var_file(path: Path, allowed) -> dict[int, float] | None:
    """Parameters of the var file at ``path`` restricted to ``allowed`` numbers (None when absent)."""
    text = _read_text(Path(path))
    return None if text is None else parse_var_file(text, str(path), frozenset(allowed))


def write_var_file(path: Path, params: dict[int, float]) -> None:
    atomic_write(Path(path), "".join(f"{k}\t{params[k]:.6f}\n" for k in sorted(params)))
