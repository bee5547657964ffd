"""O-word control flow of the interpreter: structure matching and execution.

``sub/endsub/call/return``, ``if/elseif/else/endif``, ``while/endwhile``,
``do/while``, ``repeat/endrepeat``, ``break``, ``continue``.  Structures are
matched before the program runs (:meth:`FlowMixin._prescan`); at run time each
O-word line returns the index of the next line to execute.
"""
from __future__ import annotations

import re

from ..errors import GcodeError
from .expr import ExprError
from .lexer import Line, Presplit

#: a line starting with an O word (possibly after comments, '/' and an N word)
_O_LINE = re.compile(r"^[ \t]*(?:\([^)\n]*\)[ \t]*)*/?[ \t]*(?:[nN][ \t\d.]*)?[oO][ \t]*[\d<]",
                    re.MULTILINE)
_O_LINE_ONE = re.compile(_O_LINE.pattern)

def oword_indices(text: str, first: int = 0) -> list[int]:
    """Indices (from ``first``) of the lines of ``text`` that start with an O word."""
    pos = 0
    idx = first
    out = []
    for m in _O_LINE.finditer(text):
        idx += text.count("\n", pos, m.start())
        pos = m.start()
        out.append(idx)
    return out


class _Frame:
    __slots__ = ("ret", "L", "saved", "label", "repeat", "line", "autorestore", "loops", "start")

    def __init__(self, ret, L, saved, label, line, loops=None, start=0):
        self.ret = ret
        self.L = L
        self.saved = saved           #: #1..#30 of the caller (None for M98: Fanuc parameters are global)
        self.label = label
        self.repeat: dict[int, int] = {}
        self.line = line
        self.autorestore = None
        self.loops = loops           #: M98 L: passes left (None: an o-word call)
        self.start = start           #: index of the subprogram's O line (M98)


def _label(ln: Line, v: float, letter: str = "o") -> str:
    """A computed subprogram number (o[...] call, M98 P): an integer, as LinuxCNC reads it."""
    n = int(round(v))
    if abs(v - n) > 0.0001 or n < 0:
        raise ln.error(f"subprogram number {v:g} is not a whole number", letter, "word")
    return str(n)


class FlowMixin:
    """O-word handling of :class:`~hexacnc.gcode.interp.Interpreter` (uses its state)."""

    def _prescan(self, text: str, pre: Presplit) -> None:
        """Match O-word structures (if/while/do/repeat/sub) before running."""
        self.jump: dict[int, object] = {}
        self.subs: dict[str, tuple[int, int]] = {}
        self.fsubs: dict[str, int] = {}     #: Fanuc-style subprograms: number -> index of its bare O line
        self.do_end: set[int] = set()
        idxs = pre.oword_lines(_O_LINE_ONE) if pre is not None else None
        if idxs is None:
            idxs = oword_indices(text)
        self._match(idxs, self.main_n if self.stop_at is None else self.stop_at)

    def _match(self, idxs, limit: int) -> None:
        """Match the O-word structures of the lines ``idxs`` (sorted indices below ``limit``)."""
        stack: list[list] = []
        for idx in idxs:
            if idx >= limit:
                break
            ln = self._line(idx)
            if ln.oword is None:
                continue
            kw, label, _n = ln.oword

            def err(msg):
                return GcodeError(msg, idx + 1, ln.column("o"), "flow")

            def pop(opening: tuple[str, ...]):
                if not stack or stack[-1][0] not in opening or stack[-1][1] != label:
                    what = f"o{stack[-1][1]} {stack[-1][0]} (line {stack[-1][2] + 1})" if stack else "nothing"
                    raise err(f"o{label} {kw} does not close {what}")
                return stack.pop()

            if kw == "fanuc":     # the first O-number of a name is the one M98 finds (as LinuxCNC)
                self.fsubs.setdefault(label, idx)
            elif kw == "sub":
                if any(s[0] == "sub" for s in stack):
                    raise err(f"o{label} sub defined inside another subroutine")
                if label in self.subs:
                    raise err(f"subroutine o{label} defined twice")
                stack.append(["sub", label, idx])
            elif kw == "endsub":
                s = pop(("sub",))
                self.subs[label] = (s[2], idx)
                self.jump[s[2]] = idx
            elif kw == "if":
                stack.append(["if", label, idx, []])
            elif kw in ("elseif", "else"):
                if not stack or stack[-1][0] != "if" or stack[-1][1] != label:
                    raise err(f"o{label} {kw} without a matching o{label} if")
                br = stack[-1][3]
                if br and self._line(br[-1]).oword[0] == "else":
                    raise err(f"o{label} {kw} after o{label} else")
                br.append(idx)
            elif kw == "endif":
                s = pop(("if",))
                chain = s[3] + [idx]
                self.jump[s[2]] = chain[0]
                for a, b in zip(chain[:-1], chain[1:]):
                    self.jump[a] = (b, idx)
            elif kw == "while":
                if stack and stack[-1][0] == "do" and stack[-1][1] == label:
                    s = stack.pop()
                    self.jump[s[2]] = idx
                    self.jump[idx] = s[2]
                    self.do_end.add(idx)
                else:
                    stack.append(["while", label, idx])
            elif kw == "endwhile":
                s = pop(("while",))
                self.jump[s[2]] = idx
                self.jump[idx] = s[2]
            elif kw == "do":
                stack.append(["do", label, idx])
            elif kw == "repeat":
                stack.append(["repeat", label, idx])
            elif kw == "endrepeat":
                s = pop(("repeat",))
                self.jump[s[2]] = idx
                self.jump[idx] = s[2]
            elif kw in ("break", "continue"):
                for s in reversed(stack):
                    if s[0] in ("while", "do", "repeat") and s[1] == label:
                        self.jump[idx] = s[2]
                        break
                else:
                    raise err(f"o{label} {kw} outside an o{label} while/do/repeat loop")
            elif kw == "return":     # LinuxCNC: any label, anywhere inside a subroutine
                if not any(s[0] == "sub" for s in stack):
                    raise err(f"o{label} return outside a subroutine")
        if stack:
            s = stack[-1]
            ln = self._line(s[2])
            raise GcodeError(f"o{s[1]} {s[0]} is never closed", s[2] + 1, ln.column("o"), "flow")

    # -- Fanuc-style subprograms: M98 P L, M99 ---------------------------------------------
    def _return(self, ln: Line) -> int:
        fr = self.frames[-1]
        if fr.autorestore is not None:
            self._restore(ln, fr.autorestore)
        self.saved_modal.pop(len(self.frames), None)
        self.frames.pop()
        self.L = fr.L
        if fr.saved is not None:
            self.P[1:31] = fr.saved
        return fr.ret

    def _fanuc(self, ln: Line, pc: int, kw: str) -> int:
        """M98 P<number> [L<passes>] calls subprogram O<number> (#1..#30 stay global); M99 returns."""
        if kw == "m99":
            if not self.frames:
                raise ln.error("M99 in the main program (LinuxCNC restarts the program endlessly) is not "
                               "supported", "m99", "unsupported")
            fr = self.frames[-1]
            if fr.loops is None:
                raise ln.error(f"subroutine o{fr.label} sub must end with o{fr.label} endsub or return, not M99",
                               "m99", "flow")
            if fr.loops > 1:
                fr.loops -= 1
                fr.repeat.clear()
                return fr.start + 1
            return self._return(ln)
        vals = self._eval(ln)
        label = _label(ln, vals["p"], "p")
        loops = vals.get("l", 1.0)
        if loops != int(loops) or loops < 0:
            raise ln.error(f"M98 L{loops:g}: the number of passes must be a whole number >= 0", "l", "word")
        start = self.fsubs.get(label)
        if start is None:
            what = (f"O{label} is an o-word subroutine (o{label} sub): call it with o{label} call"
                    if label in self.subs else f"M98 P{label}: subprogram O{label} is not defined in this program")
            raise ln.error(what, "p", "flow")
        if loops == 0:
            return pc + 1
        if len(self.frames) >= self.max_depth:
            raise ln.error(f"subroutine calls nested deeper than {self.max_depth}", "m98", "runaway")
        self.frames.append(_Frame(pc + 1, self.L, None, label, ln.num, int(loops), start))
        self.L = {}
        return start + 1

    # -- O-words --------------------------------------------------------------------
    def _ovals(self, ln: Line) -> tuple:
        if ln.fn is None:
            return ()
        try:
            res = ln.fn(self.P, self.L, self.G, self._sys, ln.k)
        except (KeyError, ArithmeticError, ValueError, ExprError, IndexError, TypeError) as exc:
            raise self._expr_error(ln, exc) from None
        for v in res:
            if not -1e300 < v < 1e300:
                raise ln.error(f"value {v!r} is not a finite number", "o", "expression")
        return res

    def _oword(self, ln: Line, pc: int) -> int:
        kw, label, _n = ln.oword
        self.line_now = ln.num
        jump = self.jump
        if ln.comments:
            self._comments(ln)
        if self.seek and kw not in ("elseif", "else", "endif"):
            raise ln.error("internal: seeking an O-word branch", "o", "flow")
        if kw == "sub":
            return jump[pc] + 1
        if kw in ("endsub", "return"):
            vals = self._ovals(ln)
            if not self.frames:
                raise ln.error(f"o{label} {kw} reached outside a subroutine call", "o", "flow")
            if self.frames[-1].loops is not None:
                raise ln.error(f"Fanuc-style subprogram O{self.frames[-1].label} (called by M98) must end "
                               f"with M99, not o{label} {kw}", "o", "flow")
            self.ret_value, self.ret_flag = (vals[0], 1.0) if vals else (0.0, 0.0)
            return self._return(ln)
        if kw in ("fanuc", "m98", "m99"):
            if not self.fanuc_subs:
                what = "a bare O-number" if kw == "fanuc" else kw.upper()
                raise ln.error(f"Fanuc-style subprograms are disabled (fanuc_subs off), but found {what}",
                               "o" if kw == "fanuc" else kw, "flow")
            if kw == "fanuc":    # a bare O-number run into: LinuxCNC goes on into it
                return pc + 1
            return self._fanuc(ln, pc, kw)
        if kw == "call":
            vals = self._ovals(ln)
            if label is None:
                label, vals = _label(ln, vals[0]), vals[1:]
            sub = self.subs.get(label)
            if sub is None and label in self.fsubs:
                raise ln.error(f"O{label} is a Fanuc-style subprogram (ended by M99): call it with M98 P{label}",
                               "o", "flow")
            if sub is None:
                sub = self._load_sub_file(ln, label)
            if len(self.frames) >= self.max_depth:
                raise ln.error(f"subroutine calls nested deeper than {self.max_depth}", "o", "runaway")
            self.frames.append(_Frame(pc + 1, self.L, self.P[1:31], label, ln.num))
            self.L = {}
            args = list(vals) + [0.0] * (30 - len(vals))
            self.P[1:31] = args
            return sub[0] + 1
        if kw == "if":
            if self._ovals(ln)[0] != 0.0:
                return pc + 1
            self.seek = True
            return jump[pc]
        if kw == "elseif":
            nxt, endif = jump[pc]
            if not self.seek:
                return endif + 1
            if self._ovals(ln)[0] != 0.0:
                self.seek = False
                return pc + 1
            return nxt
        if kw == "else":
            if not self.seek:
                return jump[pc][1] + 1
            self.seek = False
            return pc + 1
        if kw == "endif":
            self.seek = False
            return pc + 1
        if kw == "while":
            if pc in self.do_end:
                return jump[pc] + 1 if self._ovals(ln)[0] != 0.0 else pc + 1
            return pc + 1 if self._ovals(ln)[0] != 0.0 else jump[pc] + 1
        if kw == "endwhile":
            return jump[pc]
        if kw == "do":
            return pc + 1
        rep = self.frames[-1].repeat if self.frames else self._top_repeat
        if kw == "repeat":
            v = self._ovals(ln)[0]
            count = int(v)
            if count <= 0:
                return jump[pc] + 1
            rep[pc] = count
            return pc + 1
        if kw == "endrepeat":
            start = jump[pc]
            left = rep.get(start, 1) - 1
            if left > 0:
                rep[start] = left
                return start + 1
            rep.pop(start, None)
            return pc + 1
        start = jump[pc]
        skw = self._line(start).oword[0]
        end = jump[start]
        if kw == "break":
            rep.pop(start, None)
            return end + 1
        # continue
        if skw == "while":
            return start
        return end  # do: evaluate the closing while; repeat: count down at endrepeat
