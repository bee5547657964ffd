"""Parameters, comments and messages of the interpreter.

Read-only system parameters (LinuxCNC numbers and names) are computed from
the interpreter state; ``(MSG,...)``, ``(DEBUG,...)``, ``(PRINT,...)`` and
``(ABORT,...)`` comments are handled here, on any line.
"""
from __future__ import annotations

import re

from ..errors import GcodeError
from .expr import LENGTH_PARAMETERS, PREDEFINED, ExprError, compile_template
from .lexer import Line

_HOT = re.compile(r"\s*(msg|debug|print|abort|logopen|logappend|logclose|log)\s*,?", re.IGNORECASE)
_SUBST = re.compile(r"#(\d+)|#<([^>]+)>|%(d|f|\.\d+f|\.)?")
_INI = re.compile(r"#\s*<\s*_ini\s*\[", re.IGNORECASE)
_RUNTIME = {5061: "G38 probe result", 5062: "G38 probe result", 5063: "G38 probe result",
            5064: "G38 probe result", 5065: "G38 probe result", 5066: "G38 probe result",
            5067: "G38 probe result", 5068: "G38 probe result", 5069: "G38 probe result",
            5070: "G38.3/G38.5 probe success flag", 5399: "M66 input result"}


class ParamMixin:
    """System parameters, evaluation and comments of :class:`~hexacnc.gcode.interp.Interpreter`."""

    def _eval(self, ln: Line) -> dict:
        """Word values of ``ln`` (constant and computed) as a dict."""
        vals = ln.words
        if ln.fn is not None:
            try:
                res = ln.fn(self.P, self.L, self.G, self._sys, ln.k)
            except (KeyError, ArithmeticError, ValueError, ExprError, IndexError, TypeError, GcodeError) as exc:
                raise self._expr_error(ln, exc) from None
            vals = dict(vals)
            for key, v in zip(ln.dyn, res):
                if not -1e300 < v < 1e300:
                    raise ln.error(f"value {v!r} is not a finite number", key, "expression")
                vals[key] = v
        if self.diameter and "x" in vals:      # G7: X words are diameters (LinuxCNC halves them when read)
            vals = dict(vals)
            vals["x"] *= 0.5
        return vals

    def _expr_error(self, ln: Line, exc: Exception) -> GcodeError:
        if isinstance(exc, GcodeError):
            return GcodeError(exc.bare_message, ln.num, 1, exc.code)
        if isinstance(exc, KeyError):
            name = exc.args[0] if exc.args else "?"
            col = 1
            m = re.search(r"#\s*<\s*" + r"\s*".join(map(re.escape, str(name))) + r"\s*>",
                          ln.raw, re.IGNORECASE)
            if m:
                col = m.start() + 1
            return GcodeError(f"parameter #<{name}> is not defined", ln.num, col, "parameter")
        msg = str(exc) or type(exc).__name__
        if isinstance(exc, ZeroDivisionError):
            msg = "division by zero"
        elif isinstance(exc, OverflowError):
            msg = "numeric overflow"
        col = 1
        if ln.oword is not None:
            col = ln.column("o")
        elif ln.dyn:
            key = ln.dyn[0]
            for i, src in enumerate(ln.srcs):
                try:
                    compile_template("(" + src + ",)")(self.P, self.L, self.G, self._sys, ln.k)
                except Exception:  # noqa: BLE001 - the first value that fails is the one to name
                    key = ln.dyn[i]
                    break
            col = ln.column(key)
        return GcodeError(f"expression error: {msg}", ln.num, col, "expression")

    def _prog(self, i: int) -> float:
        """Current position of axis ``i`` in program coordinates (program units, degrees)."""
        if i < 2 and self.rot_deg != 0.0:
            return self._unrotate(self.pos)[i] / self.u
        return (self.pos[i] - self.off[i]) / (self.u if i < 3 else 1.0)

    def _sys(self, key):
        """Read-only system parameters (numbered and predefined named)."""
        u = self.u
        if isinstance(key, int):
            if 5420 <= key <= 5425:
                return self._prog(key - 5420)
            if key in (5426, 5427, 5428) or 5027 <= key <= 5029:
                return 0.0
            if 5021 <= key <= 5026:     # machine coordinates of the controlled point (tool reference point)
                i = key - 5021
                return self._ref_point(self.pos)[i] / (u if i < 3 else 1.0)
            if key == 5400:
                return float(self.tool)
            if 5401 <= key <= 5413:
                return self._tool_param(key)
            if key in LENGTH_PARAMETERS:
                return self.P[key] / self.mu
            if key in _RUNTIME:
                if key in self.runtime_pending:
                    raise GcodeError(f"#{key} ({_RUNTIME[key]}) is only known while the machine runs: "
                                     "hexacnc interprets the whole program before any motion, so a "
                                     "program cannot branch on it", self.line_now, 1, "unsupported")
                return self.P[key]
            raise KeyError(f"#{key}")
        if key[0:3] == "_ab" and key[:5] == "_abs_":
            i = "xyzabcuvw".index(key[5])
            return 0.0 if i > 5 else self.pos[i] / (u if i < 3 else 1.0)
        if len(key) == 2:
            i = "xyzabcuvw".index(key[1])
            return 0.0 if i > 5 else self._prog(i)
        if key == "_value":
            return self.ret_value
        if key == "_value_returned":
            return self.ret_flag
        return float({
            "_line": self.line_now, "_motion_mode": self.motion, "_plane": self.plane,
            "_ccomp": {"L": 410, "R": 420}.get(self.comp_side, 400),
            "_metric": self.u == 1.0, "_imperial": self.u != 1.0,
            "_absolute": self.absolute, "_incremental": not self.absolute,
            "_inverse_time": self.inverse_time, "_units_per_minute": not self.inverse_time,
            "_units_per_rev": 0, "_feed": self.feed, "_rpm": self.rpm,
            "_current_tool": self.tool, "_selected_tool": self.selected,
            "_current_pocket": self.tool, "_selected_pocket": self.selected,
            "_coord_system": [0, 540, 550, 560, 570, 580, 590, 591, 592, 593][self.cs],
            "_tool_offset": self.tool_len != 0.0, "_retract_r_plane": self.retract_r,
            "_retract_old_z": not self.retract_r, "_control_mode": 0 if self.exact_stop else 2,
            "_spindle_rpm_mode": 1, "_spindle_css_mode": 0, "_lathe_diameter_mode": self.diameter,
            "_lathe_radius_mode": not self.diameter, "_spindle_on": self.spindle_dir != 0,
            "_spindle_cw": self.spindle_dir > 0, "_flood": self.flood, "_mist": self.mist,
            "_speed_override": 1, "_feed_override": 1, "_adaptive_feed": 0, "_feed_hold": 0,
            "_task": 0, "_call_level": len(self.frames), "_remap_level": 0,
            "_ijk_absolute_mode": self.arc_absolute,
        }[key])

    # -- comments ---------------------------------------------------------------------
    def _comments(self, ln: Line) -> None:
        self.line_now = ln.num
        for c in ln.comments:
            m = _HOT.match(c)
            if not m:
                continue
            kind = m.group(1).lower()
            if kind.startswith("log"):
                continue
            if not c[m.end() - 1:m.end()] == ",":
                continue
            text = c[m.end():]
            if kind != "msg":
                if _INI.search(text):
                    raise GcodeError("#<_ini[...]> INI-file parameters are not supported (no INI file here)",
                                     ln.num, 1, "unsupported")
                self._fmt = "%f"      # LinuxCNC's %lf until a %d / %f / %.Nf in the comment
                text = _SUBST.sub(self._subst, text)
            if kind == "abort":
                raise GcodeError(text.strip() or "program aborted", ln.num, 1, "abort")
            if kind == "msg":
                text = text.strip()
            self.notes.append((kind, ln.num, text))
            if kind != "print":
                self.messages.append((ln.num, text.strip()))

    def _subst(self, m) -> str:
        if m.group(0)[0] == "%":       # LinuxCNC's format prefixes: %d, %f (4 decimals), %.Nf (one digit N)
            f = m.group(3)
            if f is None:
                return "%"
            if f == "d":
                self._fmt = "%.0f"
            elif f == "f":
                self._fmt = "%.4f"
            elif len(f) == 3:
                self._fmt = "%" + f
            else:                       # '%.' not followed by one digit and 'f': the '%' is dropped
                return f if f == "." else f[:-1] + "f"
            return ""
        try:
            if m.group(1):
                n = int(m.group(1))
                v = self._sys(n) if n in self.system_numbers else self.P[n]
            else:
                name = m.group(2).lower().replace(" ", "")
                v = self._sys(name) if name in PREDEFINED else (self.G if name[0] == "_" else self.L)[name]
            return self._fmt % (v if abs(v) >= 1e-6 else 0.0)    # as LinuxCNC: |v| < 1e-6 prints as 0
        except (KeyError, IndexError, ValueError):
            return "######"
