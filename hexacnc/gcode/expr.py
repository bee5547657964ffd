"""RS274NGC expressions (LinuxCNC dialect) compiled to Python.

Values (numbers, ``#`` parameters, ``[...]`` expressions, unary functions) are
read from a stripped, lower-case line and turned into Python source in which
every literal number is a slot ``k[i]`` of a constant tuple, so lines that
differ only in their numbers share one compiled function.  The function is
called as ``fn(P, L, G, D, k)`` with ``P`` the numbered parameters (list),
``L`` the local named parameters (dict), ``G`` the global ``_`` parameters
(dict) and ``D`` a callable for the read-only system parameters.

Precedence (LinuxCNC): ``**`` > ``* / MOD`` > ``+ -`` > ``EQ NE GT GE LT LE``
> ``AND OR XOR``, left to right.  Errors at run time are :class:`ExprError`
(or Python's arithmetic errors), converted by the interpreter.
"""
from __future__ import annotations

import math
import re

#: numbered parameters #1 .. #5601 (LinuxCNC's RS274NGC_MAX_PARAMETERS - 1)
MAX_PARAMETER = 5601
#: stored lengths (G28/G30 positions, G92 and work offsets X Y Z): kept in mm, read and set by a
#: program in the machine's length unit (LinuxCNC: the INI file's; see Interpreter machine_units)
LENGTH_PARAMETERS = frozenset({5161, 5162, 5163, 5181, 5182, 5183, 5211, 5212, 5213}
                              | {5201 + 20 * k + i for k in range(1, 10) for i in range(3)})
#: numbered parameters read through the interpreter (computed from its state, or converted)
SYSTEM_PARAMETERS = frozenset({5061, 5062, 5063, 5064, 5065, 5066, 5067, 5068, 5069, 5070, 5399}
                              | set(range(5021, 5030)) | set(range(5400, 5414)) | set(range(5420, 5429))
                              | LENGTH_PARAMETERS)
#: parameters a program may not set (LinuxCNC's readonly_parameters)
READONLY_PARAMETERS = frozenset(set(range(5021, 5030)) | set(range(5400, 5414)) | set(range(5420, 5429)))
#: read-only predefined named parameters (LinuxCNC names)
PREDEFINED = frozenset({
    "_x", "_y", "_z", "_a", "_b", "_c", "_u", "_v", "_w", "_abs_x", "_abs_y", "_abs_z", "_abs_a",
    "_abs_b", "_abs_c", "_abs_u", "_abs_v", "_abs_w",
    "_line", "_motion_mode", "_plane", "_ccomp", "_metric", "_imperial", "_absolute", "_incremental",
    "_inverse_time", "_units_per_minute", "_units_per_rev", "_feed", "_rpm", "_current_tool",
    "_selected_tool", "_current_pocket", "_selected_pocket", "_coord_system", "_tool_offset",
    "_retract_r_plane", "_retract_old_z", "_control_mode", "_spindle_rpm_mode", "_spindle_css_mode",
    "_lathe_diameter_mode", "_lathe_radius_mode", "_spindle_on", "_spindle_cw", "_flood", "_mist",
    "_speed_override", "_feed_override", "_adaptive_feed", "_feed_hold", "_task",
    "_call_level", "_remap_level", "_ijk_absolute_mode", "_value", "_value_returned",
})
#: equality tolerance of EQ / NE (LinuxCNC TOLERANCE_EQUAL)
TOLERANCE_EQUAL = 0.0001

_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")
_UNSIGNED = re.compile(r"\d+\.?\d*|\.\d+")
_INDEX = re.compile(r"\d+(?:\.0*)?")
_BINOP = re.compile(r"\*\*|\*|/|\+|-|mod|and|xor|or|eq|ne|gt|ge|lt|le")
_FUNC = re.compile(r"atan|asin|acos|sin|cos|tan|abs|exp|fix|fup|round|ln|sqrt|exists")
_PREC = {"**": 6, "*": 5, "/": 5, "mod": 5, "+": 4, "-": 4,
         "eq": 3, "ne": 3, "gt": 3, "ge": 3, "lt": 3, "le": 3, "and": 2, "or": 2, "xor": 2}


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


def _pix(P, D, v: float) -> float:
    """The parameter of a computed number (read through the interpreter where it must be)."""
    n = _ix(v)
    return D(n) if n in SYSTEM_PARAMETERS else P[n]


def _exists(v: float) -> float:
    """EXISTS of a computed parameter number: 1.0 for an integer in 1..MAX_PARAMETER."""
    n = int(round(v))
    return 1.0 if abs(v - n) <= 0.0001 and 1 <= n <= MAX_PARAMETER else 0.0


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
    "_ix": _ix, "_exists": _exists, "_pix": _pix, "_asin": _asin, "_acos": _acos, "_ln": _ln, "_sqrt": _sqrt, "_round": _round,
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


# -- syntax problems --------------------------------------------------------
class _Bad(Exception):
    """Internal: syntax problem at index ``pos`` of the stripped line."""

    def __init__(self, pos: int, message: str, code: str = "syntax"):
        super().__init__(message)
        self.pos = pos
        self.message = message
        self.code = code


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
        if name.startswith(("_ini[", "_hal[")):
            raise _Bad(i - 1, f"#<{name[:4]}[...]> {'INI-file' if name[1] == 'i' else 'HAL pin'} parameters "
                          "are not supported", "unsupported")
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
    if ch == "#" or ch == "[" or ch.isalpha():    # #[expr], ##n, #ATAN[1]/[1]: a computed number
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
            return (f"D({n})" if n in SYSTEM_PARAMETERS else f"P[{n}]"), j
        return f"_pix(P,D,{v})", j
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
        m = _INDEX.match(s, i + 2) if s.startswith("#", i + 1) else None
        if m and s.startswith("]", m.end()):     # EXISTS[#n]: numbered parameters 1..5601 exist
            n = _param_number(m.group(), i + 2)
            return (1.0 if 1 <= n <= MAX_PARAMETER else 0.0), m.end() + 1
        if s.startswith(("##", "#["), i + 1):    # EXISTS[##n], EXISTS[#[expr]]: the computed number
            v, j = _read_real(c, i + 2)
            if not s.startswith("]", j):
                raise _Bad(j, "EXISTS takes one parameter: EXISTS[#...]", "expression")
            v = c.const(v) if isinstance(v, float) else v
            return f"_exists({v})", j + 1
        if not s.startswith("#<", i + 1):
            raise _Bad(i + 1, "EXISTS needs a parameter: EXISTS[#<name>] or EXISTS[#n]", "expression")
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
