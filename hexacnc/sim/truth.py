"""The simulated *true* machine: the machine the plant and the simulated instruments follow.

A truth file is a complete machine description (the same TOML, read by the same loader, so an
unknown key or an impossible value is refused like in any config) plus an optional ``[truth]``
section with what only the plant has:

* ``backlash_mm`` (6 or one, 0..1): half backlash of each strut drive; the physical length is
  ``+h`` after the strut last extended and ``-h`` after it last retracted;
* ``payload_kg`` (0..1000): extra mass at the tool tip the carrier actually carries;
* ``seed``, ``description``: provenance (written by ``hexacnc calib synth-machine``).

Every other difference to the controller's description is simply a different value in the
usual sections: joint positions, strut offsets, per-strut stiffness, carrier mass and centre of
gravity, thermal parameters, ``[calibration] strut_scale`` / ``strut_nonlinearity_mm`` (the
true reading-to-length map of each strut).

Plant mapping (:meth:`TrueMachine.platform_pose_rad`): drive readings ``q`` (mm, what the
drive encoders count) -> true strut lengths ``L = strut_offset + map(q) + h * dir + f / k``
(``f`` the static strut forces at the true pose under the true carrier mass, COG and payload,
``k`` the true per-strut stiffness) -> true platform pose by forward kinematics of the true
geometry (fixed point over the force, 3 passes: the force changes by ~1e-4 of itself).
The controller's model never reads this file (``hexacnc run --truth`` gives it to the plant
side only: the simulated instruments in :mod:`hexacnc.sim.instruments`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import MachineConfig, Section, parse_config, read_toml
from ..errors import ConfigError
from ..kinematics import Hexapod
from ..pose import matrix_from_euler
from ..sag import gravity_wrench
from ..strutmap import strut_map_from_config

#: documented manufacturing tolerances of ``synth-machine`` (magnitude 1)
JOINT_ERROR_MM = (0.1, 0.3)          #: each joint coordinate off by 0.1..0.3 mm, random sign
OFFSET_ERROR_MM = (0.1, 0.5)         #: strut length at reading 0 (homing, length gauge)
STIFFNESS_REL = 0.20                 #: per-strut stiffness within +-20 % of nominal
GAIN_ERROR = (1e-4, 1e-3)            #: strut reading gain error (screw lead, encoder scale)
MASS_REL = 0.05                      #: carrier mass within +-5 %
COG_ERROR_MM = 5.0                   #: centre of gravity within +-5 mm per axis
BACKLASH_HALF_MM = (0.0, 0.003)      #: half backlash 0..3 um


@dataclass(frozen=True)
class TruthExtras:
    backlash_mm: np.ndarray
    payload_kg: float
    seed: int | None
    description: str


class TrueMachine:
    """The true machine: a :class:`MachineConfig` plus plant-only extras; maps readings to poses."""

    def __init__(self, cfg: MachineConfig, extras: TruthExtras, path: str = "<truth>"):
        self.cfg = cfg
        self.extras = extras
        self.path = path
        self.hx = Hexapod(cfg)
        self.smap = strut_map_from_config(cfg)
        self.off = np.asarray(cfg.strut_offset_mm, dtype=float)
        self.k = np.asarray(cfg.stiffness_N_per_mm, dtype=float)
        self.tip = np.asarray(cfg.tool.tip_platform_mm, dtype=float)
        self._X = self.hx.home_rad.copy()

    def lengths_unloaded(self, q, direction) -> np.ndarray:
        """Physical strut lengths (mm) without elastic elongation."""
        q = np.asarray(q, dtype=float)
        L = self.smap.strut_from_drive(self.off + q)
        return L + self.extras.backlash_mm * np.sign(np.asarray(direction, dtype=float))

    def forces_N(self, X: np.ndarray) -> np.ndarray:
        Jt = self.hx.jacobian_twist_rad(X)
        w = gravity_wrench(self.hx, X, self.extras.payload_kg)
        return np.linalg.solve(Jt.T, w)

    def platform_pose_rad(self, q, direction=None, guess=None) -> np.ndarray:
        """True platform pose (mm/rad) at drive readings ``q`` (mm); ``direction`` +-1 per strut
        (last motion: +1 extending), default +1."""
        d = np.ones(6) if direction is None else np.asarray(direction, dtype=float)
        L0 = self.lengths_unloaded(q, d)
        X = self._X if guess is None else np.asarray(guess, dtype=float)
        for _ in range(3):
            L = L0 + self.forces_N(X) / self.k
            res = self.hx.forward_rad(L, X.copy())
            if not res.ok:
                raise ValueError(f"{self.path}: readings {np.round(q, 4).tolist()} give no pose of the true "
                                 f"machine ({res.status})")
            X = np.r_[res.pose[:3], np.radians(res.pose[3:])]
        self._X = X.copy()
        return X

    def plant_config(self) -> MachineConfig:
        """The true machine as the simulated drives' strut model sees it: the payload (at the
        tool tip) merged into the carrier's mass and centre of gravity."""
        m, p = float(self.cfg.mass_kg), float(self.extras.payload_kg)
        if p <= 0.0:
            return self.cfg
        cog = (m * np.asarray(self.cfg.center_of_gravity_mm, dtype=float) + p * self.tip) / (m + p)
        return self.cfg.replace(mass_kg=m + p, center_of_gravity_mm=cog)

    def tool_tip_mm(self, X: np.ndarray) -> np.ndarray:
        R = matrix_from_euler(*X[3:6])
        return X[:3] + R @ self.tip


def _parse_extras(path: str, table) -> TruthExtras:
    s = Section(path, "truth", table)
    bl = s.getvec("backlash_mm", 6, [0.0] * 6, minval=0.0, maxval=1.0, allow_scalar=True)
    payload = s.getfloat("payload_kg", 0.0, minval=0.0, maxval=1000.0)
    seed = s.getint("seed", -1, minval=-1, maxval=2 ** 63 - 1)
    desc = s.getstr("description", "")
    s.finish()
    return TruthExtras(np.asarray(bl, dtype=float), float(payload), None if seed < 0 else seed, desc)


def parse_truth(doc: dict, path: str = "<truth>") -> TrueMachine:
    doc = dict(doc)
    extras = doc.pop("truth", None)
    if extras is not None and not isinstance(extras, dict):
        raise ConfigError(f"{path}: [truth] must be a table")
    cfg = parse_config(doc, path)
    return TrueMachine(cfg, _parse_extras(path, extras), path)


def load_truth(path) -> TrueMachine:
    """Read and check a truth file (a machine description plus ``[truth]``); ConfigError on anything bad."""
    p = Path(path)
    return parse_truth(read_toml(p, "the true machine description"), str(p))


def _signed(rng, lo: float, hi: float, n: int) -> np.ndarray:
    return rng.choice([-1.0, 1.0], n) * rng.uniform(lo, hi, n)


def synth_truth_doc(cfg: MachineConfig, seed: int, magnitude: float = 1.0) -> dict:
    """A plausible true machine around ``cfg`` (seeded); every tolerance scaled by ``magnitude``."""
    import copy
    if not (0.0 <= magnitude <= 20.0) or not math.isfinite(magnitude):
        raise ConfigError(f"--magnitude {magnitude!r}: expected 0..20")
    rng = np.random.default_rng(seed)
    m = float(magnitude)
    doc = copy.deepcopy(cfg.raw)
    base = np.asarray(cfg.base_joints_mm) + m * _signed(rng, *JOINT_ERROR_MM, 18).reshape(6, 3)
    plat = np.asarray(cfg.platform_joints_mm) + m * _signed(rng, *JOINT_ERROR_MM, 18).reshape(6, 3)
    off = np.asarray(cfg.strut_offset_mm) + m * _signed(rng, *OFFSET_ERROR_MM, 6)
    g = doc.setdefault("geometry", {})
    g["base_joints_mm"] = [[round(float(v), 6) for v in r] for r in base]
    g["platform_joints_mm"] = [[round(float(v), 6) for v in r] for r in plat]
    g["strut_offset_mm"] = [round(float(v), 6) for v in off]
    k = np.asarray(cfg.stiffness_N_per_mm) * (1.0 + m * STIFFNESS_REL * rng.uniform(-1, 1, 6))
    doc.setdefault("struts", {})["stiffness_N_per_mm"] = [round(float(v), 3) for v in np.maximum(k, 1.0)]
    car = doc.setdefault("carrier", {})
    car["mass_kg"] = round(float(cfg.mass_kg * (1.0 + m * MASS_REL * rng.uniform(-1, 1))), 4)
    car["center_of_gravity_mm"] = [round(float(v), 4) for v in
                                   np.asarray(cfg.center_of_gravity_mm) + m * rng.uniform(-COG_ERROR_MM,
                                                                                           COG_ERROR_MM, 3)]
    scale = 1.0 + m * _signed(rng, *GAIN_ERROR, 6)
    doc["calibration"] = {"strut_scale": [round(float(v), 9) for v in scale],
                          "source": f"hexacnc calib synth-machine --seed {seed} (true reading gain)"}
    doc.setdefault("machine", {})["name"] = f"{cfg.name}-truth-{seed}"
    bl = m * rng.uniform(*BACKLASH_HALF_MM, 6)
    doc["truth"] = {"backlash_mm": [round(float(v), 6) for v in bl], "payload_kg": 0.0, "seed": int(seed),
                    "description": f"synthetic true machine around {cfg.path}, magnitude {m:g}"}
    parse_truth(doc, "<synthetic truth>")      # refuse an impossible draw here, not at run time
    return doc
