"""The whole machine (:class:`MachineConfig`) and :func:`parse_config`, a short orchestrator over the
per-section parse functions; ``[geometry]``, ``[struts]``, ``[joints]``, ``[carrier]``, ``[tool]`` and
``[workspace]`` are parsed here."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError
from .operator import OperatorConfig, parse_operator
from .models import (CalibrationConfig, DynamicsConfig, KinematicsConfig, SpindleConfig, ThermalConfig,
                     _check_calibration, _parse_calibration, parse_dynamics, parse_kinematics, parse_spindle,
                     parse_thermal)
from .planning import (GcodeConfig, PlannerConfig, ToolTableConfig, _parse_gcode, _simulation_truth,
                       parse_planner, parse_tools)
from .runtime import BusConfig, CycleConfig, DaemonConfig, _daemon_config, parse_bus, parse_cycle
from .iomap import IoConfig, parse_io
from .section import Section, Sections, _freeze

@dataclass(frozen=True)
class ToolConfig:
    axis_platform: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    tip_platform_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True)
class MachineConfig:
    """The whole machine description. Arrays are read-only, mm and degrees."""
    path: str
    name: str
    base_joints_mm: np.ndarray          #: (6,3) base frame
    platform_joints_mm: np.ndarray      #: (6,3) platform frame
    strut_offset_mm: np.ndarray         #: (6,)
    min_length_mm: np.ndarray
    max_length_mm: np.ndarray
    max_velocity_mm_s: np.ndarray
    max_acceleration_mm_s2: np.ndarray
    max_jerk_mm_s3: np.ndarray
    stiffness_N_per_mm: np.ndarray
    base_axes: np.ndarray               #: (6,3) unit, base frame
    platform_axes: np.ndarray           #: (6,3) unit, platform frame
    max_angle_deg: np.ndarray           #: (6,)
    mass_kg: float
    center_of_gravity_mm: np.ndarray    #: (3,) platform frame
    gravity_mm_s2: np.ndarray           #: (3,) base frame
    inertia_kg_mm2: np.ndarray          #: (3,3) about the COG, platform frame
    home_pose: np.ndarray               #: (6,) x,y,z mm, a,b,c deg
    workspace_min: np.ndarray           #: (6,) box used for sampling/planning
    workspace_max: np.ndarray
    tool: ToolConfig
    spindle: SpindleConfig
    thermal: ThermalConfig
    kinematics: KinematicsConfig
    cycle: CycleConfig
    bus: BusConfig
    daemon: DaemonConfig
    planner: PlannerConfig
    tools: ToolTableConfig = field(default_factory=ToolTableConfig)
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    operator: OperatorConfig = field(default_factory=OperatorConfig)   #: see hexacnc/config/operator.py
    gcode: GcodeConfig = field(default_factory=GcodeConfig)
    io: IoConfig = field(default_factory=IoConfig)     #: ``[io]`` (hexacnc/config/iomap.py)
    #: ``[simulation] truth``: true machine the simulated plant follows (path, "" = none); the
    #: controller's model never reads it (hexacnc.sim.truth)
    simulation_truth: str = ""
    raw: dict = field(repr=False, default_factory=dict)
    #: ``[struts] max_following_error_mm`` (6,); None: ``[cycle] following_error_mm`` for every strut
    max_following_error_mm: np.ndarray | None = None

    @property
    def max_angle_rad(self) -> np.ndarray:
        return np.radians(self.max_angle_deg)

    def replace(self, **changes: Any) -> "MachineConfig":
        """A copy with some fields replaced (used by calibration)."""
        import dataclasses
        return dataclasses.replace(self, **changes)


_KNOWN_SECTIONS = ("machine", "geometry", "struts", "joints", "carrier", "tool", "spindle",
                   "workspace", "thermal", "kinematics", "cycle", "bus", "daemon", "planner", "tools",
                   "homing", "jog",
                   "dynamics", "calibration", "gcode", "simulation", "io")


def parse_config(doc: dict, path: str = "<config>") -> MachineConfig:
    """Build a :class:`MachineConfig` from a parsed TOML document."""
    unknown = sorted(set(doc) - set(_KNOWN_SECTIONS))
    if unknown:
        raise ConfigError(f"{path}: unknown section(s): {', '.join('[' + u + ']' for u in unknown)}; "
                          f"known: {', '.join(_KNOWN_SECTIONS)}")
    sec = Sections(path, doc)
    name = sec("machine").getstr("name", Path(path).stem)
    frame = parse_frame(sec)
    frame.update(parse_carrier(sec("carrier", True), frame["platform_joints_mm"]))
    tool = parse_tool(sec("tool"))
    spindle = parse_spindle(sec("spindle"))
    frame.update(parse_workspace(sec("workspace", True)))
    thermal = parse_thermal(sec("thermal"))
    kin = parse_kinematics(sec("kinematics"))
    cycle, ferr = parse_cycle(sec("cycle"), sec["struts"])
    bus = parse_bus(sec("bus"))
    daemon = _daemon_config(sec("daemon"), bus)
    planner = parse_planner(sec("planner"))
    tools = parse_tools(sec("tools"))
    dynamics = parse_dynamics(sec("dynamics"))
    calibration = _parse_calibration(sec("calibration"))
    operator = parse_operator(sec["workspace"], sec["planner"], sec["daemon"], sec("homing"), sec("jog"))
    gcode = _parse_gcode(sec("gcode"), path)
    simulation_truth = _simulation_truth(sec("simulation"), path)
    io = parse_io(sec("io"))
    sec.finish()
    cfg = MachineConfig(
        path=path, name=name, **frame,
        tool=tool, spindle=spindle, thermal=thermal, kinematics=kin, cycle=cycle, bus=bus,
        daemon=daemon, planner=planner, tools=tools, dynamics=dynamics, calibration=calibration, operator=operator,
        gcode=gcode, io=io, simulation_truth=simulation_truth, max_following_error_mm=ferr, raw=doc,
    )
    _check_geometry(cfg)
    _check_calibration(cfg)
    return cfg


def parse_frame(sec: Sections) -> dict[str, np.ndarray]:
    """``[geometry]``, ``[struts]`` and ``[joints]``: the MachineConfig fields they give (frozen arrays)."""
    g = sec("geometry", True)
    base = g.getmatrix("base_joints_mm", 6, 3)
    plat = g.getmatrix("platform_joints_mm", 6, 3)
    off = g.getvec("strut_offset_mm", 6, minval=0.0, allow_scalar=True)

    s = sec("struts", True)
    lmin = s.getvec("min_length_mm", 6, above=0.0, allow_scalar=True)
    lmax = s.getvec("max_length_mm", 6, above=0.0, allow_scalar=True)
    for i in range(6):
        if lmax[i] <= lmin[i]:
            raise s.error("max_length_mm", f"strut {i + 1}: max {lmax[i]} must exceed min_length_mm {lmin[i]}")
    vmax = s.getvec("max_velocity_mm_s", 6, above=0.0, allow_scalar=True)
    amax = s.getvec("max_acceleration_mm_s2", 6, above=0.0, allow_scalar=True)
    jmax = s.getvec("max_jerk_mm_s3", 6, above=0.0, allow_scalar=True)
    stiff = s.getvec("stiffness_N_per_mm", 6, above=0.0, allow_scalar=True)

    j = sec("joints", True)
    base_axes = j.getunits("base_axes", 6)
    plat_axes = j.getunits("platform_axes", 6)
    max_angle = j.getvec("max_angle_deg", 6, above=0.0, maxval=90.0, allow_scalar=True)
    return dict(
        base_joints_mm=_freeze(base), platform_joints_mm=_freeze(plat), strut_offset_mm=_freeze(off),
        min_length_mm=_freeze(lmin), max_length_mm=_freeze(lmax), max_velocity_mm_s=_freeze(vmax),
        max_acceleration_mm_s2=_freeze(amax), max_jerk_mm_s3=_freeze(jmax), stiffness_N_per_mm=_freeze(stiff),
        base_axes=_freeze(base_axes), platform_axes=_freeze(plat_axes), max_angle_deg=_freeze(max_angle))


def parse_carrier(c: Section, plat: np.ndarray) -> dict[str, Any]:
    """``[carrier]``: mass, centre of gravity (platform frame), gravity (base frame), inertia."""
    mass = c.getfloat("mass_kg", minval=0.0)
    cog = c.getvec("center_of_gravity_mm", 3)
    grav = c.getvec("gravity_mm_s2", 3, [0.0, 0.0, -9810.0])
    if c.has("inertia_kg_mm2"):
        inertia = c.getmatrix("inertia_kg_mm2", 3, 3)
        if not np.allclose(inertia, inertia.T) or np.any(np.linalg.eigvalsh(0.5 * (inertia + inertia.T)) < 0):
            raise c.error("inertia_kg_mm2", "must be symmetric positive semi-definite")
    else:
        c.used.add("inertia_kg_mm2")
        # a solid disc of the platform joint radius as a plausible default
        r = float(np.mean(np.linalg.norm(plat[:, :2], axis=1))) if mass > 0 else 0.0
        inertia = np.diag([mass * r * r / 4, mass * r * r / 4, mass * r * r / 2])
    return dict(mass_kg=mass, center_of_gravity_mm=_freeze(cog), gravity_mm_s2=_freeze(grav),
                inertia_kg_mm2=_freeze(inertia))


def parse_tool(t: Section) -> ToolConfig:
    """``[tool]``: tool axis (unit, platform frame) and tip (mm, platform frame)."""
    axis = t.getvec("axis_platform", 3, [0.0, 0.0, 1.0])
    if abs(float(np.linalg.norm(axis)) - 1.0) > 1e-3:
        raise t.error("axis_platform", f"{axis.tolist()} is not a unit vector")
    return ToolConfig(axis_platform=_freeze(axis / np.linalg.norm(axis)),
                      tip_platform_mm=_freeze(t.getvec("tip_platform_mm", 3, [0.0, 0.0, 0.0])))


def parse_workspace(w: Section) -> dict[str, np.ndarray]:
    """``[workspace]``: home pose inside the min/max box (default: home +-100 mm, +-10 deg)."""
    home = w.getvec("home_pose", 6)
    wmin = w.getvec("min", 6, None) if w.has("min") else None
    wmax = w.getvec("max", 6, None) if w.has("max") else None
    w.used.update({"min", "max"})
    if wmin is None:
        wmin = home + np.array([-100.0, -100.0, -100.0, -10.0, -10.0, -10.0])
    if wmax is None:
        wmax = home + np.array([100.0, 100.0, 100.0, 10.0, 10.0, 10.0])
    for i in range(6):
        if not (wmin[i] <= home[i] <= wmax[i]):
            raise w.error("home_pose", f"coordinate {'xyzabc'[i]}={home[i]} is outside [workspace] min/max "
                                       f"[{wmin[i]}, {wmax[i]}]")
    return dict(home_pose=_freeze(home), workspace_min=_freeze(wmin), workspace_max=_freeze(wmax))


def _check_geometry(cfg: MachineConfig) -> None:
    """Reject singular geometry and a home pose outside the limits."""
    from ..kinematics import Hexapod  # local: kinematics imports config
    from ..errors import KinematicsError
    hx = Hexapod(cfg)
    try:
        hx.check_pose(cfg.home_pose)
    except KinematicsError as exc:
        raise ConfigError(f"{cfg.path}: [workspace] home_pose {cfg.home_pose.tolist()}: {exc}") from exc
    cond = hx.condition(cfg.home_pose)
    if not np.isfinite(cond) or cond > cfg.kinematics.max_condition:
        raise ConfigError(f"{cfg.path}: [geometry] is singular or near-singular at the home pose "
                          f"(Jacobian condition {cond:.3g} > [kinematics] max_condition "
                          f"{cfg.kinematics.max_condition:.3g})")
