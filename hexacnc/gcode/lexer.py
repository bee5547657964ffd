"""RS274NGC line lexer and expression compiler (LinuxCNC dialect).

One source line becomes one :class:`Line`: its constant words, its computed
words (``[...]`` expressions, parameters, functions) compiled into one Python
function per line *shape*, its parameter assignments and its O-word statement.
Lines are parsed once; loops and subroutines reuse the parsed form.

Expressions are compiled to Python source in which every literal number is a
slot ``k[i]`` of a per-line constant tuple, so lines that differ only in their
numbers (the usual CAM output) share one compiled function.  The function is
called as ``fn(P, L, G, D, k)`` with ``P`` the numbered parameters (list),
``L`` the local named parameters (dict), ``G`` the global ``_`` parameters
(dict) and ``D`` a callable for the read-only system parameters.

Columns in errors are 1-based positions in the raw source line.
"""
from __future__ import annotations

import itertools
import math
import operator
import re

from ..errors import GcodeError

#: numbered parameters #1 .. #5601 (LinuxCNC's RS274NGC_MAX_PARAMETERS - 1)
MAX_PARAMETER = 5601
#: numbered parameters computed from the interpreter state (read-only)
SYSTEM_PARAMETERS = frozenset({5400, 5403, 5420, 5421, 5422, 5423, 5424, 5425})
#: read-only predefined named parameters (LinuxCNC names)
PREDEFINED = frozenset({
    "_x", "_y", "_z", "_a", "_b", "_c", "_abs_x", "_abs_y", "_abs_z", "_abs_a", "_abs_b", "_abs_c",
    "_line", "_motion_mode", "_plane", "_metric", "_imperial", "_absolute", "_incremental",
    "_inverse_time", "_units_per_minute", "_feed", "_rpm", "_current_tool", "_selected_tool",
    "_coord_system", "_tool_offset", "_spindle_on", "_spindle_cw", "_flood", "_mist",
    "_call_level", "_remap_level", "_ijk_absolute_mode",
})
#: equality tolerance of EQ / NE (LinuxCNC TOLERANCE_EQUAL)
TOLERANCE_EQUAL = 0.0001

_WS_DEL = str.maketrans("", "", " \t\r\n\f\v")
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")
_UNSIGNED = re.compile(r"\d+\.?\d*|\.\d+")
_INDEX = re.compile(r"\d+(?:\.0*)?")
_DIGITS = re.compile(r"\d+")
_BINOP = re.compile(r"\*\*|\*|/|\+|-|mod|and|xor|or|eq|ne|gt|ge|lt|le")
_FUNC = re.compile(r"atan|asin|acos|sin|cos|tan|abs|exp|fix|fup|round|ln|sqrt|exists")
_OWORD = re.compile(r"(elseif|else|endif|endsub|endwhile|endrepeat|sub|call|if|while|do|"
                    r"repeat|break|continue|return)")
_PREC = {"**": 6, "*": 5, "/": 5, "mod": 5, "+": 4, "-": 4,
         "eq": 3, "ne": 3, "gt": 3, "ge": 3, "lt": 3, "le": 3, "and": 2, "or": 2, "xor": 2}
#: word letters the dialect knows (others are refused)
_LETTERS = frozenset("abcfghijklmpqrstxyz")
_FORBIDDEN_LETTERS = {
    "d": "D word (cutter radius compensation) is not supported",
    "e": "E word is not supported",
    "u": "U axis does not exist on a hexapod (axes X Y Z A B C)",
    "v": "V axis does not exist on a hexapod (axes X Y Z A B C)",
    "w": "W axis does not exist on a hexapod (axes X Y Z A B C)",
    "n": "N word must be the first word of a line",
    "o": "O word must be the first word of a line",
}


class ExprError(Exception):
    """Raised by expression helpers at run time (converted to GcodeError)."""


# -- run-time helpers used by compiled expressions ------------------------
def _pw(a: float, b: float) -> float:
    if a < 0.0 and b != math.floor(b):
        raise ExprError(f"negative base {a:g} raised to non-integer power {b:g}")
    if a == 0.0 and b < 0.0:
        raise ExprError("zero raised to a negative power")
    return float(a ** b)


def _md(a: float, b: float) -> float:
    if b == 0.0:
        raise ExprError("MOD by zero")
    r = math.fmod(a, b)
    if r < 0.0:
        r += abs(b)
    return r


def _eq(a: float, b: float) -> float:
    return 1.0 if abs(a - b) < TOLERANCE_EQUAL else 0.0


def _ne(a: float, b: float) -> float:
    return 0.0 if abs(a - b) < TOLERANCE_EQUAL else 1.0


def _and(a: float, b: float) -> float:
    return 1.0 if (a != 0.0 and b != 0.0) else 0.0


def _or(a: float, b: float) -> float:
    return 1.0 if (a != 0.0 or b != 0.0) else 0.0


def _xor(a: float, b: float) -> float:
    return 1.0 if ((a != 0.0) != (b != 0.0)) else 0.0


def _ix(v: float) -> int:
    n = int(round(v))
    if abs(v - n) > 0.0001:
        raise ExprError(f"parameter number {v:g} is not an integer")
    if n < 1 or n > MAX_PARAMETER:
        raise ExprError(f"parameter number {n} is outside 1..{MAX_PARAMETER}")
    return n


def _asin(x: float) -> float:
    if x < -1.0 or x > 1.0:
        raise ExprError(f"ASIN argument {x:g} outside [-1, 1]")
    return math.degrees(math.asin(x))


def _acos(x: float) -> float:
    if x < -1.0 or x > 1.0:
        raise ExprError(f"ACOS argument {x:g} outside [-1, 1]")
    return math.degrees(math.acos(x))


def _ln(x: float) -> float:
    if x <= 0.0:
        raise ExprError(f"LN of non-positive value {x:g}")
    return math.log(x)


def _sqrt(x: float) -> float:
    if x < 0.0:
        raise ExprError(f"SQRT of negative value {x:g}")
    return math.sqrt(x)


def _round(x: float) -> float:
    return float(math.floor(x + 0.5) if x >= 0.0 else -math.floor(-x + 0.5))


_RAD = math.pi / 180.0
_ENV = {
    "__builtins__": {},
    "_pw": _pw, "_md": _md, "_eq": _eq, "_ne": _ne, "_and": _and, "_or": _or, "_xor": _xor,
    "_ix": _ix, "_asin": _asin, "_acos": _acos, "_ln": _ln, "_sqrt": _sqrt, "_round": _round,
    "_sin": lambda x: math.sin(x * _RAD), "_cos": lambda x: math.cos(x * _RAD),
    "_tan": lambda x: math.tan(x * _RAD), "_atan": lambda y, x: math.degrees(math.atan2(y, x)),
    "_exp": lambda x: math.exp(x), "_abs": lambda x: abs(x),
    "_fix": lambda x: float(math.floor(x)), "_fup": lambda x: float(math.ceil(x)),
}
_UNARY = {"sin": "_sin", "cos": "_cos", "tan": "_tan", "asin": "_asin", "acos": "_acos",
          "abs": "_abs", "exp": "_exp", "fix": "_fix", "fup": "_fup", "round": "_round",
          "ln": "_ln", "sqrt": "_sqrt"}
_BINSRC = {"+": "({0}+{1})", "-": "({0}-{1})", "*": "({0}*{1})", "/": "({0}/{1})",
           "**": "_pw({0},{1})", "mod": "_md({0},{1})", "eq": "_eq({0},{1})", "ne": "_ne({0},{1})",
           "gt": "(1.0 if {0}>{1} else 0.0)", "ge": "(1.0 if {0}>={1} else 0.0)",
           "lt": "(1.0 if {0}<{1} else 0.0)", "le": "(1.0 if {0}<={1} else 0.0)",
           "and": "_and({0},{1})", "or": "_or({0},{1})", "xor": "_xor({0},{1})"}

#: template source -> compiled function (shared by all programs)
_FN_CACHE: dict[str, object] = {}
_CACHE_MAX = 20_000


def compile_template(src: str):
    """``src``: a tuple display of expressions -> function ``(P, L, G, D, k) -> tuple``."""
    fn = _FN_CACHE.get(src)
    if fn is None:
        try:
            fn = eval("lambda P,L,G,D,k:" + src, _ENV)  # noqa: S307 - generated from our own grammar
        except (SyntaxError, RecursionError, MemoryError) as exc:
            raise _Bad(0, f"expression too deeply nested or too long ({type(exc).__name__})",
                       "expression") from None
        if len(_FN_CACHE) >= _CACHE_MAX:   # bounded: a long-running daemon sees many programs
            _FN_CACHE.clear()
        _FN_CACHE[src] = fn
    return fn


# -- stripping comments and whitespace ------------------------------------
class _Bad(Exception):
    """Internal: syntax problem at index ``pos`` of the stripped line."""

    def __init__(self, pos: int, message: str, code: str = "syntax"):
        super().__init__(message)
        self.pos = pos
        self.message = message
        self.code = code


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
                 "oword", "comments", "cols", "axes", "plain", "empty", "gmot", "srcs")

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


class _Ph(float):
    """A number placeholder of a line shape (value filled in per line)."""
    __slots__ = ("idx",)


_MAX_DEPTH = 60
_MAX_TERMS = 400


class _Ctx:
    __slots__ = ("s", "k", "nph", "depth")

    def __init__(self, s: str):
        self.s = s
        self.k: list[float] = []
        self.nph = 0
        self.depth = 0

    def const(self, v: float) -> str:
        self.k.append(v)
        if len(self.k) > _MAX_TERMS:
            raise _Bad(0, f"more than {_MAX_TERMS} numbers in the expressions of one line", "expression")
        return f"k[{len(self.k) - 1}]"


def _read_real(c: _Ctx, i: int):
    """Read a real value at ``i``: returns (float | source str, next index)."""
    s = c.s
    if i >= len(s):
        raise _Bad(i, "value missing at end of line")
    ch = s[i]
    if ch == "\x01":
        v = _Ph(0.0)
        v.idx = c.nph
        c.nph += 1
        return v, i + 1
    if ch == "[":
        src, j = _read_expr(c, i + 1)
        return src, j
    if ch == "#":
        return _read_param(c, i + 1)
    if ch == "-" or ch == "+":
        m = _NUMBER.match(s, i)
        if m:
            return _number(m.group(), i), m.end()
        c.depth += 1
        if c.depth > _MAX_DEPTH:
            raise _Bad(i, f"expression nested deeper than {_MAX_DEPTH}", "expression")
        v, j = _read_real(c, i + 1)
        c.depth -= 1
        if type(v) is float:
            return (-v if ch == "-" else v), j
        if isinstance(v, float):
            v = c.const(v)
        return (f"(-{v})" if ch == "-" else v), j
    if ch.isdigit() or ch == ".":
        m = _UNSIGNED.match(s, i)
        if m:
            return _number(m.group(), i), m.end()
        raise _Bad(i, f"bad number at {s[i:i + 8]!r}")
    if ch.isalpha():
        m = _FUNC.match(s, i)
        if m:
            return _read_func(c, m.group(), m.end(), i)
        raise _Bad(i, f"unknown function or word {s[i:i + 8]!r} where a value is expected",
                   "expression")
    raise _Bad(i, f"bad character {ch!r} where a value is expected")


def _number(text: str, i: int) -> float:
    v = float(text)
    if not -1e300 < v < 1e300:
        raise _Bad(i, f"number {text[:20]}... is out of range", "value")
    return v


def _param_number(text: str, i: int) -> int:
    if len(text) > 12:
        raise _Bad(i, f"parameter number {text[:12]}... is outside 1..{MAX_PARAMETER}", "parameter")
    return int(float(text))


def _read_param(c: _Ctx, i: int):
    """After '#': a parameter reference -> (source, next index)."""
    s = c.s
    if i >= len(s):
        raise _Bad(i, "parameter number missing after '#'", "parameter")
    ch = s[i]
    if ch == "<":
        j = s.find(">", i + 1)
        if j < 0:
            raise _Bad(i, "named parameter '#<' is not closed with '>'", "parameter")
        name = s[i + 1:j]
        if not name or "<" in name:
            raise _Bad(i, f"bad parameter name {s[i:j + 1]!r}", "parameter")
        return _named_src(name), j + 1
    if ch.isdigit():
        m = _INDEX.match(s, i)
        n = _param_number(m.group(), i)
        if n < 1 or n > MAX_PARAMETER:
            raise _Bad(i, f"parameter number {n} is outside 1..{MAX_PARAMETER}", "parameter")
        if n in SYSTEM_PARAMETERS:
            return f"D({n})", m.end()
        if s.startswith(".", m.end()):
            raise _Bad(m.end(), "parameter number is not an integer", "parameter")
        return f"P[{n}]", m.end()
    if ch == "#" or ch == "[":
        c.depth += 1
        if c.depth > _MAX_DEPTH:
            raise _Bad(i, f"parameter reference nested deeper than {_MAX_DEPTH}", "parameter")
        v, j = _read_real(c, i)
        c.depth -= 1
        if isinstance(v, _Ph):
            v = c.const(v)
        if type(v) is float:
            n = int(v)
            if n != v or n < 1 or n > MAX_PARAMETER:
                raise _Bad(i, f"parameter number {v:g} is not an integer in 1..{MAX_PARAMETER}",
                           "parameter")
            return f"P[{n}]", j
        return f"P[_ix({v})]", j
    raise _Bad(i, f"bad parameter reference '#{ch}'", "parameter")


def _named_src(name: str) -> str:
    if name[0] == "_":
        if name in PREDEFINED:
            return f"D({name!r})"
        return f"G[{name!r}]"
    return f"L[{name!r}]"


def _read_func(c: _Ctx, name: str, i: int, start: int):
    s = c.s
    if not s.startswith("[", i):
        raise _Bad(i, f"function {name.upper()} needs its argument in [ ]", "expression")
    if name == "exists":
        if not s.startswith("#<", i + 1):
            raise _Bad(i + 1, "EXISTS needs a named parameter: EXISTS[#<name>]", "expression")
        j = s.find(">", i + 3)
        if j < 0 or not s.startswith("]", j + 1):
            raise _Bad(i + 1, "EXISTS needs a named parameter: EXISTS[#<name>]", "expression")
        pname = s[i + 3:j]
        if pname in PREDEFINED:
            return 1.0, j + 2
        where = "G" if pname.startswith("_") else "L"
        return f"(1.0 if {pname!r} in {where} else 0.0)", j + 2
    arg, j = _read_expr(c, i + 1)
    arg = c.const(arg) if isinstance(arg, float) else arg
    if name == "atan":
        if not s.startswith("/[", j):
            raise _Bad(j, "ATAN needs two arguments: ATAN[y]/[x]", "expression")
        arg2, j = _read_expr(c, j + 2)
        arg2 = c.const(arg2) if isinstance(arg2, float) else arg2
        return f"_atan({arg},{arg2})", j
    return f"{_UNARY[name]}({arg})", j


def _read_expr(c: _Ctx, i: int):
    """After '[': expression up to the matching ']' -> (float | source, next index)."""
    c.depth += 1
    if c.depth > _MAX_DEPTH:
        raise _Bad(i, f"expression nested deeper than {_MAX_DEPTH}", "expression")
    v, j = _binary(c, i, 0)
    c.depth -= 1
    s = c.s
    if j >= len(s):
        raise _Bad(j, "expression not closed with ']'", "expression")
    if s[j] != "]":
        raise _Bad(j, f"unknown operator at {s[j:j + 6]!r} (expected an operator or ']')",
                   "expression")
    return v, j + 1


def _binary(c: _Ctx, i: int, minprec: int):
    lhs, i = _read_real(c, i)
    s = c.s
    while True:
        m = _BINOP.match(s, i)
        if not m:
            return lhs, i
        op = m.group()
        prec = _PREC[op]
        if prec < minprec:
            return lhs, i
        rhs, i = _binary(c, m.end(), prec + 1)
        a = c.const(lhs) if isinstance(lhs, float) else lhs
        b = c.const(rhs) if isinstance(rhs, float) else rhs
        lhs = _BINSRC[op].format(a, b)


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
_SHAPE_SPLIT = re.compile(r"(?<=[abcfhijklnpqrstxyz\[*/+\-=])([-+]?[\d.]+)")
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

    __slots__ = ("lines", "shapes", "nums", "offsets", "shape_text")

    def __init__(self, text: str, lines: list[str]):
        self.lines = lines
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
                ln = _fill(sh, self.nums[off[idx]:off[idx + 1]], raw, idx + 1, None)
                if ln is not None:
                    return ln
        return parse_line(raw, idx + 1)


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
              "oword": None, "cols": None, "axes": tpl.axes, "empty": False, "gmot": tpl.gmot,
              "srcs": tpl.srcs, "__slots__": ()}
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
    ln.axes = tuple((_AXIS_INDEX[a], a) for a in "xyzabc" if a in seen)
    simple = (not ln.ms and not ln.assigns and not ln.delete
              and all(a in "xyzabcf" for a in seen) and all(len(d) == 1 for d in ln.dyn))
    ln.plain = simple and not ln.gs
    if simple and len(ln.gs) == 1 and ln.gs[0] in (0, 10):
        ln.gmot = ln.gs[0]
    return c


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
        if target in SYSTEM_PARAMETERS:
            raise _Bad(j, f"parameter #{target} is read-only", "parameter")
        kind = "n"
        j = m.end()
    elif ch == "#" or ch == "[":
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
        if not m:
            raise _Bad(j, "O word needs a number or <name>")
        label = m.group().lstrip("0") or "0"
        j = m.end()
    m = _OWORD.match(s, j)
    if not m:
        raise _Bad(j, f"unknown O-word keyword at {s[j:j + 10]!r}", "unsupported")
    kw = m.group()
    j = m.end()
    c = _Ctx(s)
    srcs: list[str] = []
    while j < len(s):
        if kw not in ("if", "elseif", "while", "repeat", "return", "endsub", "call"):
            raise _Bad(j, f"nothing may follow O-word {kw!r}", "syntax")
        if kw != "call" and srcs:
            raise _Bad(j, f"O-word {kw!r} takes one value", "syntax")
        v, j = _read_real(c, j)
        srcs.append(c.const(v) if isinstance(v, float) else v)
    if kw in ("if", "elseif", "while", "repeat") and not srcs:
        raise _Bad(j, f"O-word {kw!r} needs a condition value", "syntax")
    if kw == "call" and len(srcs) > 30:
        raise _Bad(j, "at most 30 call arguments (#1..#30)", "syntax")
    if srcs:
        ln.k = tuple(c.k)
        ln.fn = compile_template("(" + ",".join(srcs) + ",)")
        ln.srcs = tuple(srcs)
    ln.oword = (kw, label, len(srcs))
    ln.cols["o"] = i
