"""Subroutine files: ``o<name> call`` of a subroutine not defined in the program.

As LinuxCNC, the file ``<name>.ngc`` is searched in the directories of the
subroutine path (``[gcode] subroutine_path``) in order; it must define
``o<name> sub`` ... ``o<name> endsub``.  Its lines are appended behind the
program (read once per program, bounded in size); errors in it name the file
and its own line numbers.
"""
from __future__ import annotations

from pathlib import Path

from ..errors import GcodeError
from .flow import oword_indices
from .lexer import Line

#: largest subroutine file read (bytes)
MAX_SUB_FILE_BYTES = 16 * 1024 * 1024
#: most subroutine files one program may load
MAX_SUB_FILES = 256


class SubfileMixin:
    """Loading subroutine files for :class:`~hexacnc.gcode.interp.Interpreter`."""

    def _find_sub_file(self, ln: Line, label: str) -> Path:
        if label.isdigit():
            raise ln.error(f"subroutine o{label} is not defined in this program (numbered subroutines are "
                           "not searched in files)", "o", "flow")
        names = [f"{label}.ngc"]
        if self.sub_path:
            for d in self.sub_path:
                for n in names:
                    f = Path(d) / n
                    if f.is_file():
                        return f
        where = ", ".join(self.sub_path) if self.sub_path else "(empty: [gcode] subroutine_path is not set)"
        raise ln.error(f"subroutine o<{label}> is not defined in this program and its file {label}.ngc is "
                       f"not on the subroutine path: {where}", "o", "flow")

    def _load_sub_file(self, ln: Line, label: str) -> tuple[int, int]:
        f = self._find_sub_file(ln, label)
        if len(self.segments) >= MAX_SUB_FILES:
            raise ln.error(f"more than {MAX_SUB_FILES} subroutine files", "o", "runaway")
        try:
            size = f.stat().st_size
            if size > MAX_SUB_FILE_BYTES:
                raise ln.error(f"subroutine file {f} is larger than {MAX_SUB_FILE_BYTES} bytes", "o", "flow")
            text = f.read_text(errors="strict")
        except (OSError, UnicodeDecodeError) as exc:
            raise ln.error(f"cannot read subroutine file {f}: {exc}", "o", "flow") from None
        lines = text.split("\n")
        if lines and lines[-1] == "":
            lines.pop()
        start = len(self.lines)
        self.segments.append((start, str(f)))
        self.lines.extend(lines)
        self.parsed.extend([None] * len(lines))
        before = set(self.subs)
        try:
            self._match(oword_indices(text, start), start + len(lines))
        except GcodeError as exc:
            raise self._in_file(exc, None, str(f)) from None
        sub = self.subs.get(label)
        for other in set(self.subs) - before - {label}:   # as LinuxCNC: only the named subroutine of a
            del self.subs[other]                          # file is known (its other subs are not)
        if sub is None:
            raise ln.error(f"subroutine file {f} does not define o<{label}> sub", "o", "flow")
        return sub

    def _in_file(self, exc: GcodeError, pc, fname: str | None = None) -> GcodeError:
        """``exc`` with the subroutine file named when it happened in one."""
        if fname is None:
            if pc is None or pc < self.main_n or not self.segments:
                return exc
            fname = max((s for s in self.segments if s[0] <= pc), key=lambda s: s[0])[1]
        if fname in str(exc):
            return exc
        new = GcodeError(f"in subroutine file {fname}: {exc.bare_message}", exc.line, exc.column, exc.code)
        return new
