"""Exception hierarchy of hexacnc.

Every error a user can provoke derives from :class:`HexacncError` and carries a
message that names *what* is wrong and *where* (file, key, line, row, column).
Wrap lower-level exceptions with ``raise ... from exc``.
"""
from __future__ import annotations

# The root, ConfigError and BusError are defined by the drive layer (it imports nothing from
# hexacnc); they are the same classes here.
from drivers.errors import BusError, ConfigError  # noqa: F401 (re-exported)
from drivers.errors import ControlError as HexacncError


class DataError(HexacncError):
    """An input data file (CSV, measurements, program) is malformed."""


class KinematicsError(HexacncError):
    """A pose is unreachable, singular, or outside strut/joint limits."""


class ProtocolError(HexacncError):
    """A socket client sent something the protocol does not allow."""


class GcodeError(HexacncError):
    """A G-code program cannot be parsed or is not supported.

    Attributes ``line`` (1-based) and ``column`` (1-based) locate the problem.
    """

    def __init__(self, message: str, line: int | None = None, column: int | None = None,
                 code: str = "gcode"):
        self.line = line
        self.column = column
        self.code = code
        where = ""
        if line is not None:
            where = f"line {line}" + (f", column {column}" if column is not None else "") + ": "
        super().__init__(where + message)
        self.bare_message = message


class PlanError(HexacncError):
    """A program cannot be planned within the machine's limits.

    ``line`` is the program line of the first violation, ``limit`` names it.
    """

    def __init__(self, message: str, line: int | None = None, limit: str | None = None,
                 code: str = "limit"):
        self.line = line
        self.limit = limit
        self.code = code
        super().__init__((f"line {line}: " if line is not None else "") + message)
        self.bare_message = message
