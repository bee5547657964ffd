"""Machine description: one TOML loader, read once at start.

Every value is range-checked, unknown sections and keys are rejected, and every
error names the file, the ``[section] key`` and the bad value.

Public contract (more keys may be added, none renamed):

* ``[geometry] base_joints_mm`` (6x3, base frame), ``platform_joints_mm``
  (6x3, platform frame), ``strut_offset_mm`` (6: strut length at drive reading 0).
* ``[struts] min_length_mm, max_length_mm, max_velocity_mm_s,
  max_acceleration_mm_s2, max_jerk_mm_s3, stiffness_N_per_mm`` (6 or one for all).
* ``[joints] base_axes, platform_axes`` (6x3 unit vectors), ``max_angle_deg``.
* ``[carrier] mass_kg, center_of_gravity_mm`` (platform frame), gravity along
  -z of the base frame unless ``gravity_mm_s2`` is given.
* ``[tools] length_mm = {"1" = 62.5}``: tool lengths (mm along the tool axis) for G43 H.
* ``[gcode] subroutine_path = ["subs"]`` (directories searched for ``<name>.ngc`` on ``o<name> call``;
  relative to the config file), ``require_end = false`` (true: refuse programs without M2/M30/%).
* ``[calibration] strut_scale`` (6 or one, dimensionless, 0.5..2), ``strut_nonlinearity_mm``
  (6 rows of Legendre coefficients P1..Pd, d <= 7), ``strut_nonlinearity_center_mm`` and
  ``strut_nonlinearity_half_range_mm`` (6, required with the polynomial), ``source``, ``date``:
  the reading-to-length map ``L = strut_offset + s q + sum_k c_k P_k((q - center) / half_range)``
  applied by the cycle (:mod:`hexacnc.strutmap`); absent = identity; the map's slope must stay in
  [0.5, 2] over the stroke.

Everything is stored in mm, mm/s, degrees at this interface; radians are
derived for the inside (``*_rad`` attributes).

The package keeps each section's typed dataclass beside its parse function: :mod:`.section` (the
range-checked :class:`Section` getters), :mod:`.machine` (:class:`MachineConfig`, :func:`parse_config`,
geometry/struts/joints/carrier/tool/workspace), :mod:`.runtime` (cycle, bus, daemon), :mod:`.models`
(thermal, spindle, dynamics, kinematics, calibration), :mod:`.planning` (planner, tools, gcode,
simulation) and :mod:`.load` (files, the embedded default).  Everything importable from
``hexacnc.config`` before the split is re-exported here.
"""
from __future__ import annotations

from .operator import OperatorConfig, parse_operator
from .load import DEFAULT_CONFIG_NAME, default_config_path, load_config, read_toml
from .machine import (_KNOWN_SECTIONS, MachineConfig, ToolConfig, _check_geometry, parse_carrier, parse_config,
                      parse_frame, parse_tool, parse_workspace)
from .models import (CalibrationConfig, DynamicsConfig, KinematicsConfig, SpindleConfig, ThermalConfig,
                     _check_calibration, _parse_calibration, parse_dynamics, parse_kinematics, parse_spindle,
                     parse_thermal)
from .planning import (GcodeConfig, PlannerConfig, ToolTableConfig, _noop_m_codes, _parse_gcode,
                       _simulation_truth, parse_planner, parse_tools)
from .runtime import (BusConfig, CycleConfig, DaemonConfig, _bus_nodes, _daemon_config, _tcp_host, parse_bus,
                      parse_cycle)
from .section import _REQUIRED, Section, Sections, _expand_user_vars, _freeze, _section
from ..errors import ConfigError

__all__ = [
    "BusConfig", "CalibrationConfig", "ConfigError", "CycleConfig", "DEFAULT_CONFIG_NAME", "DaemonConfig",
    "DynamicsConfig", "GcodeConfig", "KinematicsConfig", "MachineConfig", "OperatorConfig", "PlannerConfig",
    "Section", "Sections", "SpindleConfig", "ThermalConfig", "ToolConfig", "ToolTableConfig",
    "default_config_path", "load_config", "read_toml", "parse_bus", "parse_carrier", "parse_config", "parse_cycle",
    "parse_dynamics", "parse_frame", "parse_kinematics", "parse_operator", "parse_planner", "parse_spindle",
    "parse_thermal", "parse_tool", "parse_tools", "parse_workspace",
    # private helpers, importable as before the split
    "_KNOWN_SECTIONS", "_REQUIRED", "_bus_nodes", "_check_calibration", "_check_geometry", "_daemon_config",
    "_expand_user_vars", "_freeze", "_noop_m_codes", "_parse_calibration", "_parse_gcode", "_section",
    "_simulation_truth", "_tcp_host",
]
