"""Strut dynamics models for the simulated drives: a small callable interface, pluggable.

A model is made per strut by a factory ``(strut index 0..5, MachineConfig or None) -> StrutModel``;
:func:`load_model_factory` resolves ``"package.module:callable"`` (``python -m hexacnc.sim.drives --model``);
the host picks the one ``[dynamics] simulated_drives`` names (``hexacnc.sim.drives.strut_model_factory``).
Positions are drive readings in mm (strut length - strut_offset_mm).
"""
from __future__ import annotations

import math
from typing import Callable, Protocol

from .errors import ConfigError


# --------------------------------------------------------------------------------------------
# strut models
# --------------------------------------------------------------------------------------------
class StrutModel(Protocol):
    """Pluggable strut dynamics. Positions are drive readings in mm (strut length - offset)."""

    velocity_mm_s: float

    def reset(self, position_mm: float) -> None:
        """Put the strut at rest at ``position_mm``."""

    def step(self, target_mm: float, dt_s: float, enabled: bool) -> float:
        """Advance by ``dt_s`` towards ``target_mm`` (drive enabled) or braking to rest
        (disabled); returns the actual position in mm."""


#: factory: (strut index 0..5, MachineConfig or None) -> StrutModel
ModelFactory = Callable[[int, object], StrutModel]


class SecondOrderStrut:
    """Position loop with velocity feed-forward: ``a = wn^2 (xt - x) + 2 zeta wn (vt - v)``.

    ``vt`` is the target's rate (finite difference of successive targets). ``|v| <= vmax``,
    ``|a| <= amax``; disabled: braking at ``amax`` to rest. Sub-stepped so ``wn dt <= 0.2``.
    """

    def __init__(self, natural_hz: float = 60.0, damping: float = 0.9,
                 max_velocity_mm_s: float = 500.0, max_acceleration_mm_s2: float = 20000.0):
        self.wn = 2 * math.pi * natural_hz
        self.zeta = damping
        self.vmax = max_velocity_mm_s
        self.amax = max_acceleration_mm_s2
        self.x = 0.0
        self.velocity_mm_s = 0.0
        self._last_target: float | None = None

    def reset(self, position_mm: float) -> None:
        self.x = float(position_mm)
        self.velocity_mm_s = 0.0
        self._last_target = None

    def step(self, target_mm: float, dt_s: float, enabled: bool) -> float:
        if dt_s <= 0:
            return self.x
        if not enabled:
            self._last_target = None
            v = self.velocity_mm_s
            dv = self.amax * dt_s
            v = 0.0 if abs(v) <= dv else v - math.copysign(dv, v)
            self.x += 0.5 * (v + self.velocity_mm_s) * dt_s
            self.velocity_mm_s = v
            return self.x
        vt = 0.0 if self._last_target is None else (target_mm - self._last_target) / dt_s
        self._last_target = target_mm
        n = max(1, math.ceil(self.wn * dt_s / 0.2))
        h = dt_s / n
        wn2, c = self.wn * self.wn, 2 * self.zeta * self.wn
        x, v = self.x, self.velocity_mm_s
        for k in range(n):
            xt = target_mm - vt * (dt_s - (k + 1) * h)      # target interpolated inside the period
            a = wn2 * (xt - x) + c * (vt - v)
            a = max(-self.amax, min(self.amax, a))
            v = max(-self.vmax, min(self.vmax, v + a * h))
            x += v * h
        self.x, self.velocity_mm_s = x, v
        return x


def default_model_factory(strut: int, cfg) -> StrutModel:
    """Drive limits somewhat above the machine's strut limits, so legitimate motion never saturates."""
    if cfg is None:
        return SecondOrderStrut()
    return SecondOrderStrut(natural_hz=60.0, damping=0.9,
                            max_velocity_mm_s=1.5 * float(cfg.max_velocity_mm_s[strut]),
                            max_acceleration_mm_s2=3.0 * float(cfg.max_acceleration_mm_s2[strut]))


def load_model_factory(spec: str) -> ModelFactory:
    """``"package.module:callable"`` -> the callable (a :data:`ModelFactory`)."""
    import importlib
    mod, _, name = spec.partition(":")
    try:
        obj = getattr(importlib.import_module(mod), name or "model_factory")
    except (ImportError, AttributeError, ValueError) as exc:
        raise ConfigError(f"--model {spec!r}: cannot load the strut model factory: {exc}") from exc
    if not callable(obj):
        raise ConfigError(f"--model {spec!r} is not callable")
    return obj
