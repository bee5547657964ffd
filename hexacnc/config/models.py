"""``[thermal]``, ``[spindle]``, ``[dynamics]``, ``[kinematics]`` and ``[calibration]``: the model
sections, each typed dataclass beside its parse function."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ConfigError
from .section import Section, _freeze

if TYPE_CHECKING:
    from .machine import MachineConfig

@dataclass(frozen=True)
class ThermalConfig:
    """1-D heat model of each strut (see :mod:`hexacnc.thermal`)."""
    segments: int = 10
    expansion_per_K: float = 11.5e-6          #: linear expansion coefficient (steel)
    heat_per_speed_W_s_mm: float = 0.05        #: heat input per mm/s of strut speed, W
    conductivity_W_mK: float = 45.0
    density_kg_m3: float = 7850.0
    heat_capacity_J_kgK: float = 460.0
    area_mm2: float = 1200.0                   #: conducting cross-section
    perimeter_mm: float = 250.0                #: convective perimeter
    convection_W_m2K: float = 8.0
    end_conductance_W_K: float = 0.5           #: strut end to frame at each joint
    probes: tuple[int, ...] = (0, 5)           #: segment indices carrying a sensor
    probe_noise_K: float = 0.02
    process_noise_K: float = 0.01
    enabled: bool = True
    reference_temperature_C: float = 20.0      #: strut temperature at which offsets are zero (calibration)
    # -- in the daemon (hexacnc.daemon.thermalsup) --
    source: str = "auto"                       #: auto | sim | socket | none (auto: sim with [bus] simulate)
    probe_rate_hz: float = 1.0                 #: probe readings per wall-clock second (sim plant; socket nominal)
    sim_time_scale: float = 1.0                #: simulated plant seconds per wall-clock second
    sim_spindle_noise_K: float = 0.05          #: sim plant: spindle-housing probe noise (1 sigma)
    sim_seed: int = 1                          #: sim plant: noise seed
    max_offset_mm: float = 0.2                 #: |strut offset| and |spindle growth| never beyond this
    max_offset_rate_mm_s: float = 0.002        #: offsets change at most this fast (wall-clock)
    stale_after_s: float = 10.0                #: no reading for this long (wall-clock): warn, freeze offsets
    probe_min_C: float = -20.0                 #: a reading outside [probe_min_C, probe_max_C] is refused
    probe_max_C: float = 100.0


@dataclass(frozen=True)
class SpindleConfig:
    growth_mm_per_K: float = 0.0012            #: tool growth along the tool axis per K over reference
    reference_temperature_C: float = 20.0
    probe_lag_s: float = 0.0                   #: the growing shaft lags the housing probe (first order); 0: none


@dataclass(frozen=True)
class DynamicsConfig:
    """Strut drive and carrier dynamics for the simulator (see :mod:`hexacnc.sim.dynamics`)."""
    reflected_mass_kg: float = 60.0            #: motor + screw inertia reflected to the strut axis
    drive_lag_s: float = 0.0003                #: current loop + velocity sampling as a first-order lag
    strut_damping_ratio: float = 0.03          #: strut spring damping, ratio at k and mass/6 of the carrier
    bus_dead_time_s: float = 0.0015            #: setpoint/feedback dead time of the main control loop
    velocity_bandwidth_hz: float = 0.0         #: drive velocity loop; 0: tuned the conventional way
    position_gain_1_s: float = 0.0             #: drive position loop Kv factor; 0: bandwidth / 4
    integral_time_s: float = 0.0               #: velocity PI integral time; 0: 4 / bandwidth
    velocity_feedforward: bool = True          #: drives use the setpoint's rate as velocity feed-forward
    simulated_drives: str = "second_order"     #: strut model of the daemon's simulated drives: second_order | coupled


@dataclass(frozen=True)
class KinematicsConfig:
    fk_tolerance_mm: float = 1e-6
    fk_max_iterations: int = 30
    max_condition: float = 1e4                 #: Jacobian condition number counted as near-singular


@dataclass(frozen=True)
class CalibrationConfig:
    """``[calibration]``: strut-space causes fitted by ``hexacnc diagnose``/``calib fit`` (see
    :mod:`hexacnc.strutmap`).  Physical strut length from drive reading q (mm)::

        L = strut_offset + strut_scale * q + sum_k strut_nonlinearity_mm[k-1] * P_k((q - center) / half_range)

    Absent section: identity (scale 1, no polynomial)."""
    strut_scale: np.ndarray = field(default_factory=lambda: np.ones(6))                 #: (6,) dimensionless
    strut_nonlinearity_mm: np.ndarray = field(default_factory=lambda: np.zeros((6, 0)))  #: (6, d) Legendre P1..Pd
    strut_nonlinearity_center_mm: np.ndarray = field(default_factory=lambda: np.zeros(6))   #: reading at t = 0
    strut_nonlinearity_half_range_mm: np.ndarray = field(default_factory=lambda: np.ones(6))  #: reading per unit t
    source: str = ""                           #: provenance, free text (data, command, causes)
    date: str = ""                             #: when it was fitted (ISO 8601 text)

    @property
    def identity(self) -> bool:
        return bool(np.all(self.strut_scale == 1.0) and not np.any(self.strut_nonlinearity_mm != 0.0))


def parse_thermal(th: Section) -> ThermalConfig:
    """``[thermal]``: strut heat model, probes, the daemon's thermal source and offset limits."""
    dflt = ThermalConfig()
    segs = th.getint("segments", dflt.segments, minval=2, maxval=200)
    probes = th.getvec("probes", len(th.table.get("probes", dflt.probes)) or 1, list(dflt.probes),
                       minval=0, maxval=segs - 1)
    thermal = ThermalConfig(
        segments=segs,
        expansion_per_K=th.getfloat("expansion_per_K", dflt.expansion_per_K, minval=0.0, maxval=1e-3),
        heat_per_speed_W_s_mm=th.getfloat("heat_per_speed_W_s_mm", dflt.heat_per_speed_W_s_mm, minval=0.0),
        conductivity_W_mK=th.getfloat("conductivity_W_mK", dflt.conductivity_W_mK, above=0.0),
        density_kg_m3=th.getfloat("density_kg_m3", dflt.density_kg_m3, above=0.0),
        heat_capacity_J_kgK=th.getfloat("heat_capacity_J_kgK", dflt.heat_capacity_J_kgK, above=0.0),
        area_mm2=th.getfloat("area_mm2", dflt.area_mm2, above=0.0),
        perimeter_mm=th.getfloat("perimeter_mm", dflt.perimeter_mm, above=0.0),
        convection_W_m2K=th.getfloat("convection_W_m2K", dflt.convection_W_m2K, minval=0.0),
        end_conductance_W_K=th.getfloat("end_conductance_W_K", dflt.end_conductance_W_K, minval=0.0),
        probes=tuple(int(p) for p in probes),
        probe_noise_K=th.getfloat("probe_noise_K", dflt.probe_noise_K, above=0.0),
        process_noise_K=th.getfloat("process_noise_K", dflt.process_noise_K, above=0.0),
        enabled=th.getbool("enabled", dflt.enabled),
        reference_temperature_C=th.getfloat("reference_temperature_C", dflt.reference_temperature_C,
                                            minval=-50.0, maxval=200.0),
        source=th.getchoice("source", ("auto", "sim", "socket", "none"), dflt.source),
        probe_rate_hz=th.getfloat("probe_rate_hz", dflt.probe_rate_hz, minval=0.01, maxval=100.0),
        sim_time_scale=th.getfloat("sim_time_scale", dflt.sim_time_scale, minval=1.0, maxval=1e5),
        sim_spindle_noise_K=th.getfloat("sim_spindle_noise_K", dflt.sim_spindle_noise_K, minval=0.0, maxval=10.0),
        sim_seed=th.getint("sim_seed", dflt.sim_seed, minval=0, maxval=2 ** 31 - 1),
        max_offset_mm=th.getfloat("max_offset_mm", dflt.max_offset_mm, above=0.0, maxval=5.0),
        max_offset_rate_mm_s=th.getfloat("max_offset_rate_mm_s", dflt.max_offset_rate_mm_s, above=0.0,
                                         maxval=1.0),
        stale_after_s=th.getfloat("stale_after_s", dflt.stale_after_s, above=0.0, maxval=86400.0),
        probe_min_C=th.getfloat("probe_min_C", dflt.probe_min_C, minval=-100.0, maxval=300.0),
        probe_max_C=th.getfloat("probe_max_C", dflt.probe_max_C, minval=-100.0, maxval=300.0),
    )
    if thermal.probe_min_C >= thermal.probe_max_C:
        raise th.error("probe_max_C", f"must be above probe_min_C ({thermal.probe_min_C}), got {thermal.probe_max_C}")
    return thermal


def parse_spindle(sp: Section) -> SpindleConfig:
    """``[spindle]``: thermal growth of the tool along its axis."""
    return SpindleConfig(growth_mm_per_K=sp.getfloat("growth_mm_per_K", 0.0012, minval=0.0, maxval=1.0),
                         reference_temperature_C=sp.getfloat("reference_temperature_C", 20.0,
                                                             minval=-50.0, maxval=200.0),
                         probe_lag_s=sp.getfloat("probe_lag_s", 0.0, minval=0.0, maxval=36000.0))


def parse_kinematics(k: Section) -> KinematicsConfig:
    """``[kinematics]``: forward-kinematics tolerance and iterations, near-singular condition."""
    return KinematicsConfig(
        fk_tolerance_mm=k.getfloat("fk_tolerance_mm", 1e-6, above=0.0, maxval=1.0),
        fk_max_iterations=k.getint("fk_max_iterations", 30, minval=1, maxval=1000),
        max_condition=k.getfloat("max_condition", 1e4, above=1.0),
    )


def parse_dynamics(dy: Section) -> DynamicsConfig:
    """``[dynamics]``: strut drive and carrier dynamics of the simulator."""
    dyd = DynamicsConfig()
    return DynamicsConfig(
        reflected_mass_kg=dy.getfloat("reflected_mass_kg", dyd.reflected_mass_kg, above=0.0, maxval=1e5),
        drive_lag_s=dy.getfloat("drive_lag_s", dyd.drive_lag_s, above=0.0, maxval=0.1),
        strut_damping_ratio=dy.getfloat("strut_damping_ratio", dyd.strut_damping_ratio, minval=0.0, maxval=2.0),
        bus_dead_time_s=dy.getfloat("bus_dead_time_s", dyd.bus_dead_time_s, minval=0.0, maxval=0.1),
        velocity_bandwidth_hz=dy.getfloat("velocity_bandwidth_hz", dyd.velocity_bandwidth_hz, minval=0.0,
                                          maxval=5000.0),
        position_gain_1_s=dy.getfloat("position_gain_1_s", dyd.position_gain_1_s, minval=0.0, maxval=10000.0),
        integral_time_s=dy.getfloat("integral_time_s", dyd.integral_time_s, minval=0.0, maxval=10.0),
        velocity_feedforward=dy.getbool("velocity_feedforward", dyd.velocity_feedforward),
        simulated_drives=dy.getchoice("simulated_drives", ("second_order", "coupled"), dyd.simulated_drives),
    )


def _parse_calibration(cs: Section) -> CalibrationConfig:
    """``[calibration]``: per-strut scale and nonlinearity (Legendre coefficients), provenance."""
    cd = CalibrationConfig()
    scale = cs.getvec("strut_scale", 6, [1.0] * 6, minval=0.5, maxval=2.0, allow_scalar=True)
    if cs.has("strut_nonlinearity_mm"):
        v = cs.table["strut_nonlinearity_mm"]
        d = len(v[0]) if isinstance(v, (list, tuple)) and v and isinstance(v[0], (list, tuple)) else 0
        if not 1 <= d <= 7:
            raise cs.error("strut_nonlinearity_mm", f"expected 6 rows of 1 to 7 Legendre coefficients (P1..P7, mm), "
                                                    f"got {v!r}")
        coef = cs.getmatrix("strut_nonlinearity_mm", 6, d)
        for i in range(6):
            for k in range(d):
                if abs(coef[i, k]) > 1000.0:
                    coef_ik = float(coef[i, k])
                    raise cs.error("strut_nonlinearity_mm", f"row {i + 1}, P{k + 1} coefficient {coef_ik!r} mm "
                                                            f"is beyond +-1000 mm")
        for key in ("strut_nonlinearity_center_mm", "strut_nonlinearity_half_range_mm"):
            if not cs.has(key):
                raise cs.error(key, "missing: required with strut_nonlinearity_mm (the reading that maps to t = 0 "
                                    "and the reading per unit t of the polynomial, as fitted)")
        center = cs.getvec("strut_nonlinearity_center_mm", 6, minval=-1e5, maxval=1e5)
        half = cs.getvec("strut_nonlinearity_half_range_mm", 6, above=0.0, maxval=1e5)
    else:
        coef = cd.strut_nonlinearity_mm
        for key in ("strut_nonlinearity_center_mm", "strut_nonlinearity_half_range_mm"):
            if cs.has(key):
                raise cs.error(key, "given without strut_nonlinearity_mm")
        center = cd.strut_nonlinearity_center_mm
        half = cd.strut_nonlinearity_half_range_mm
    date = cs._get("date", "")
    if hasattr(date, "isoformat"):        # a TOML date or date-time
        date = date.isoformat()
    if not isinstance(date, str):
        raise cs.error("date", f"expected a date (TOML date or ISO 8601 text), got {date!r}")
    return CalibrationConfig(strut_scale=_freeze(scale), strut_nonlinearity_mm=_freeze(coef),
                             strut_nonlinearity_center_mm=_freeze(center),
                             strut_nonlinearity_half_range_mm=_freeze(half),
                             source=cs.getstr("source", ""), date=date)


def _check_calibration(cfg: MachineConfig) -> None:
    """The calibrated reading-to-length map must be monotone with a sane slope over the stroke."""
    if cfg.calibration.identity:
        return
    from ..strutmap import SLOPE_MAX, SLOPE_MIN, STROKE_MARGIN, strut_map_from_config
    bad = strut_map_from_config(cfg).slope_violation()
    if bad is not None:
        i, q, slope = bad
        key = "strut_nonlinearity_mm" if cfg.calibration.strut_nonlinearity_mm.size else "strut_scale"
        raise ConfigError(f"{cfg.path}: [calibration] {key}: strut {i + 1}: the reading-to-length map has slope "
                          f"{slope:.4g} at reading {q:.4g} mm; it must stay within [{SLOPE_MIN}, {SLOPE_MAX}] over "
                          f"the stroke (+{STROKE_MARGIN:.0%}) of [struts] min/max_length_mm")
