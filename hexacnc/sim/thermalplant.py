"""The simulated machine's heat, stepped in time: what the daemon's probes read with ``[bus] simulate``.

:class:`ThermalPlant` is the "truth" of ``hexacnc simulate thermal`` (:mod:`hexacnc.sim.thermal`)
made incremental, so the running daemon can be fed by it at the probe rate:

* six struts, each a finer 1-D heat model than the observer's (``ThermalScenario.truth_segments``,
  40 against ``[thermal] segments``), friction heat falling 3:1 from the drive (base) end and
  ``truth_heat_ratio`` (1.15) times ``[thermal] heat_per_speed_W_s_mm`` - the observer's model
  is deliberately wrong in the same ways as in the offline scenario;
* the input is each strut's actual speed (mm/s), measured by the caller from the drives' feedback;
* ambient: creeps ``ambient_creep_K`` per ``duration_s`` and swings ``ambient_swing_K`` with
  ``ambient_period_s`` (HVAC); frame: first-order lag ``frame_tau_s`` behind the ambient;
* spindle housing: first order (``spindle_tau_s``) towards ambient + ``spindle_rise_K`` while the
  spindle runs; the shaft (what grows along the tool axis) lags the housing by ``spindle_shaft_lag_s``.

:meth:`ThermalPlant.readings` gives the probe readings with white Gaussian noise: per strut the
``[thermal] probes`` segments (their centres located on the truth grid), one ambient and one frame
sensor (``[thermal] probe_noise_K``), one spindle-housing probe (``[thermal] sim_spindle_noise_K``).
Time is plant time (s); the daemon advances it ``[thermal] sim_time_scale`` times faster than the
wall clock, with the strut speeds measured in wall-clock time (the motion seen goes on that long).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..kinematics import Hexapod
from ..thermal import discretise, spindle_growth_mm, strut_heat_model
from .thermal import ThermalScenario, truth_probe_segments


class ThermalPlant:
    """Six struts, frame, air and spindle of the simulated machine (see module docstring)."""

    def __init__(self, cfg, scenario: ThermalScenario | None = None, seed: int | None = None,
                 T0_C: float | None = None):
        sc = scenario or ThermalScenario()
        self.cfg = cfg
        self.sc = sc
        tc = cfg.thermal
        self.rng = np.random.default_rng(tc.sim_seed if seed is None else seed)
        self.T0 = float(sc.T0_C if T0_C is None else T0_C)
        lengths = Hexapod(cfg).lengths(cfg.home_pose)
        nseg = self.nseg = sc.truth_segments
        prof = np.linspace(sc.heat_profile_ratio, 1.0, nseg)
        h_true = (tc.heat_per_speed_W_s_mm if sc.heat_per_speed_W_s_mm is None
                  else sc.heat_per_speed_W_s_mm / sc.truth_heat_ratio) * sc.truth_heat_ratio
        self.heat_per_speed_W_s_mm = float(h_true)
        true_cfg = dataclasses.replace(tc, heat_per_speed_W_s_mm=self.heat_per_speed_W_s_mm)
        self.models = [strut_heat_model(true_cfg, float(L), segments=nseg, source_profile=prof) for L in lengths]
        self.C = np.stack([m.C for m in self.models])
        self.T_ref = float(tc.reference_temperature_C)
        self.pidx = truth_probe_segments(cfg, float(lengths[0]), nseg)
        self.noise_K = float(tc.probe_noise_K)
        self.spindle_noise_K = float(tc.sim_spindle_noise_K)
        self._disc: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        self._u = np.zeros((6, 3))
        self.reset()

    def reset(self) -> None:
        """Everything at ``T0`` (from cold), plant time 0."""
        self.t_s = 0.0
        self.T = np.full((6, self.nseg), self.T0)
        self.ambient_C = self.T0
        self.frame_C = self.T0
        self.housing_C = self.T0
        self.shaft_C = self.T0

    def _matrices(self, dt_s: float):
        key = round(dt_s, 6)
        d = self._disc.get(key)
        if d is None:
            if len(self._disc) > 16:
                self._disc.clear()
            pairs = [discretise(m.A, m.B, key) for m in self.models]
            d = self._disc[key] = (np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs]))
        return d

    def ambient_at(self, t_s: float) -> float:
        sc = self.sc
        return (self.T0 + sc.ambient_creep_K * t_s / sc.duration_s
                + sc.ambient_swing_K * math.sin(2 * math.pi * t_s / sc.ambient_period_s))

    def step(self, dt_s: float, speed_mm_s, spindle_on: bool) -> None:
        """Advance by ``dt_s`` plant seconds with strut speeds (6,) mm/s held over the step."""
        if not (dt_s > 0 and math.isfinite(dt_s)):
            return
        sc = self.sc
        v = np.abs(np.asarray(speed_mm_s, dtype=float))
        if v.shape != (6,) or not np.all(np.isfinite(v)):
            v = np.zeros(6)
        t_mid = self.t_s + 0.5 * dt_s
        Ta = self.ambient_at(t_mid)
        a_f = math.exp(-dt_s / sc.frame_tau_s)
        self.frame_C = a_f * self.frame_C + (1 - a_f) * Ta
        u = self._u
        u[:, 0] = v
        u[:, 1] = Ta
        u[:, 2] = self.frame_C
        Ad, Bd = self._matrices(dt_s)
        self.T = np.einsum("ijk,ik->ij", Ad, self.T) + np.einsum("ijk,ik->ij", Bd, u)
        a_s = math.exp(-dt_s / sc.spindle_tau_s)
        a_l = math.exp(-dt_s / sc.spindle_shaft_lag_s)
        self.housing_C = a_s * self.housing_C + (1 - a_s) * (Ta + (sc.spindle_rise_K if spindle_on else 0.0))
        self.shaft_C = a_l * self.shaft_C + (1 - a_l) * self.housing_C
        self.t_s += dt_s
        self.ambient_C = self.ambient_at(self.t_s)

    # ------------------------------------------------------------------ outputs
    def growth_mm(self) -> np.ndarray:
        """True strut growth (6,) mm over the reference temperature."""
        return np.einsum("ij,ij->i", self.T - self.T_ref, self.C)

    def mean_C(self) -> np.ndarray:
        return self.T.mean(axis=1)

    def spindle_growth_mm(self) -> float:
        """True tool growth along the tool axis (the shaft's temperature), mm."""
        return spindle_growth_mm(self.shaft_C, self.cfg)

    def readings(self) -> dict:
        """Noisy probe readings, in the ``temperatures`` op's dict form plus ``time_s``."""
        r = self.rng
        p = self.T[:, self.pidx] + r.normal(0.0, self.noise_K, (6, len(self.pidx)))
        return {"probes_C": {"struts": p.tolist(),
                             "ambient": float(self.ambient_C + r.normal(0.0, self.noise_K)),
                             "frame": float(self.frame_C + r.normal(0.0, self.noise_K))},
                "spindle_C": float(self.housing_C + r.normal(0.0, self.spindle_noise_K)),
                "time_s": self.t_s}

    def truth(self) -> dict:
        return {"time_s": self.t_s, "strut_growth_mm": self.growth_mm().tolist(),
                "strut_mean_C": self.mean_C().tolist(), "ambient_C": self.ambient_C, "frame_C": self.frame_C,
                "spindle_housing_C": self.housing_C, "spindle_growth_mm": self.spindle_growth_mm()}


def thermal_plant(cfg, **kw) -> ThermalPlant:
    """Factory: the simulated machine's heat for the daemon."""
    return ThermalPlant(cfg, **kw)
