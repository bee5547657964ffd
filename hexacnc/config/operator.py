"""Operator settings of the machine description: ``[homing]``, ``[jog]`` and the operator keys of
``[workspace]``, ``[planner]`` and ``[daemon]`` (parsed by :func:`parse_operator` from the
:class:`hexacnc.config.Section` objects of :func:`hexacnc.config.parse_config`).

Keys (all optional, every value range-checked):

* ``[workspace] pivot_mm``: the point rotations jog about, platform frame (default: the tool tip);
  ``tip_min`` / ``tip_max``: the Cartesian soft limits of the tool tip (x y z mm, a b c deg,
  machine frame); default: ``min`` / ``max`` (the platform pose box) carried to the tool tip at the
  home orientation, i.e. shifted by ``R(home) tip_platform_mm``.
* ``[planner] max_feed_override``: the largest feed override accepted (1.0 .. 2.0, default 2.0);
  ``optional_stop``: the optional-stop switch at start (M1 pauses like M0 when on; default true, as
  LinuxCNC's canon starts it; the operator switches it with the ``override`` op / ``hexacnc optional-stop``);
  ``block_delete``: the block-delete switch at start (lines starting with ``/`` are skipped when on; default
  true, as LinuxCNC's canon; ``override`` op / ``hexacnc block-delete``, for programs taken after it).
* ``[daemon] state_dir``: where the persistent offsets and tool table live (default: beside the
  config file; for the embedded default machine ``$XDG_STATE_HOME/hexacnc``, else
  ``~/.local/state/hexacnc``).
* ``[homing] method``: ``absolute`` (absolute encoders: referenced at power-up) or ``cia402``
  (homing mode 6 of each drive: ``homing_method`` 0x6098, ``speed_search_mm_s`` /
  ``speed_zero_mm_s`` 0x6099, ``acceleration_mm_s2`` 0x609A, ``offset_mm`` 0x607C);
  ``required``: refuse program, MDI and Cartesian jog motion until referenced (default false);
  the reference is lost as :mod:`hexacnc.daemon.reference` says (``cia402``: any fault, a drive's
  boot-up, a failed homing run; both: an encoder-error EMCY).
* ``[jog] speed_mm_s``, ``speed_deg_s``, ``strut_speed_mm_s`` (continuous jog speeds),
  ``acceleration_scale`` (fraction of the strut limits a jog uses, 0.05 .. 0.8, default 0.3),
  ``deadman_s`` (a continuous jog stops when no confirmation came for this long, 0.01 .. 0.1,
  default 0.05).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class HomingConfig:
    method: str = "absolute"          #: absolute | cia402
    required: bool = False
    homing_method: int = 35           #: CiA 402 0x6098 (35/37: current position)
    speed_search_mm_s: float = 10.0   #: 0x6099 sub 1
    speed_zero_mm_s: float = 2.0      #: 0x6099 sub 2
    acceleration_mm_s2: float = 100.0  #: 0x609A
    offset_mm: np.ndarray = field(default_factory=lambda: np.zeros(6))   #: 0x607C per strut


@dataclass(frozen=True)
class JogConfig:
    speed_mm_s: float = 10.0
    speed_deg_s: float = 2.0
    strut_speed_mm_s: float = 5.0
    acceleration_scale: float = 0.3
    deadman_s: float = 0.05


@dataclass(frozen=True)
class OperatorConfig:
    homing: HomingConfig = field(default_factory=HomingConfig)
    jog: JogConfig = field(default_factory=JogConfig)
    pivot_mm: np.ndarray | None = None        #: platform frame; None: the tool tip
    tip_min: np.ndarray | None = None         #: explicit tool-tip limits (else derived, see tip_box)
    tip_max: np.ndarray | None = None
    max_feed_override: float = 2.0
    state_dir: str = ""
    optional_stop: bool = True                #: the M1 switch at start (LinuxCNC: on)
    block_delete: bool = True                 #: skip '/' lines (LinuxCNC: on)


def _frozen(v) -> np.ndarray:
    a = np.array(v, dtype=float)
    a.setflags(write=False)
    return a


def parse_operator(w, p, d, hm, jg) -> OperatorConfig:
    """Operator keys from the sections ``[workspace]`` ``w``, ``[planner]`` ``p``, ``[daemon]`` ``d``,
    ``[homing]`` ``hm`` and ``[jog]`` ``jg`` (each a :class:`hexacnc.config.Section`)."""
    hd = HomingConfig()
    homing = HomingConfig(
        method=hm.getchoice("method", ("absolute", "cia402"), hd.method),
        required=hm.getbool("required", hd.required),
        homing_method=hm.getint("homing_method", hd.homing_method, minval=-128, maxval=127),
        speed_search_mm_s=hm.getfloat("speed_search_mm_s", hd.speed_search_mm_s, above=0.0, maxval=1000.0),
        speed_zero_mm_s=hm.getfloat("speed_zero_mm_s", hd.speed_zero_mm_s, above=0.0, maxval=1000.0),
        acceleration_mm_s2=hm.getfloat("acceleration_mm_s2", hd.acceleration_mm_s2, above=0.0, maxval=1e5),
        offset_mm=_frozen(hm.getvec("offset_mm", 6, [0.0] * 6, minval=-1000.0, maxval=1000.0,
                                    allow_scalar=True)),
    )
    jd = JogConfig()
    jog = JogConfig(
        speed_mm_s=jg.getfloat("speed_mm_s", jd.speed_mm_s, above=0.0, maxval=200.0),
        speed_deg_s=jg.getfloat("speed_deg_s", jd.speed_deg_s, above=0.0, maxval=45.0),
        strut_speed_mm_s=jg.getfloat("strut_speed_mm_s", jd.strut_speed_mm_s, above=0.0, maxval=200.0),
        acceleration_scale=jg.getfloat("acceleration_scale", jd.acceleration_scale, minval=0.05, maxval=0.8),
        deadman_s=jg.getfloat("deadman_s", jd.deadman_s, minval=0.01, maxval=0.1),
    )
    pivot = w.getvec("pivot_mm", 3, None, minval=-1e4, maxval=1e4) if w.has("pivot_mm") else None
    tmin = w.getvec("tip_min", 6, None) if w.has("tip_min") else None
    tmax = w.getvec("tip_max", 6, None) if w.has("tip_max") else None
    w.used.update({"pivot_mm", "tip_min", "tip_max"})
    if (tmin is None) != (tmax is None):
        raise w.error("tip_min" if tmin is None else "tip_max", "tip_min and tip_max go together")
    if tmin is not None:
        for i in range(6):
            if not tmin[i] < tmax[i]:
                raise w.error("tip_max", f"coordinate {'xyzabc'[i]}: tip_max {tmax[i]} must exceed "
                                         f"tip_min {tmin[i]}")
    mfo = p.getfloat("max_feed_override", 2.0, minval=1.0, maxval=2.0)
    ostop = p.getbool("optional_stop", True)
    bdel = p.getbool("block_delete", True)
    sdir = d.getstr("state_dir", "")
    return OperatorConfig(homing=homing, jog=jog, pivot_mm=None if pivot is None else _frozen(pivot),
                          tip_min=None if tmin is None else _frozen(tmin),
                          tip_max=None if tmax is None else _frozen(tmax),
                          max_feed_override=mfo, state_dir=sdir, optional_stop=ostop,
                          block_delete=bdel)


def tip_box(cfg) -> tuple[np.ndarray, np.ndarray]:
    """Cartesian soft limits of the tool tip (machine frame): (lo, hi), x y z mm, a b c deg."""
    op = cfg.operator
    if op.tip_min is not None:
        return np.asarray(op.tip_min, dtype=float), np.asarray(op.tip_max, dtype=float)
    from ..pose import matrix_from_euler
    home = np.asarray(cfg.home_pose, dtype=float)
    R = matrix_from_euler(*np.radians(home[3:6]))
    shift = np.r_[R @ np.asarray(cfg.tool.tip_platform_mm, dtype=float), 0.0, 0.0, 0.0]
    return np.asarray(cfg.workspace_min, dtype=float) + shift, np.asarray(cfg.workspace_max, dtype=float) + shift


def tip_violation(cfg, tip_deg, box=None) -> str | None:
    """None when the tool tip pose (mm/deg, machine frame) is inside the soft limits, else a text."""
    lo, hi = box if box is not None else tip_box(cfg)
    for i in range(6):
        v = float(tip_deg[i])
        if not math.isfinite(v) or v < lo[i] - 1e-9 or v > hi[i] + 1e-9:
            unit = "mm" if i < 3 else "deg"
            return (f"tool tip {'xyzabc'[i]} = {v:.3f} {unit} outside the [workspace] soft limit "
                    f"[{lo[i]:.3f}, {hi[i]:.3f}]")
    return None
