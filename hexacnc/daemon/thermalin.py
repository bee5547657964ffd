"""Thermal inputs of the running daemon, checked before use: probe readings (:func:`parse_reading`,
refused whole with :class:`ThermalInputError` naming the field), the reading source
(:func:`resolve_source`) and the largest offset rate the cycle's acceleration guard accepts
(:func:`max_safe_offset_rate_mm_s`).  The supervisor that uses them: :mod:`.thermalsup`."""
from __future__ import annotations

import math

import numpy as np

from ..errors import HexacncError


class ThermalInputError(HexacncError):
    """A refused reading. ``code`` is a protocol error code, ``field`` names the offending field."""

    def __init__(self, code: str, field: str, message: str):
        super().__init__(message)
        self.code = code
        self.field = field


def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check_temp(v, field: str, tc) -> float:
    if not _num(v):
        raise ThermalInputError("bad_type", field, f"{field} must be a number (degC), got {type(v).__name__}")
    x = float(v)
    if not math.isfinite(x):
        raise ThermalInputError("bad_value", field, f"{field} is not finite ({x!r})")
    if not tc.probe_min_C <= x <= tc.probe_max_C:
        raise ThermalInputError("bad_value", field, f"{field} = {x:g} degC is outside [thermal] probe_min_C.."
                                                    f"probe_max_C [{tc.probe_min_C:g}, {tc.probe_max_C:g}]")
    return x


def parse_reading(fields: dict, tc) -> dict:
    """Validate one ``temperatures`` request; returns ``{"struts": (6,p), "ambient", "frame",
    "spindle" (or None), "time_s" (or None)}`` or raises :class:`ThermalInputError`.

    ``probes_C`` is a map ``{"struts": [[p values] x 6], "ambient": T, "frame": T}`` or a flat list
    of ``6 p + 2`` values: strut 1 probes (in ``[thermal] probes`` order), ..., strut 6, ambient,
    frame.  ``spindle_C`` (housing) and ``time_s`` (acquisition clock, s, increasing) are optional.
    """
    p = len(tc.probes)
    if "probes_C" not in fields or fields["probes_C"] is None:
        raise ThermalInputError("missing_field", "probes_C", "op 'temperatures' needs field 'probes_C'")
    raw = fields["probes_C"]
    struts = np.empty((6, p))
    if isinstance(raw, dict):
        for key in ("struts", "ambient", "frame"):
            if key not in raw:
                raise ThermalInputError("missing_field", f"probes_C.{key}", f"probes_C has no {key!r}")
        rows = raw["struts"]
        if not isinstance(rows, (list, tuple)):
            raise ThermalInputError("bad_type", "probes_C.struts", "probes_C.struts must be an array of 6 arrays")
        if len(rows) != 6:
            raise ThermalInputError("bad_value", "probes_C.struts",
                                    f"probes_C.struts must have 6 rows (one per strut), got {len(rows)}")
        for i, row in enumerate(rows):
            f = f"probes_C.struts[{i}]"
            if not isinstance(row, (list, tuple)):
                raise ThermalInputError("bad_type", f, f"{f} must be an array of {p} probe values")
            if len(row) != p:
                raise ThermalInputError("bad_value", f, f"{f} must have {p} values ([thermal] probes = "
                                                        f"{list(tc.probes)}), got {len(row)}")
            for j, v in enumerate(row):
                struts[i, j] = _check_temp(v, f"{f}[{j}]", tc)
        ambient = _check_temp(raw["ambient"], "probes_C.ambient", tc)
        frame = _check_temp(raw["frame"], "probes_C.frame", tc)
    elif isinstance(raw, (list, tuple)):
        n = 6 * p + 2
        if len(raw) != n:
            raise ThermalInputError("bad_value", "probes_C", f"probes_C must have {n} values (6 struts x {p} probes, "
                                                             f"ambient, frame), got {len(raw)}")
        for k in range(6 * p):
            struts[k // p, k % p] = _check_temp(raw[k], f"probes_C[{k}]", tc)
        ambient = _check_temp(raw[6 * p], f"probes_C[{6 * p}]", tc)
        frame = _check_temp(raw[6 * p + 1], f"probes_C[{6 * p + 1}]", tc)
    else:
        raise ThermalInputError("bad_type", "probes_C", "probes_C must be a map or an array")
    spindle = None
    if fields.get("spindle_C") is not None:
        spindle = _check_temp(fields["spindle_C"], "spindle_C", tc)
    t = fields.get("time_s")
    if t is not None:
        if not _num(t):
            raise ThermalInputError("bad_type", "time_s", f"time_s must be a number (s), got {type(t).__name__}")
        t = float(t)
        if not math.isfinite(t) or t < 0:
            raise ThermalInputError("bad_value", "time_s", f"time_s must be a finite number >= 0, got {t!r}")
    return {"struts": struts, "ambient": ambient, "frame": frame, "spindle": spindle, "time_s": t}


#: the offsets' slew may use at most this fraction of the smallest strut acceleration limit (the cycle's
#: guard allows 5 % over the limit; the planner may use all of it)
ACCEL_SHARE = 0.025


def max_safe_offset_rate_mm_s(cfg, period_s: float) -> float:
    """Largest ``[thermal] max_offset_rate_mm_s`` whose slew steps stay within ``ACCEL_SHARE`` of the
    strut acceleration limit: the hot loop moves the applied offsets every ``THERMAL_EVERY`` cycles by
    ``rate * THERMAL_EVERY * period``, a step the strut commands see as an acceleration of
    ``step / period**2`` on top of the motion's."""
    from .loop import THERMAL_EVERY
    a = float(np.min(cfg.max_acceleration_mm_s2))
    return ACCEL_SHARE * a * period_s / THERMAL_EVERY


def check_offset_rate(cfg, period_s: float) -> None:
    """Refuse (ConfigError, with the numbers) an offset rate the cycle's acceleration guard could trip on."""
    from ..errors import ConfigError
    from .loop import THERMAL_EVERY
    lim = max_safe_offset_rate_mm_s(cfg, period_s)
    r = cfg.thermal.max_offset_rate_mm_s
    if cfg.thermal.enabled and r > lim:
        raise ConfigError(f"[thermal] max_offset_rate_mm_s = {r:g} mm/s is too fast for a {period_s * 1e3:g} ms "
                          f"cycle: the offsets are slewed in steps every few cycles, and at this rate a step adds "
                          f"{r * THERMAL_EVERY / period_s:.0f} mm/s^2 to the strut commands; at most {lim:.4g} mm/s "
                          f"({ACCEL_SHARE * 100:g} % of the smallest max_acceleration_mm_s2)")


def resolve_source(cfg) -> str:
    tc = cfg.thermal
    if not tc.enabled:
        return "none"
    if tc.source == "auto":
        return "sim" if cfg.bus.simulate else "socket"
    return tc.source
