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
"""
from __future__ import annotations

import ipaddress
import dataclasses
import math
import os
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ConfigError
from .opconfig import OperatorConfig, parse_operator

_REQUIRED = object()

#: path of the embedded default machine (simulated drives, no root needed)
DEFAULT_CONFIG_NAME = "default.toml"


def default_config_path() -> Path:
    """Path of ``config/default.toml`` (repository) or the packaged copy."""
    repo = Path(__file__).resolve().parent.parent / "config" / DEFAULT_CONFIG_NAME
    if repo.exists():
        return repo
    return Path(str(resources.files("hexacnc") / "data" / DEFAULT_CONFIG_NAME))



def _bus_nodes(b: "Section", bus: "BusConfig") -> "BusConfig":
    """``[bus] nodes``: a list of tables ``{node_id = N, eds = "file.eds|dcf", vendor_id = ...,
    product_code = ..., revision = ...}`` (all but node_id optional), one per drive in strut order.
    Sets node_ids (must agree with an explicit ``node_ids``), node_eds, node_identity."""
    if not b.has("nodes"):
        return bus
    entries = b._get("nodes", None)
    if not isinstance(entries, list) or len(entries) != 6 or not all(isinstance(e, dict) for e in entries):
        raise b.error("nodes", "expected a list of 6 tables like {node_id = 1, eds = \"drive.eds\"}")
    base = os.path.dirname(os.path.abspath(b.path)) if os.path.isfile(b.path) else os.getcwd()
    ids, eds, idents = [], [], []
    for k, e in enumerate(entries):
        where = f"nodes[{k}]"
        extra = set(e) - {"node_id", "eds", "vendor_id", "product_code", "revision"}
        if extra:
            raise b.error(where, f"unknown key(s) {sorted(extra)}")
        nid = e.get("node_id")
        if isinstance(nid, bool) or not isinstance(nid, int) or not 1 <= nid <= 127:
            raise b.error(where, f"node_id must be an integer 1..127, got {nid!r}")
        ids.append(nid)
        path = e.get("eds", "")
        if not isinstance(path, str):
            raise b.error(where, f"eds must be a file name, got {path!r}")
        if path:
            path = os.path.join(base, os.path.expanduser(path))
            if not os.path.isfile(path):
                raise b.error(where, f"eds {path!r}: no such file")
        eds.append(path)
        ident = []
        for key in ("vendor_id", "product_code", "revision"):
            v = e.get(key, -1)
            if isinstance(v, bool) or not isinstance(v, int) or not -1 <= v <= 0xFFFFFFFF:
                raise b.error(where, f"{key} must be an integer 0..0xFFFFFFFF, got {v!r}")
            ident.append(v)
        idents.append(tuple(ident))
    if len(set(ids)) != 6:
        raise b.error("nodes", f"node ids must be 6 distinct integers, got {ids}")
    if b.has("node_ids") and tuple(ids) != tuple(bus.node_ids):
        raise b.error("nodes", f"node ids {ids} disagree with [bus] node_ids {list(bus.node_ids)}")
    return dataclasses.replace(bus, node_ids=tuple(ids), node_eds=tuple(eds), node_identity=tuple(idents))

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


# ---------------------------------------------------------------------------
# Section data
# ---------------------------------------------------------------------------
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
class ToolConfig:
    axis_platform: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    tip_platform_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True)
class KinematicsConfig:
    fk_tolerance_mm: float = 1e-6
    fk_max_iterations: int = 30
    max_condition: float = 1e4                 #: Jacobian condition number counted as near-singular


@dataclass(frozen=True)
class CycleConfig:
    period_s: float = 0.0005
    max_overruns_in_row: int = 3
    setpoint_timeout_s: float = 0.05
    realtime_priority: int = 80
    cpu: int = -1                              #: -1: last CPU
    following_error_mm: float = 1.0
    watchdog_s: float = 2.0
    spin_s: float = 0.0002                     #: the hot loop spins this long before each deadline
    #: a drive without a fresh position sample this long faults (stale feedback), heartbeat or not; also
    #: the longest stall of the feedback the following-error check still matches to its SYNC
    feedback_timeout_s: float = 0.35


@dataclass(frozen=True)
class BusConfig:
    interface: str = "virtual"                 #: socketcan | virtual | udp_multicast
    channel: str = "hexacnc"
    bitrate: int = 1_000_000
    fd: bool = False
    data_bitrate: int = 2_000_000
    buses: int = 2                             #: 1 Mbit/s classic: 2 buses so feedback fits 0.5 ms
    node_ids: tuple[int, ...] = (1, 2, 3, 4, 5, 6)
    layout: str = "paired"                     #: single | paired | fd | separate (no dummies)
    feedback_divider: int = 3                  #: TPDO every n-th SYNC (staggered per drive)
    max_load: float = 0.95                     #: worst-case bus time / cycle
    increments_per_mm: float = 10000.0
    heartbeat_ms: int = 100
    heartbeat_timeout_ms: int = 350
    simulate: bool = True                      #: start the simulated drives process
    simulate_profile: str = "permissive"       #: permissive | strict (simulated drives, see drivers/README.md)
    node_eds: tuple = ()                       #: per node: EDS/DCF path ("" = bundled default), from [bus] nodes
    node_identity: tuple = ()                  #: per node: (vendor, product, revision), -1 = from the EDS
    boot_timeout_s: float = 15.0               #: boot-up messages after NMT reset
    #: drives stop on their own (quick stop) when the master is silent this long (configured at boot:
    #: heartbeat consumer 0x1016, RPDO/SYNC time-outs); the hot loop's master heartbeat comes 4x as often
    comm_loss_timeout_s: float = 0.02
    feed_mm_per_rev: float = 0.0               #: strut travel per driving-shaft revolution (0: units unchecked)
    write_factor_group: bool = False           #: write 0x6092 feed constant from increments_per_mm x feed_mm_per_rev


@dataclass(frozen=True)
class DaemonConfig:
    #: "" = the default place (hexacnc.daemon.sockpath.server_socket_path): $RUNTIME_DIRECTORY under
    #: systemd, else $XDG_RUNTIME_DIR/hexacnc/, else a 0700 /tmp/hexacnc-UID/ the user owns
    socket_path: str = ""
    tcp_port: int = 0                          #: 0: no TCP
    tcp_token: str = ""                        #: legacy: prefer token_file; >= 128 bits either way (checked
                                               #: with the file modes at start: hexacnc.daemon.admission.preflight)
    token_file: str = ""                       #: TCP token, a file only the daemon's user can read
    controller_group: str = ""                 #: Unix peers in this group may command motion
    observer_group: str = ""                   #: Unix peers in this group may only read
    sensor_group: str = ""                     #: Unix peers in this group may read and send temperatures
    tcp_role: str = "controller"               #: role of an authenticated TCP client
    service_user: str = "hexacnc"              #: clients trust sockets owned by this user (and own/root)
    idle_timeout_s: float = 600.0              #: a connection silent this long (no wait/stream running) is closed
    max_unauthenticated: int = 16              #: TCP connections before "hello": own pool, never a client slot
    enable_at_start: bool = True               #: resolved at load: default true only with [bus] simulate
    tcp_host: str = "127.0.0.1"                #: TCP address; other than loopback only with TLS
    tls_cert: str = ""                         #: PEM certificate: TLS on the TCP socket (with tls_key)
    tls_key: str = ""                          #: PEM private key, readable by the daemon's user only
    status_rate_hz: float = 20.0
    log_level: str = "INFO"
    max_clients: int = 32                      #: simultaneous socket clients
    max_message_bytes: int = 16 * 1024 * 1024  #: largest protocol message accepted
    #: a program is interpreted and planned in a child process with at most this address space (MB)
    max_plan_memory_mb: int = 4096
    #: ... and at most this long (s); over either it is refused naming the limit and the line reached
    max_plan_s: float = 300.0


@dataclass(frozen=True)
class PlannerConfig:
    lookahead_segments: int = 200
    default_feed_mm_min: float = 1000.0
    rapid_feed_mm_min: float = 15000.0
    max_angular_velocity_deg_s: float = 90.0
    path_tolerance_mm: float = 0.01
    sample_bound_mm: float = 0.001
    #: lines up to this tool-tip length (mm) that meet at small turns are smoothed into one C2 curve
    #: inside the G64 P tolerance (CAM output; see hexacnc/planner/smooth.py); 0 = corner blends only
    smooth_max_segment_mm: float = 0.0
    work_offset_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: user/remap M-codes (100..9999) the interpreter accepts as no-ops (noted in the program's
    #: messages), e.g. LinuxCNC's M428/M429 kinematics switches, which a hexapod does not need
    noop_m_codes: tuple = ()


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


@dataclass(frozen=True)
class ToolTableConfig:
    """``[tools] length_mm = {"1" = 62.5, ...}``: tool number -> length along the tool axis (G43 H)."""
    length_mm: dict = field(default_factory=dict)


@dataclass(frozen=True)
class GcodeConfig:
    """``[gcode]``: subroutine search path (``o<name> call`` of ``name.ngc``), program-end rule."""
    subroutine_path: tuple = ()     #: directories (relative ones: to the config file's directory)
    require_end: bool = False       #: refuse programs without M2/M30/% at the end (LinuxCNC)


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
    operator: OperatorConfig = field(default_factory=OperatorConfig)   #: see hexacnc/opconfig.py
    gcode: GcodeConfig = field(default_factory=GcodeConfig)
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


def _daemon_config(d: Section, bus: BusConfig) -> DaemonConfig:
    """``[daemon]``: socket, access (groups, TCP token, TLS), time-outs, enable at start."""
    dd = DaemonConfig()
    daemon = DaemonConfig(
        socket_path=_expand_user_vars(d.getstr("socket_path", dd.socket_path)),
        tcp_port=d.getint("tcp_port", dd.tcp_port, minval=0, maxval=65535),
        tcp_token=d.getstr("tcp_token", dd.tcp_token),
        status_rate_hz=d.getfloat("status_rate_hz", dd.status_rate_hz, above=0.0, maxval=1000.0),
        log_level=d.getchoice("log_level", ("DEBUG", "INFO", "WARNING", "ERROR"), dd.log_level),
        max_clients=d.getint("max_clients", dd.max_clients, minval=1, maxval=1024),
        max_message_bytes=d.getint("max_message_bytes", dd.max_message_bytes, minval=4096, maxval=1 << 30),
        max_plan_memory_mb=d.getint("max_plan_memory_mb", dd.max_plan_memory_mb, minval=512, maxval=1 << 20),
        max_plan_s=d.getfloat("max_plan_s", dd.max_plan_s, above=0.0, maxval=86400.0),
        token_file=_expand_user_vars(d.getstr("token_file", dd.token_file)),
        controller_group=d.getstr("controller_group", dd.controller_group),
        observer_group=d.getstr("observer_group", dd.observer_group),
        sensor_group=d.getstr("sensor_group", dd.sensor_group),
        tcp_role=d.getchoice("tcp_role", ("controller", "sensor", "observer"), dd.tcp_role),
        service_user=d.getstr("service_user", dd.service_user),
        idle_timeout_s=d.getfloat("idle_timeout_s", dd.idle_timeout_s, minval=1.0, maxval=86400.0),
        max_unauthenticated=d.getint("max_unauthenticated", dd.max_unauthenticated, minval=1, maxval=1024),
        enable_at_start=d.getbool("enable_at_start", bool(bus.simulate)),
        tcp_host=_tcp_host(d),
        tls_cert=_expand_user_vars(d.getstr("tls_cert", dd.tls_cert)),
        tls_key=_expand_user_vars(d.getstr("tls_key", dd.tls_key)),
    )
    if bool(daemon.tls_cert) != bool(daemon.tls_key):
        raise d.error("tls_key" if daemon.tls_cert else "tls_cert", "tls_cert and tls_key go together")
    if not daemon.tls_cert and not ipaddress.ip_address(daemon.tcp_host).is_loopback:
        raise d.error("tcp_host", f"value {daemon.tcp_host!r} is not a loopback address: off the host the "
                                  f"token needs TLS (set tls_cert and tls_key)")
    if daemon.tcp_port and not (daemon.tcp_token or daemon.token_file):
        raise d.error("token_file", "a token is required when tcp_port is set (token_file, or legacy tcp_token)")
    return daemon


def _tcp_host(d: Section) -> str:
    v = d.getstr("tcp_host", "127.0.0.1")
    try:
        return str(ipaddress.ip_address(v))
    except ValueError:
        raise d.error("tcp_host", f"value {v!r} is not an IP address") from None


def _freeze(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def _section(path: str, doc: dict, name: str, required: bool) -> Section:
    t = doc.get(name)
    if t is None and required:
        raise ConfigError(f"{path}: section [{name}] is missing")
    if t is not None and not isinstance(t, dict):
        raise ConfigError(f"{path}: [{name}] must be a table")
    return Section(path, name, t)


_KNOWN_SECTIONS = ("machine", "geometry", "struts", "joints", "carrier", "tool", "spindle",
                   "workspace", "thermal", "kinematics", "cycle", "bus", "daemon", "planner", "tools",
                   "homing", "jog",
                   "dynamics", "calibration", "gcode", "simulation")


def parse_config(doc: dict, path: str = "<config>") -> MachineConfig:
    """Build a :class:`MachineConfig` from a parsed TOML document."""
    unknown = sorted(set(doc) - set(_KNOWN_SECTIONS))
    if unknown:
        raise ConfigError(f"{path}: unknown section(s): {', '.join('[' + u + ']' for u in unknown)}; "
                          f"known: {', '.join(_KNOWN_SECTIONS)}")
    sections: list[Section] = []

    def sec(name: str, required: bool = False) -> Section:
        s = _section(path, doc, name, required)
        sections.append(s)
        return s

    m = sec("machine")
    name = m.getstr("name", Path(path).stem)

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

    c = sec("carrier", True)
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

    t = sec("tool")
    axis = t.getvec("axis_platform", 3, [0.0, 0.0, 1.0])
    if abs(float(np.linalg.norm(axis)) - 1.0) > 1e-3:
        raise t.error("axis_platform", f"{axis.tolist()} is not a unit vector")
    tool = ToolConfig(axis_platform=_freeze(axis / np.linalg.norm(axis)),
                      tip_platform_mm=_freeze(t.getvec("tip_platform_mm", 3, [0.0, 0.0, 0.0])))

    sp = sec("spindle")
    spindle = SpindleConfig(growth_mm_per_K=sp.getfloat("growth_mm_per_K", 0.0012, minval=0.0, maxval=1.0),
                            reference_temperature_C=sp.getfloat("reference_temperature_C", 20.0,
                                                                minval=-50.0, maxval=200.0),
                            probe_lag_s=sp.getfloat("probe_lag_s", 0.0, minval=0.0, maxval=36000.0))

    w = sec("workspace", True)
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

    th = sec("thermal")
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

    k = sec("kinematics")
    kin = KinematicsConfig(
        fk_tolerance_mm=k.getfloat("fk_tolerance_mm", 1e-6, above=0.0, maxval=1.0),
        fk_max_iterations=k.getint("fk_max_iterations", 30, minval=1, maxval=1000),
        max_condition=k.getfloat("max_condition", 1e4, above=1.0),
    )

    cy = sec("cycle")
    cd = CycleConfig()
    cycle = CycleConfig(
        period_s=cy.getfloat("period_s", cd.period_s, minval=1e-4, maxval=0.1),
        max_overruns_in_row=cy.getint("max_overruns_in_row", cd.max_overruns_in_row, minval=1, maxval=1000),
        setpoint_timeout_s=cy.getfloat("setpoint_timeout_s", cd.setpoint_timeout_s, above=0.0, maxval=10.0),
        realtime_priority=cy.getint("realtime_priority", cd.realtime_priority, minval=1, maxval=99),
        cpu=cy.getint("cpu", cd.cpu, minval=-1, maxval=1023),
        following_error_mm=cy.getfloat("following_error_mm", cd.following_error_mm, above=0.0),
        watchdog_s=cy.getfloat("watchdog_s", cd.watchdog_s, above=0.0, maxval=600.0),
        spin_s=cy.getfloat("spin_s", cd.spin_s, minval=0.0, maxval=0.1),
        feedback_timeout_s=cy.getfloat("feedback_timeout_s", cd.feedback_timeout_s, above=0.0, maxval=10.0),
    )
    ferr = (s.getvec("max_following_error_mm", 6, above=0.0, maxval=1000.0, allow_scalar=True)
            if s.has("max_following_error_mm") else None)
    if cycle.spin_s > 0.8 * cycle.period_s:
        raise cy.error("spin_s", f"{cycle.spin_s:g} s is more than 80 % of period_s = {cycle.period_s:g} s: "
                                 "the hot loop must sleep part of every period (SCHED_FIFO throttling)")

    b = sec("bus")
    bd = BusConfig()
    node_ids = b.getvec("node_ids", 6, list(bd.node_ids), minval=1, maxval=127)
    if len(set(int(x) for x in node_ids)) != 6 or any(x != int(x) for x in node_ids):
        raise b.error("node_ids", f"must be 6 distinct integers 1..127, got {node_ids.tolist()}")
    bus = BusConfig(
        interface=b.getchoice("interface", ("socketcan", "virtual", "udp_multicast"), bd.interface),
        channel=b.getstr("channel", bd.channel),
        bitrate=b.getint("bitrate", bd.bitrate, minval=10_000, maxval=1_000_000),
        fd=b.getbool("fd", bd.fd),
        data_bitrate=b.getint("data_bitrate", bd.data_bitrate, minval=10_000, maxval=8_000_000),
        buses=b.getint("buses", bd.buses, minval=1, maxval=6),
        node_ids=tuple(int(x) for x in node_ids),
        layout=b.getchoice("layout", ("single", "paired", "fd", "separate"), bd.layout),
        feedback_divider=b.getint("feedback_divider", bd.feedback_divider, minval=1, maxval=100),
        max_load=b.getfloat("max_load", bd.max_load, above=0.0, maxval=1.0),
        increments_per_mm=b.getfloat("increments_per_mm", bd.increments_per_mm, above=0.0, maxval=1e7),
        heartbeat_ms=b.getint("heartbeat_ms", bd.heartbeat_ms, minval=1, maxval=10000),
        heartbeat_timeout_ms=b.getint("heartbeat_timeout_ms", bd.heartbeat_timeout_ms, minval=1, maxval=60000),
        comm_loss_timeout_s=b.getfloat("comm_loss_timeout_s", bd.comm_loss_timeout_s, minval=0.002, maxval=10.0),
        simulate=b.getbool("simulate", bd.simulate),
        simulate_profile=b.getchoice("simulate_profile", ("permissive", "strict"), bd.simulate_profile),
        boot_timeout_s=b.getfloat("boot_timeout_s", bd.boot_timeout_s, above=0.0, maxval=600.0),
        feed_mm_per_rev=b.getfloat("feed_mm_per_rev", bd.feed_mm_per_rev, minval=0.0, maxval=1e4),
        write_factor_group=b.getbool("write_factor_group", bd.write_factor_group),
    )
    bus = _bus_nodes(b, bus)

    d = sec("daemon")
    daemon = _daemon_config(d, bus)

    p = sec("planner")
    pd = PlannerConfig()
    planner = PlannerConfig(
        lookahead_segments=p.getint("lookahead_segments", pd.lookahead_segments, minval=50, maxval=10_000_000),
        default_feed_mm_min=p.getfloat("default_feed_mm_min", pd.default_feed_mm_min, above=0.0),
        rapid_feed_mm_min=p.getfloat("rapid_feed_mm_min", pd.rapid_feed_mm_min, above=0.0),
        max_angular_velocity_deg_s=p.getfloat("max_angular_velocity_deg_s", pd.max_angular_velocity_deg_s,
                                              above=0.0),
        path_tolerance_mm=p.getfloat("path_tolerance_mm", pd.path_tolerance_mm, above=0.0),
        sample_bound_mm=p.getfloat("sample_bound_mm", pd.sample_bound_mm, above=0.0),
        smooth_max_segment_mm=p.getfloat("smooth_max_segment_mm", pd.smooth_max_segment_mm, minval=0.0,
                                         maxval=1000.0),
        work_offset_mm=_freeze(p.getvec("work_offset_mm", 3, [0.0, 0.0, 0.0])),
        noop_m_codes=_noop_m_codes(p),
    )

    tl = sec("tools")
    lengths = tl._get("length_mm", {})
    if not isinstance(lengths, dict):
        raise tl.error("length_mm", f"expected a table of tool number = length, got {lengths!r}")
    tool_len: dict[int, float] = {}
    for key, v in lengths.items():
        if not str(key).isdigit() or not 1 <= int(key) <= 99999:
            raise tl.error("length_mm", f"tool number {key!r} must be an integer 1..99999")
        if not Section._is_number(v) or not math.isfinite(float(v)) or not -1000.0 <= float(v) <= 1000.0:
            raise tl.error("length_mm", f"tool {key}: length {v!r} must be a number in [-1000, 1000] mm")
        tool_len[int(key)] = float(v)
    tools = ToolTableConfig(length_mm=tool_len)

    dy = sec("dynamics")
    dyd = DynamicsConfig()
    dynamics = DynamicsConfig(
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

    calibration = _parse_calibration(sec("calibration"))
    operator = parse_operator(w, p, d, sec("homing"), sec("jog"))
    gcode = _parse_gcode(sec("gcode"), path)
    simulation_truth = _simulation_truth(sec("simulation"), path)

    for sct in sections:
        sct.finish()

    cfg = MachineConfig(
        path=path, name=name,
        base_joints_mm=_freeze(base), platform_joints_mm=_freeze(plat), strut_offset_mm=_freeze(off),
        min_length_mm=_freeze(lmin), max_length_mm=_freeze(lmax), max_velocity_mm_s=_freeze(vmax),
        max_acceleration_mm_s2=_freeze(amax), max_jerk_mm_s3=_freeze(jmax), stiffness_N_per_mm=_freeze(stiff),
        base_axes=_freeze(base_axes), platform_axes=_freeze(plat_axes), max_angle_deg=_freeze(max_angle),
        mass_kg=mass, center_of_gravity_mm=_freeze(cog), gravity_mm_s2=_freeze(grav),
        inertia_kg_mm2=_freeze(inertia),
        home_pose=_freeze(home), workspace_min=_freeze(wmin), workspace_max=_freeze(wmax),
        tool=tool, spindle=spindle, thermal=thermal, kinematics=kin, cycle=cycle, bus=bus,
        daemon=daemon, planner=planner, tools=tools, dynamics=dynamics, calibration=calibration, operator=operator,
        gcode=gcode, simulation_truth=simulation_truth,
        max_following_error_mm=None if ferr is None else _freeze(ferr),
        raw=doc,
    )
    _check_geometry(cfg)
    _check_calibration(cfg)
    return cfg




def _parse_gcode(gs: Section, path: str) -> GcodeConfig:
    """``[gcode] subroutine_path = ["subs", "/opt/ngc"]``, ``require_end = false``."""
    raw = gs._get("subroutine_path", [])
    if isinstance(raw, str):
        raw = [raw]
    if not isinstance(raw, list) or len(raw) > 32 or not all(isinstance(d, str) and 0 < len(d) <= 4096
                                                               for d in raw):
        raise gs.error("subroutine_path", f"{raw!r} must be a list of at most 32 directory names")
    base = os.path.dirname(os.path.abspath(path)) if not path.startswith("<") else os.getcwd()
    dirs = tuple(d if os.path.isabs(d) else os.path.normpath(os.path.join(base, d)) for d in raw)
    return GcodeConfig(subroutine_path=dirs, require_end=gs.getbool("require_end", False))


def _simulation_truth(ss: Section, path: str) -> str:
    """``[simulation] truth``: a true machine file (relative to this file) for the simulated plant."""
    t = ss.getstr("truth", "")
    if not t:
        return ""
    p = Path(_expand_user_vars(t))
    if not p.is_absolute() and not path.startswith("<"):
        p = Path(path).parent / p
    if not p.is_file():
        raise ss.error("truth", f"{t!r}: no such file ({p})")
    return str(p)


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
                    raise cs.error("strut_nonlinearity_mm", f"row {i + 1}, P{k + 1} coefficient {coef[i, k]!r} mm "
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
    from .strutmap import SLOPE_MAX, SLOPE_MIN, STROKE_MARGIN, strut_map_from_config
    bad = strut_map_from_config(cfg).slope_violation()
    if bad is not None:
        i, q, slope = bad
        key = "strut_nonlinearity_mm" if cfg.calibration.strut_nonlinearity_mm.size else "strut_scale"
        raise ConfigError(f"{cfg.path}: [calibration] {key}: strut {i + 1}: the reading-to-length map has slope "
                          f"{slope:.4g} at reading {q:.4g} mm; it must stay within [{SLOPE_MIN}, {SLOPE_MAX}] over "
                          f"the stroke (+{STROKE_MARGIN:.0%}) of [struts] min/max_length_mm")


def _noop_m_codes(p: Section) -> tuple:
    """``[planner] noop_m_codes``: a list of distinct integers 100..9999 (user and remap M-codes only)."""
    v = p._get("noop_m_codes", [])
    if not isinstance(v, list):
        raise p.error("noop_m_codes", f"expected a list of M-code numbers, got {v!r}")
    out = []
    for m in v:
        if isinstance(m, bool) or not isinstance(m, int) or not 100 <= m <= 9999:
            raise p.error("noop_m_codes", f"{m!r} is not a user or remap M-code (an integer 100..9999); "
                                          "built-in M-codes cannot be made no-ops")
        if m in out:
            raise p.error("noop_m_codes", f"M{m} is listed twice")
        out.append(m)
    return tuple(out)


def _check_geometry(cfg: MachineConfig) -> None:
    """Reject singular geometry and a home pose outside the limits."""
    from .kinematics import Hexapod  # local: kinematics imports config
    from .errors import KinematicsError
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


def load_config(path: str | os.PathLike | None = None) -> MachineConfig:
    """Read and check a machine description; ``None`` gives the embedded default."""
    p = Path(path) if path is not None else default_config_path()
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read machine description: {exc.strerror or exc}") from exc
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from exc
    return parse_config(doc, str(p))
