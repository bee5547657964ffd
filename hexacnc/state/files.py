"""The persistent files, in LinuxCNC's formats, written atomically.

* ``tool.tbl``: one tool a line, ``T<n> P<pocket> Z<length mm> D<diameter mm> ;comment`` (and
  LinuxCNC's X Y I J Q, kept; A B C U V W read and ignored), through the interpreter's codec
  (:mod:`hexacnc.gcode.state`): one format, one :class:`ToolEntry`, for programs and the operator.
* ``hexacnc.var``: ``<number><TAB><value>`` a line, sorted (LinuxCNC's var file).

Writing goes to a temporary file in the same directory, fsync, then ``os.replace``: a reader or a
crash sees the old file or the new one, never half of one.  Reading errors name the file and line.
"""
from __future__ import annotations

import math
from pathlib import Path

from ..csvio import atomic_write_bytes
from ..errors import DataError, GcodeError
from ..gcode.state import ToolEntry, format_tool_table
from ..gcode.state import parse_tool_table as gcode_tool_table

#: tool numbers accepted (LinuxCNC: 0 is "no tool")
MAX_TOOL = 99999
#: the largest tool table / var file read (bytes): bounded memory whatever is on disk
MAX_FILE_BYTES = 4 * 1024 * 1024


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
    atomic_write_bytes(path, text.encode("utf-8"), make_parents=True)


def check_tool(e: ToolEntry, where: str = "tool") -> ToolEntry:
    """Raise DataError unless ``e`` is a valid tool entry."""
    if not (isinstance(e.tool, int) and 1 <= e.tool <= MAX_TOOL):
        raise DataError(f"{where}: tool number {e.tool!r} must be an integer 1..{MAX_TOOL}")
    if not (isinstance(e.pocket, int) and 0 <= e.pocket <= MAX_TOOL):
        raise DataError(f"{where}: T{e.tool}: pocket {e.pocket!r} must be an integer 0..{MAX_TOOL}")
    for letter, v in (("Z", e.z_offset_mm), ("X", e.x_offset_mm), ("Y", e.y_offset_mm)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and -1000.0 <= v <= 1000.0):
            raise DataError(f"{where}: T{e.tool}: offset {letter} {v!r} must be in [-1000, 1000] mm")
    if not (math.isfinite(e.diameter_mm) and 0.0 <= e.diameter_mm <= 1000.0):
        raise DataError(f"{where}: T{e.tool}: diameter D {e.diameter_mm!r} must be in [0, 1000] mm")
    if "\n" in e.comment or "\r" in e.comment or len(e.comment) > 200:
        raise DataError(f"{where}: T{e.tool}: comment must be one line of at most 200 characters")
    return e


def parse_tool_table(text: str, where: str) -> dict[int, ToolEntry]:
    """The tool table in ``text`` (LinuxCNC format, read by the interpreter's codec), each entry
    range-checked; a tool listed twice is refused.  Errors name ``where`` and the line."""
    seen: set[int] = set()

    def check(e: ToolEntry, num: int) -> None:
        check_tool(e, f"{where}:{num}")
        if e.tool in seen:
            raise DataError(f"{where}:{num}: tool T{e.tool} listed twice")
        seen.add(e.tool)

    try:
        return gcode_tool_table(text, where, check)
    except GcodeError as exc:
        raise DataError(f"{where}:{exc.line}: {exc.bare_message.removeprefix(where + ': ')}") from None


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
