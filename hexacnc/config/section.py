"""The range-checked getters of one TOML table (:class:`Section`) and the sections of one document.

Every config key goes through these getters: each error names the file, the ``[section] key`` and the
bad value; ``finish`` rejects keys nobody read.
"""
from __future__ import annotations

import math
import os
from typing import Any

import numpy as np

from ..errors import ConfigError

_REQUIRED = object()


class Section:
    """Range-checked getters over one TOML table; ``finish`` rejects leftovers."""

    def __init__(self, path: str, name: str, table: dict[str, Any] | None):
        self.path = path
        self.name = name
        self.table = dict(table or {})
        self.used: set[str] = set()

    # -- helpers ---------------------------------------------------------
    def where(self, key: str) -> str:
        return f"{self.path}: [{self.name}] {key}"

    def error(self, key: str, msg: str) -> ConfigError:
        return ConfigError(f"{self.where(key)}: {msg}")

    def has(self, key: str) -> bool:
        return key in self.table

    def _get(self, key: str, default: Any) -> Any:
        self.used.add(key)
        if key in self.table:
            return self.table[key]
        if default is _REQUIRED:
            raise self.error(key, "missing (required)")
        return default

    def _check_range(self, key: str, v: float, minval, maxval, above, below) -> None:
        v = float(v)                 # a plain float in the messages (not numpy's np.float64(...) repr)
        if not math.isfinite(v):
            raise self.error(key, f"value {v!r} is not finite")
        if minval is not None and v < minval:
            raise self.error(key, f"value {v!r} is below the minimum {minval}")
        if maxval is not None and v > maxval:
            raise self.error(key, f"value {v!r} is above the maximum {maxval}")
        if above is not None and v <= above:
            raise self.error(key, f"value {v!r} must be greater than {above}")
        if below is not None and v >= below:
            raise self.error(key, f"value {v!r} must be less than {below}")

    @staticmethod
    def _is_number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    # -- getters ---------------------------------------------------------
    def getfloat(self, key: str, default: Any = _REQUIRED, minval=None, maxval=None,
                 above=None, below=None) -> float:
        v = self._get(key, default)
        if v is None:
            return None  # type: ignore[return-value]
        if not self._is_number(v):
            raise self.error(key, f"expected a number, got {v!r}")
        v = float(v)
        self._check_range(key, v, minval, maxval, above, below)
        return v

    def getint(self, key: str, default: Any = _REQUIRED, minval=None, maxval=None) -> int:
        v = self._get(key, default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.error(key, f"expected an integer, got {v!r}")
        self._check_range(key, float(v), minval, maxval, None, None)
        return int(v)

    def getbool(self, key: str, default: Any = _REQUIRED) -> bool:
        v = self._get(key, default)
        if not isinstance(v, bool):
            raise self.error(key, f"expected true or false, got {v!r}")
        return v

    def getstr(self, key: str, default: Any = _REQUIRED) -> str:
        v = self._get(key, default)
        if v is None:
            return None  # type: ignore[return-value]
        if not isinstance(v, str):
            raise self.error(key, f"expected a string, got {v!r}")
        return v

    def getchoice(self, key: str, choices: tuple[str, ...] | list[str], default: Any = _REQUIRED) -> str:
        v = self.getstr(key, default)
        if v not in choices:
            raise self.error(key, f"value {v!r} is not one of {', '.join(map(repr, choices))}")
        return v

    def getvec(self, key: str, n: int, default: Any = _REQUIRED, minval=None, maxval=None,
               above=None, below=None, allow_scalar: bool = False) -> np.ndarray:
        """A list of ``n`` numbers (or, with ``allow_scalar``, one number for all)."""
        v = self._get(key, default)
        if allow_scalar and self._is_number(v):
            v = [v] * n
        if not isinstance(v, (list, tuple)):
            raise self.error(key, f"expected a list of {n} numbers"
                             + (" or one number" if allow_scalar else "") + f", got {v!r}")
        if len(v) != n:
            raise self.error(key, f"expected {n} values, got {len(v)}")
        out = np.empty(n)
        for i, x in enumerate(v):
            if not self._is_number(x):
                raise self.error(key, f"element {i + 1} is {x!r}, not a number")
            out[i] = float(x)
            try:
                self._check_range(key, out[i], minval, maxval, above, below)
            except ConfigError as exc:
                raise self.error(key, f"element {i + 1}: {str(exc).split(': ', 2)[-1]}") from None
        return out

    def getmatrix(self, key: str, rows: int, cols: int, default: Any = _REQUIRED) -> np.ndarray:
        v = self._get(key, default)
        if not isinstance(v, (list, tuple)) or len(v) != rows:
            got = len(v) if isinstance(v, (list, tuple)) else repr(v)
            raise self.error(key, f"expected {rows} rows of {cols} numbers, got {got} rows")
        out = np.empty((rows, cols))
        for i, row in enumerate(v):
            if not isinstance(row, (list, tuple)) or len(row) != cols:
                raise self.error(key, f"row {i + 1} must have {cols} numbers, got {row!r}")
            for j, x in enumerate(row):
                if not self._is_number(x) or not math.isfinite(float(x)):
                    raise self.error(key, f"row {i + 1}, element {j + 1} is {x!r}, not a finite number")
                out[i, j] = float(x)
        return out

    def getunits(self, key: str, rows: int, default: Any = _REQUIRED) -> np.ndarray:
        """``rows`` unit 3-vectors (normalised; tolerance 1e-3 on the length)."""
        m = self.getmatrix(key, rows, 3, default)
        n = np.linalg.norm(m, axis=1)
        for i in range(rows):
            if abs(n[i] - 1.0) > 1e-3:
                raise self.error(key, f"row {i + 1} {m[i].tolist()} is not a unit vector (length {n[i]:.6g})")
        return m / n[:, None]

    def finish(self) -> None:
        unknown = sorted(set(self.table) - self.used)
        if unknown:
            raise ConfigError(f"{self.path}: [{self.name}] unknown option(s): {', '.join(unknown)}")


def _freeze(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def _expand_user_vars(path: str) -> str:
    """Expand ``$USER`` (even where the environment lacks it) and other variables."""
    if "$USER" in path or "${USER}" in path:
        import getpass
        try:
            user = os.environ.get("USER") or getpass.getuser()
        except (KeyError, OSError):
            user = str(os.getuid())
        path = path.replace("${USER}", user).replace("$USER", user)
    return os.path.expandvars(path)


def _section(path: str, doc: dict, name: str, required: bool) -> Section:
    t = doc.get(name)
    if t is None and required:
        raise ConfigError(f"{path}: section [{name}] is missing")
    if t is not None and not isinstance(t, dict):
        raise ConfigError(f"{path}: [{name}] must be a table")
    return Section(path, name, t)


class Sections:
    """The tables of one document, handed out by name in the order they are read; ``finish`` checks
    every table read so far for unknown keys (in that order)."""

    def __init__(self, path: str, doc: dict):
        self.path = path
        self.doc = doc
        self.read: dict[str, Section] = {}

    def __call__(self, name: str, required: bool = False) -> Section:
        s = _section(self.path, self.doc, name, required)
        self.read[name] = s
        return s

    def __getitem__(self, name: str) -> Section:
        return self.read[name]

    def finish(self) -> None:
        for s in self.read.values():
            s.finish()
