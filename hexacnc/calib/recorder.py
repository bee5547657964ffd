"""Client-side recorder: status samples of the daemon's stream into a :class:`~.recording.Recording`.

The daemon's ``subscribe`` stream (docs/protocol.md) delivers status samples at
``rate_hz`` (0.1-1000 Hz), i.e. the cycle's signals decimated to that rate; the
recorder keeps them in order, bounded in memory (``max_samples``), starting at
a trigger (with an optional pre-trigger history).

Triggers: ``none`` (start at once), ``state=NAME`` (the daemon's ``state``
becomes NAME, e.g. ``running``), ``following_error>MM`` (any strut's following
error above MM mm), ``temperature>C``.
"""
from __future__ import annotations

import math
import re
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..errors import DataError
from .recording import MAX_SAMPLES, SIGNALS, STRUT_SIGNALS, Recording

#: status keys the recorder reads torques/currents from, when the daemon provides them
TORQUE_KEYS = ("torque_actual_permille", "torque_permille")
CURRENT_KEYS = ("current_actual_permille", "current_permille")


@dataclass(frozen=True)
class Trigger:
    kind: str            #: none | state | following_error | temperature
    value: object = None

    def fired(self, row: dict, st: dict) -> bool:
        if self.kind == "none":
            return True
        if self.kind == "state":
            return st.get("state") == self.value
        if self.kind == "following_error":
            return bool(np.nanmax(np.abs(row["following_error_mm"])) > self.value) \
                if np.any(np.isfinite(row["following_error_mm"])) else False
        if self.kind == "temperature":
            return bool(np.nanmax(row["temperature_C"]) > self.value) \
                if np.any(np.isfinite(row["temperature_C"])) else False
        return False


def parse_trigger(text: str) -> Trigger:
    t = (text or "none").strip()
    if t == "none":
        return Trigger("none")
    m = re.fullmatch(r"state=(\w+)", t)
    if m:
        return Trigger("state", m.group(1))
    m = re.fullmatch(r"(following_error|temperature)>([-+0-9.eE]+)", t)
    if m:
        try:
            return Trigger(m.group(1), float(m.group(2)))
        except ValueError:
            pass
    raise DataError(f"--trigger {text!r}: give none, state=NAME, following_error>MM or temperature>C")


def _vec(v, n: int = 6) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        return np.full(n, np.nan)
    return a[:n] if a.size >= n else np.full(n, np.nan)


#: drive torques / currents older than this (s, status ``*_actual_age_s``) are recorded as NaN: the daemon
#: samples them at rest only on layouts without bus room in motion (hexacnc.daemon.torqueread)
MAX_SAMPLE_AGE_S = 0.5


def _first(st: dict, keys) -> np.ndarray:
    for k in keys:
        if st.get(k) is not None:
            age = st.get(k.replace("_permille", "_age_s"))
            if isinstance(age, (int, float)) and age > MAX_SAMPLE_AGE_S:
                return np.full(6, np.nan)
            return _vec(st[k])
    return np.full(6, np.nan)


def row_from_status(st: dict) -> dict:
    """One sample of every signal from a status message (NaN where the daemon gives nothing)."""
    cmd, act = _vec(st.get("struts_cmd_mm")), _vec(st.get("struts_act_mm"))
    pc, pa = _vec(st.get("pose_cmd")), _vec(st.get("pose_act"))
    th = st.get("thermal") if isinstance(st.get("thermal"), dict) else {}
    temp = _vec(th.get("strut_mean_C_est"))
    pl = st.get("payload_kg")
    return {"struts_cmd_mm": cmd, "struts_act_mm": act, "following_error_mm": cmd - act,
            "torque_permille": _first(st, TORQUE_KEYS), "current_permille": _first(st, CURRENT_KEYS),
            "temperature_C": temp, "thermal_offsets_mm": _vec(st.get("thermal_offsets_mm")),
            "pose_cmd": pc, "pose_act": pa, "fk_residual_mm": float(np.linalg.norm(pc[:3] - pa[:3])),
            "payload_kg": float(pl) if isinstance(pl, (int, float)) else math.nan,
            "t_loop_s": float(lt) if isinstance(lt := st.get("loop_time_s"), (int, float)) else math.nan,
            "drives_enabled": float(en) if isinstance(en := st.get("drives_enabled"), bool) else math.nan}


class Recorder:
    def __init__(self, trigger: Trigger, max_samples: int = 100_000, pretrigger: int = 0):
        if not 1 <= max_samples <= MAX_SAMPLES:
            raise DataError(f"--count must be within 1..{MAX_SAMPLES}, got {max_samples}")
        self.trigger = trigger
        self.max_samples = max_samples
        self.pre: deque = deque(maxlen=max(0, min(pretrigger, max_samples)))
        self.rows: list[tuple[float, dict]] = []
        self.triggered_at: float | None = None
        self.seen = 0

    @property
    def full(self) -> bool:
        return len(self.rows) >= self.max_samples

    def add(self, st: dict, t_s: float) -> bool:
        """Add one status sample taken at ``t_s``; True when the recording is full."""
        self.seen += 1
        row = row_from_status(st)
        if self.triggered_at is None:
            if not self.trigger.fired(row, st):
                self.pre.append((t_s, row))
                return False
            self.triggered_at = t_s
            self.rows.extend(self.pre)
            self.pre.clear()
        if not self.full:
            self.rows.append((t_s, row))
        return self.full

    def recording(self, meta: dict) -> Recording:
        if not self.rows:
            raise DataError("nothing recorded" + ("" if self.triggered_at is not None else
                                                  f" (the trigger {self.trigger.kind} never fired)"))
        n = len(self.rows)
        t0 = self.rows[0][0]
        data = {"t_s": np.array([t - t0 for t, _ in self.rows])}
        for nm in SIGNALS[1:]:
            data[nm] = np.array([r[nm] for _, r in self.rows], dtype=float).reshape((n, 6) if nm in STRUT_SIGNALS
                                                                                    else (n,))
        tl = data["t_loop_s"]
        if np.isfinite(tl[0]):
            data["t_loop_s"] = tl - tl[0]
        m = dict(meta)
        m["trigger"] = {"kind": self.trigger.kind, "value": self.trigger.value,
                        "at_s": None if self.triggered_at is None else self.triggered_at - t0}
        m["samples_seen"] = self.seen
        return Recording(data, m)
