"""RS274NGC line lexer (LinuxCNC dialect).

One source line becomes one :class:`Line`: its constant words, its computed
words (``[...]`` expressions, parameters, functions; see :mod:`.expr`)
compiled into one Python function per line *shape*, its parameter
assignments and its O-word statement.  A shape is the stripped line with the
numbers in value positions replaced by a placeholder: CAM output has few
shapes, so each is parsed and compiled once and only its numbers are filled
in per line.  :class:`Presplit` reduces a whole program to shapes in one pass.
Lines are parsed once; loops and subroutines reuse the parsed form.

Columns in errors are 1-based positions in the raw source line.
"""
from __future__ import annotations

import itertools
import operator
import re

from ..errors import GcodeError
from .expr import (
    _CACHE_MAX, _INDEX, _UNSIGNED, MAX_PARAMETER, PREDEFINED, READONLY_PARAMETERS, _Bad, _Ctx, _Ph,
    _param_number, _read_real, compile_template,
)

_WS_DEL = str.maketrans("", "", " \t\r\n\f\v")
_DIGITS = re.compile(r"\d+")
_OWORD = re.compile(r"(elseif|else|endif|endsub|endwhile|endrepeat|sub|call|if|while|do|"
                    r"repeat|break|continue|return)")
#: word letters the dialect knows (others are refused)
_LETTERS = frozenset("abcdefghijklmpqrstxyz")
_FORBIDDEN_LETTERS = {
    "@": "polar coordinates (@ radius) are not supported",
    "^": "polar coordinates (^ angle) are not supported",
    "$": "$ spindle selection (multiple spindles) is not supported",
    "u": "U axis does not exist on a hexapod (axes X Y Z A B C)",
    "v": "V axis does not exist on a hexapod (axes X Y Z A B C)",
    "w": "W axis does not exist on a hexapod (axes X Y Z A B C)",
    "n": "N word must be the first word of a line",
    "o": "O word must be the first word of a line",
}


def strip_with_map(raw: str, lineno: int) -> tuple[str, list[int], list[str]]:
    """Lower-case ``raw`` without whitespace and comments.

    Returns ``(s, cols, comments)``: ``cols[i]`` is the 1-based raw column of
    ``s[i]``; ``comments`` the texts of ``( )`` and ``;`` comments.
    """
    out: list[str] = []
    cols: list[int] = []
    comments: list[str] = []
    i = 0
    n = len(raw)
    while i < n:
        ch = raw[i]
        if ch == "(":
            j = raw.find(")", i + 1)
            if j < 0:
                raise GcodeError("comment opened with '(' is not closed on this line", lineno, i + 1,
                                 "syntax")
            k = raw.find("(", i + 1, j)
            if k >= 0:
                raise GcodeError("nested comment: '(' inside a comment", lineno, k + 1, "syntax")
            comments.append(raw[i + 1:j])
            i = j + 1
            continue
        if ch == ";":
            comments.append(raw[i + 1:])
            break
        if ch == ")":
            raise GcodeError("')' without a matching '('", lineno, i + 1, "syntax")
        if ch in " \t\r\n\f\v":
            i += 1
            continue
        if not (" " < ch < "\x7f"):
            raise GcodeError(f"bad character {ch!r} outside a comment", lineno, i + 1, "syntax")
        out.append(ch.lower())
        cols.append(i + 1)
        i += 1
    return "".join(out), cols, comments


def raw_column(raw: str, lineno: int, pos: int) -> int:
    """1-based raw column of index ``pos`` of the stripped line."""
    try:
        _s, cols, _c = strip_with_map(raw, lineno)
    except GcodeError as exc:
        return exc.column or 1
    if pos < len(cols):
        return cols[pos]
    return (cols[-1] + 1) if cols else 1


# -- the parsed line --------------------------------------------------------
class Line:
    """One parsed source line (see module docstring)."""

    __slots__ = ("num", "raw", "delete", "words", "gs", "ms", "dyn", "fn", "k", "assigns",
                 "oword", "comments", "cols", "axes", "plain", "empty", "gmot", "srcs", "arcok")

    def __init__(self, num: int, raw: str):
        self.num = num
        self.raw = raw
        self.delete = False
        self.words: dict[str, float] = {}
        self.gs: list[int] = []          #: G codes x10 (G90.1 -> 901), constant ones
        self.ms: list[int] = []          #: M codes, constant ones
        self.dyn: list[str] = []         #: letters (or '#n' / '=name' targets) of computed values
        self.fn = None                   #: compiled evaluator of the computed values
        self.k: tuple = ()
        self.assigns: list[tuple] = []   #: (kind, target, slot) kind: 'n' numbered, 'i' indirect, 'l'/'g' named
        self.oword: tuple | None = None  #: (keyword, label, slots of its values)
        self.comments: list[str] = []
        self.cols: dict[str, int] = {}   #: letter -> index in the stripped line
        self.axes: tuple = ()            #: ((axis index, letter), ...)
        self.plain = False               #: only axis/F words: fast path (modal G0/G1)
        self.empty = False
        self.gmot = None                 #: G0/G1 (0/10) as the only code with axis/F words: fast path
        self.srcs: tuple = ()            #: source of each computed value (to locate errors)
        self.arcok = False               #: only axis/F/I/J/K/R/P words: fast path for modal arcs

    def column(self, letter: str) -> int:
        cols = self.cols
        if cols is None:  # built from a shape: re-parse in full for the positions
            try:
                s, _c, comments = strip_with_map(self.raw, self.num)
                cols = _parse_full(self.raw, self.num, s, comments).cols
            except GcodeError:
                cols = {}
        return raw_column(self.raw, self.num, cols.get(letter, 0))

    def error(self, message: str, letter: str | None = None, code: str = "syntax") -> GcodeError:
        col = self.column(letter) if letter is not None else 1
        return GcodeError(message, self.num, col, code)


_AXIS_INDEX = {"x": 0, "y": 1, "z": 2, "a": 3, "b": 4, "c": 5}


# -- line parser ------------------------------------------------------------
def _gcode_int(v: float) -> int | None:
    """G/M value -> code x10 (G59.1 -> 591) or None when not a multiple of 0.1."""
    if not 0.0 <= v < 1e6:
        return None
    t = round(v * 10.0)
    if abs(v * 10.0 - t) > 0.001 or t < 0:
        return None
    return int(t)


#: numbers in value position (after a value word letter, an operator, '[' or '=')
#: (a malformed run of digits and dots makes float() fail: the line is then parsed in full)
_SHAPE_SPLIT = re.compile(r"(?<=[abcdefhijklnpqrstxyz\[*/+\-=])([-+]?[\d.]+)")
_NAMED_DIGIT = re.compile(r"<[^>]*[\d\x01][^>]*>")
_SHAPES: dict[str, tuple | None] = {}
_COMMENT = re.compile(r"\(([^()]*)\)")
_OSHAPE = re.compile(r"/?(?:n\x01)?o[\d<]")


def parse_line(raw: str, num: int) -> Line:
    """Parse one raw source line (1-based number ``num``).

    Lines are reduced to a *shape* (numbers in value positions replaced by a
    placeholder); a shape is parsed once and then only its numbers are filled
    in.  Any problem falls back to the full parse, which reports it.
    """
    comments = None
    if "(" in raw or ";" in raw or ")" in raw or not raw.isascii():
        parts = _COMMENT.split(raw) if ";" not in raw else None
        if parts is not None and len(parts) > 1:
            rest = "".join(parts[0::2])
            if "(" in rest or ")" in rest or not rest.isascii():
                s, _cols, comments = strip_with_map(raw, num)
            else:
                comments = parts[1::2]
                s = rest.translate(_WS_DEL).lower()
        else:
            s, _cols, comments = strip_with_map(raw, num)
    else:
        s = raw.replace(" ", "")
        if "\t" in s or "\r" in s or "\f" in s or "\v" in s:
            s = s.translate(_WS_DEL)
        s = s.lower()
    if not s:
        ln = Line(num, raw)
        ln.empty = True
        if comments:
            ln.comments = comments
        return ln
    if s[0] != "o" and len(s) < 300 and "\x01" not in s:
        parts = _SHAPE_SPLIT.split(s)
        ln = _fill("\x01".join(parts[0::2]), parts[1::2], raw, num, comments)
        if ln is not None:
            return ln
    return _parse_full(raw, num, s, comments)


def _fill(shape: str, nums: list[str], raw: str, num: int, comments) -> Line | None:
    """A line from its shape and numbers (None: the shape cannot be used)."""
    tpl = _SHAPES.get(shape, False)
    if tpl is False:
        tpl = _make_shape(shape, len(nums))
    if tpl is None:
        return None
    cls, wletters, wget, fixed, kget, kidx, kfix = tpl
    try:
        vals = list(map(float, nums))
    except ValueError:
        return None
    ln = cls()
    ln.num = num
    ln.raw = raw
    if wget is not None:
        w = dict(zip(wletters, wget(vals)))
        if fixed:
            w.update(fixed)
        ln.words = w
    else:
        ln.words = dict(fixed) if fixed else {}
    if kget is not None:
        ln.k = kget(vals)
    elif kidx:
        vals.extend(kfix)
        ln.k = tuple([vals[i] for i in kidx])
    else:
        ln.k = ()
    ln.comments = comments or ()
    return ln


class Presplit:
    """All lines of a program reduced to shapes in one pass over the text.

    ``line(idx)`` gives the parsed line ``idx`` (0-based) like
    :func:`parse_line`; lines with comments, non-ASCII text or anything the
    shapes do not cover take the per-line path.
    """

    __slots__ = ("lines", "shapes", "nums", "offsets", "shape_text", "base")

    def __init__(self, text: str, lines: list[str], base: int = 0):
        self.lines = lines
        self.base = base          #: line number of lines[0] minus 1 (a window of a longer file)
        self.shapes = None
        if "\x01" in text or not text.isascii():
            return
        t = text.replace(" ", "")
        for ch in "\t\r\f\v":
            if ch in t:
                t = t.replace(ch, "")
        parts = _SHAPE_SPLIT.split(t.lower())
        self.shape_text = "\x01".join(parts[0::2])
        shapes = self.shape_text.split("\n")
        if len(shapes) < len(lines):
            return
        self.nums = parts[1::2]
        self.offsets = list(itertools.accumulate((s.count("\x01") for s in shapes), initial=0))
        self.shapes = shapes

    def oword_lines(self, line_regex) -> list[int] | None:
        """Indices of the lines that start with an O word (None: not available).

        Only lines whose shape contains an 'o' are looked at; lines with
        comments are checked on their raw text with ``line_regex``.
        """
        shapes = self.shapes
        if shapes is None:
            return None
        st = self.shape_text
        out = []
        line = 0
        pos = 0
        i = st.find("o")
        while i >= 0:
            line += st.count("\n", pos, i)
            s = shapes[line]
            if _OSHAPE.match(s) or (("(" in s or ";" in s) and line_regex.match(self.lines[line])):
                out.append(line)
            nl = st.find("\n", i)
            if nl < 0:
                break
            line += 1
            pos = nl + 1
            i = st.find("o", pos)
        return out

    def line(self, idx: int) -> Line:
        raw = self.lines[idx]
        shapes = self.shapes
        if shapes is not None:
            sh = shapes[idx]
            if sh and sh[0] != "o" and len(sh) < 300 and "(" not in sh and ")" not in sh and ";" not in sh:
                off = self.offsets
                ln = _fill(sh, self.nums[off[idx]:off[idx + 1]], raw, idx + 1 + self.base, None)
                if ln is not None:
                    return ln
        return parse_line(raw, idx + 1 + self.base)


def _parse_full(raw: str, num: int, s: str, comments) -> Line:
    ln = Line(num, raw)
    if comments:
        ln.comments = comments
    try:
        _parse(ln, s)
    except _Bad as exc:
        raise GcodeError(exc.message, num, raw_column(raw, num, exc.pos), exc.code) from None
    return ln


def _make_shape(shape: str, nnum: int):
    tpl = Line(0, "")
    if "<" in shape and _NAMED_DIGIT.search(shape):  # a number inside #<name>: no shape
        _SHAPES[shape] = None
        return None
    try:
        c = _parse(tpl, shape)
    except _Bad:
        c = None
    if len(_SHAPES) >= _CACHE_MAX:   # bounded (lines already parsed keep their shape class)
        _SHAPES.clear()
    if c is None or c.nph != nnum or any(d[0] in "gm" for d in tpl.dyn):
        _SHAPES[shape] = None
        return None
    # where each number goes: words (letter, index) and constant slots
    wl = [(L, v.idx) for L, v in tpl.words.items() if isinstance(v, _Ph)]
    fixed = {L: v for L, v in tpl.words.items() if not isinstance(v, _Ph)}
    kidx = [v.idx if isinstance(v, _Ph) else nnum + j for j, v in enumerate(c.k)]
    kfix = [float(v) for v in c.k]
    # a Line subclass whose class attributes hold what all lines of the shape share
    shared = {"gs": tpl.gs, "ms": tpl.ms, "dyn": tpl.dyn, "fn": staticmethod(tpl.fn) if tpl.fn else None,
              "assigns": tpl.assigns,
              "oword": tpl.oword, "cols": None, "axes": tpl.axes, "empty": False, "gmot": tpl.gmot,
              "srcs": tpl.srcs, "arcok": tpl.arcok, "__slots__": ()}
    shared["plain"] = tpl.plain
    shared["delete"] = tpl.delete
    cls = type("ShapedLine", (_ShapedBase,), shared)
    widx = [i for _, i in wl]
    wget = None
    if len(widx) == 1:
        i0 = widx[0]
        wget = lambda v: (v[i0],)  # noqa: E731
    elif widx:
        wget = operator.itemgetter(*widx)
    kget = None
    if kidx and all(i < nnum for i in kidx):
        if len(kidx) == 1:
            k0 = kidx[0]
            kget = lambda v: (v[k0],)  # noqa: E731
        else:
            kget = operator.itemgetter(*kidx)
    res = (cls, tuple(L for L, _ in wl), wget, fixed, kget, tuple(kidx), kfix)
    _SHAPES[shape] = res
    return res


class _ShapedBase:
    """Base of per-shape line classes: only the per-line fields are slots."""
    __slots__ = ("num", "raw", "words", "k", "comments")
    column = Line.column
    error = Line.error


def _parse(ln: Line, s: str) -> None:
    i = 0
    n = len(s)
    c = _Ctx(s)
    if s[0] == "/":
        ln.delete = True
        i = 1
    if i < n and s[i] == "n":
        if s.startswith("\x01", i + 1):   # a shape's placeholder: the line number is not used
            c.nph += 1
            i += 2
        else:
            m = _UNSIGNED.match(s, i + 1)
            if not m:
                raise _Bad(i, "N word needs a line number")
            i = m.end()
    if i < n and s[i] == "o":
        _parse_oword(ln, s, i)
        return None
    srcs: list[str] = []
    words = ln.words
    cols = ln.cols
    seen: set[str] = set()
    while i < n:
        ch = s[i]
        if ch == "#":
            i = _parse_assign(ln, c, i, srcs)
            continue
        if ch not in _LETTERS:
            if ch in _FORBIDDEN_LETTERS:
                raise _Bad(i, _FORBIDDEN_LETTERS[ch], "unsupported")
            if ch == "%":
                raise _Bad(i, "'%' must stand alone on its line")
            raise _Bad(i, f"bad character {ch!r}: a word letter is expected")
        v, j = _read_real(c, i + 1)
        if isinstance(v, _Ph) and (ch == "g" or ch == "m"):
            v = c.const(v)
        if ch == "g" or ch == "m":
            if type(v) is float:
                code = _gcode_int(v)
                if code is None or (ch == "m" and code % 10):
                    raise _Bad(i, f"{ch.upper()}{v:g} is not a valid {ch.upper()} code", "unsupported")
                (ln.gs if ch == "g" else ln.ms).append(code if ch == "g" else code // 10)
                cols[f"{ch}{code if ch == 'g' else code // 10}"] = i
            else:
                key = f"{ch}@{i}"
                ln.dyn.append(key)
                srcs.append(v)
                cols[key] = i
        else:
            if ch in seen:
                raise _Bad(i, f"{ch.upper()} word appears more than once on the line", "word")
            seen.add(ch)
            cols[ch] = i
            if isinstance(v, float):
                words[ch] = v
            else:
                ln.dyn.append(ch)
                srcs.append(v)
        i = j
    if srcs:
        ln.k = tuple(c.k)
        ln.fn = compile_template("(" + ",".join(srcs) + ",)")
        ln.srcs = tuple(srcs)
    if ln.ms and (98 in ln.ms or 99 in ln.ms):
        _fanuc_m(ln, seen)
    ln.axes = tuple((_AXIS_INDEX[a], a) for a in "xyzabc" if a in seen)
    simple = (not ln.ms and not ln.assigns and not ln.delete
              and all(a in "xyzabcf" for a in seen) and all(len(d) == 1 for d in ln.dyn))
    ln.plain = simple and not ln.gs
    ln.arcok = (not ln.gs and not ln.ms and not ln.assigns and not ln.delete
                and all(a in "xyzabcfijkrp" for a in seen) and all(len(d) == 1 for d in ln.dyn))
    if simple and len(ln.gs) == 1 and ln.gs[0] in (0, 10):
        ln.gmot = ln.gs[0]
    return c


def _fanuc_m(ln: Line, seen: set) -> None:
    """M98 P<sub> [L<count>] / M99: Fanuc-style subprogram call and return, alone on their line."""
    m = 98 if 98 in ln.ms else 99
    allowed = {"p", "l"} if m == 98 else set()
    if len(ln.ms) != 1 or ln.gs or ln.assigns or (seen - allowed):
        raise _Bad(ln.cols.get(f"m{m}", 0), f"M{m} must stand alone on its line"
                   + (" (with its P and L words)" if m == 98 else ""), "word")
    if m == 98 and "p" not in seen:
        raise _Bad(ln.cols.get("m98", 0), "M98 needs a P word (the subprogram number)", "word")
    ln.oword = (f"m{m}", "", 0)


def _parse_assign(ln: Line, c: _Ctx, i: int, srcs: list[str]) -> int:
    s = c.s
    j = i + 1
    if j >= len(s):
        raise _Bad(i, "parameter number missing after '#'", "parameter")
    ch = s[j]
    slot_target = None
    if ch == "<":
        k = s.find(">", j + 1)
        if k < 0:
            raise _Bad(j, "named parameter '#<' is not closed with '>'", "parameter")
        if "\x01" in s[j:k]:
            raise _Bad(j, "internal: placeholder inside a parameter name")
        name = s[j + 1:k]
        if not name or "<" in name:
            raise _Bad(j, f"bad parameter name {s[j:k + 1]!r}", "parameter")
        if name in PREDEFINED:
            raise _Bad(j, f"#<{name}> is read-only", "parameter")
        kind, target = ("g" if name[0] == "_" else "l"), name
        j = k + 1
    elif ch.isdigit():
        m = _INDEX.match(s, j)
        target = _param_number(m.group(), j)
        if target < 1 or target > MAX_PARAMETER:
            raise _Bad(j, f"parameter number {target} is outside 1..{MAX_PARAMETER}", "parameter")
        if target in READONLY_PARAMETERS:
            raise _Bad(j, f"parameter #{target} is read-only", "parameter")
        kind = "n"
        j = m.end()
    elif ch == "#" or ch == "[" or ch.isalpha():     # #[expr] = , ##n = , #ATAN[1]/[1] =
        v, j = _read_real(c, j)
        if isinstance(v, float):
            v = c.const(v)
        slot_target = len(srcs)
        srcs.append(f"_ix({v})")
        kind, target = "i", slot_target
        ln.dyn.append(f"#@{i}")
        ln.cols[f"#@{i}"] = i
    else:
        raise _Bad(j, f"bad parameter reference '#{ch}'", "parameter")
    if j >= len(s) or s[j] != "=":
        raise _Bad(j, "'=' expected in parameter assignment (a parameter alone is not a word)",
                   "parameter")
    v, j = _read_real(c, j + 1)
    key = f"=@{i}"
    ln.cols[key] = i
    ln.dyn.append(key)
    srcs.append(c.const(v) if isinstance(v, float) else v)
    ln.assigns.append((kind, target, key))
    return j


def _parse_oword(ln: Line, s: str, i: int) -> None:
    j = i + 1
    if j < len(s) and s[j] == "<":
        k = s.find(">", j + 1)
        if k < 0 or k == j + 1:
            raise _Bad(j, "O-word name must be written o<name>", "syntax")
        label = s[j + 1:k]
        j = k + 1
    else:
        m = _DIGITS.match(s, j)
        c = _Ctx(s)
        srcs: list[str] = []
        if not m and j < len(s) and s[j] in "#[":     # o#<name> call, o[expr] call: the label computed
            v, j = _read_real(c, j)
            if not s.startswith("call", j):
                raise _Bad(j, "computed O-word labels are supported with 'call' only", "unsupported")
            srcs.append(c.const(v) if isinstance(v, float) else v)
            label = None
        elif not m:
            raise _Bad(j, "O word needs a number or <name>")
        else:
            label = m.group().lstrip("0") or "0"
            j = m.end()
    if j == len(s):      # a bare O-number: Fanuc-style program number / subprogram start (M98 ... M99)
        ln.oword = ("fanuc", label, 0)
        ln.cols["o"] = i
        return
    m = _OWORD.match(s, j)
    if not m:
        raise _Bad(j, f"unknown O-word keyword at {s[j:j + 10]!r}", "unsupported")
    kw = m.group()
    j = m.end()
    if label is not None:
        c = _Ctx(s)
        srcs = []
    while j < len(s):
        if kw not in ("if", "elseif", "while", "repeat", "return", "endsub", "call"):
            raise _Bad(j, f"nothing may follow O-word {kw!r}", "syntax")
        if kw != "call" and srcs:
            raise _Bad(j, f"O-word {kw!r} takes one value", "syntax")
        v, j = _read_real(c, j)
        srcs.append(c.const(v) if isinstance(v, float) else v)
    if kw in ("if", "elseif", "while", "repeat") and not srcs:
        raise _Bad(j, f"O-word {kw!r} needs a condition value", "syntax")
    if kw == "call" and len(srcs) > 30 + (label is None):
        raise _Bad(j, "at most 30 call arguments (#1..#30)", "syntax")
    if srcs:
        ln.k = tuple(c.k)
        ln.fn = compile_template("(" + ",".join(srcs) + ",)")
        ln.srcs = tuple(srcs)
    ln.oword = (kw, label, len(srcs))
    ln.cols["o"] = i
