"""Simulated measuring instruments, each with a documented noise model.

Every instrument looks at the *true* platform pose (:mod:`hexacnc.sim.truth`) and returns what
a real one would report, as measured coordinates of the measurement contract
(``docs/measurements.md``) plus the target they refer to:

* :class:`LaserTracker` - a 6-DOF tracker (T-Mac style probe on the carrier) whose software
  reports the **platform** pose in the base frame (the target's offset to the platform frame
  is part of the tracker's own setup).  Noise, Gaussian, independent per reading:
  ``sigma_xyz = sigma0_mm + ppm * distance`` per axis (default 3 um + 3 um/m from the station
  at ``station_mm``), ``sigma_abc = sigma_deg`` (default 0.0005 deg) per angle.
  ``position_only=True`` reports x, y, z only.
* :class:`TouchProbe` - a touch probe on the spindle and a reference artefact of spheres at
  known places (a 3D ball artefact, centres calibrated to ``artefact_sigma_mm``).  A probing
  cycle (5 touches: 4 around the equator, 1 on top) gives the sphere centre in machine
  coordinates; compared with the calibrated centre it gives the **tool tip** position at the
  readings the machine stood at.  Noise per axis: the touch repeatability ``sigma_mm``
  (default 0.5 um) averaged over the touches that see that axis (x, y: 2 touches, z: 1),
  plus the artefact's calibration ``artefact_sigma_mm`` (default 1 um, fixed per sphere).
  The cycle is simulated by its result (see docs/calibration-cycle.md: what is not done).
* :class:`DialIndicator` - one coordinate of the **tool tip** (default z) against a reference
  surface at a known place; noise ``sigma_mm`` (default 1 um) per reading.

``noise_floor_um`` is the RMS tool-tip error (3-D, over the coordinates the instrument
measures) that the instrument alone gives on a perfect machine at the given poses
(Monte Carlo, seeded): the best any calibration verified with it can show.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..pose import matrix_from_euler

INSTRUMENTS = ("tracker", "probe", "indicator")


@dataclass
class Reading:
    """One instrument reading: measured coordinates (mm / deg) of ``target`` and their sigma."""
    instrument: str
    target: str                      #: "platform" or "tool" (the tool tip)
    values: dict                     #: subset of x, y, z, a, b, c
    sigma: dict = field(default_factory=dict)


def _tip(X: np.ndarray, tip_mm: np.ndarray) -> np.ndarray:
    return X[:3] + matrix_from_euler(*X[3:6]) @ tip_mm


class LaserTracker:
    name = "tracker"
    target = "platform"

    def __init__(self, seed: int = 0, sigma0_mm: float = 0.003, ppm: float = 3.0, sigma_deg: float = 0.0005,
                 station_mm=(1800.0, 0.0, -900.0), position_only: bool = False):
        self.rng = np.random.default_rng(seed)
        self.sigma0_mm, self.ppm, self.sigma_deg = float(sigma0_mm), float(ppm), float(sigma_deg)
        self.station = np.asarray(station_mm, dtype=float)
        self.position_only = bool(position_only)

    def sigma_mm(self, X: np.ndarray) -> float:
        return self.sigma0_mm + self.ppm * 1e-6 * float(np.linalg.norm(X[:3] - self.station))

    def read(self, X_true: np.ndarray, tip_mm: np.ndarray) -> Reading:
        s = self.sigma_mm(X_true)
        p = X_true[:3] + self.rng.normal(0.0, s, 3)
        vals = {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}
        sig = {"x": s, "y": s, "z": s}
        if not self.position_only:
            ang = np.degrees(X_true[3:6]) + self.rng.normal(0.0, self.sigma_deg, 3)
            vals.update({"a": float(ang[0]), "b": float(ang[1]), "c": float(ang[2])})
            sig.update({"a": self.sigma_deg, "b": self.sigma_deg, "c": self.sigma_deg})
        return Reading(self.name, self.target, vals, sig)


class TouchProbe:
    name = "probe"
    target = "tool"

    def __init__(self, seed: int = 0, sigma_mm: float = 0.0005, artefact_sigma_mm: float = 0.001,
                 spheres_mm=None):
        self.rng = np.random.default_rng(seed)
        self.sigma_mm, self.artefact_sigma_mm = float(sigma_mm), float(artefact_sigma_mm)
        if spheres_mm is None:        # 3D ball artefact: 3 x 3 x 3 spheres, 100 mm apart
            g = np.array([-100.0, 0.0, 100.0])
            spheres_mm = [(x, y, z) for z in (-1250.0, -1150.0, -1050.0) for y in g for x in g]
        self.spheres = np.asarray(spheres_mm, dtype=float)
        # the artefact's calibration error: fixed per sphere (seeded), unknown to everyone
        self.sphere_error = np.random.default_rng(seed + 7919).normal(0.0, self.artefact_sigma_mm,
                                                                      self.spheres.shape)
        self.axis_sigma = np.sqrt(np.array([self.sigma_mm ** 2 / 2, self.sigma_mm ** 2 / 2, self.sigma_mm ** 2])
                                  + self.artefact_sigma_mm ** 2)

    def nearest_sphere(self, tip_mm) -> int:
        return int(np.argmin(np.linalg.norm(self.spheres - np.asarray(tip_mm, dtype=float)[None], axis=1)))

    def read(self, X_true: np.ndarray, tip_mm: np.ndarray) -> Reading:
        p = _tip(X_true, tip_mm)
        k = self.nearest_sphere(p)
        if np.linalg.norm(p - self.spheres[k]) > 5.0:
            return Reading(self.name, self.target, {}, {})   # no sphere within reach of a probing cycle
        touch = self.rng.normal(0.0, 1.0, 3) * np.sqrt(np.array([self.sigma_mm ** 2 / 2,
                                                                self.sigma_mm ** 2 / 2, self.sigma_mm ** 2]))
        m = p + touch + self.sphere_error[k]
        vals = {"x": float(m[0]), "y": float(m[1]), "z": float(m[2])}
        return Reading(self.name, self.target, vals, dict(zip("xyz", map(float, self.axis_sigma))))


class DialIndicator:
    name = "indicator"
    target = "tool"

    def __init__(self, seed: int = 0, sigma_mm: float = 0.001, axis: str = "z"):
        if axis not in ("x", "y", "z"):
            raise ValueError(f"indicator axis {axis!r}: expected x, y or z")
        self.rng = np.random.default_rng(seed)
        self.sigma_mm = float(sigma_mm)
        self.axis = axis

    def read(self, X_true: np.ndarray, tip_mm: np.ndarray) -> Reading:
        p = _tip(X_true, tip_mm)
        j = "xyz".index(self.axis)
        v = float(p[j] + self.rng.normal(0.0, self.sigma_mm))
        return Reading(self.name, self.target, {self.axis: v}, {self.axis: self.sigma_mm})


def make_instrument(name: str, seed: int = 0, **kw):
    if name == "tracker":
        return LaserTracker(seed, **kw)
    if name == "probe":
        return TouchProbe(seed, **kw)
    if name == "indicator":
        return DialIndicator(seed, **kw)
    raise ValueError(f"unknown instrument {name!r}; known: {', '.join(INSTRUMENTS)}")


def measured_tip(reading_values: dict, target: str, tip_mm: np.ndarray, X_cmd: np.ndarray) -> dict:
    """Tool-tip coordinates (mm) a reading gives; a platform reading without angles uses the
    commanded orientation (only for position-only trackers)."""
    v = reading_values
    if target == "tool":
        return {k: float(v[k]) for k in "xyz" if k in v}
    if not all(k in v for k in "xyz"):
        return {}
    ang = [math.radians(v[k]) if k in v else X_cmd[3 + i] for i, k in enumerate("abc")]
    p = np.array([v["x"], v["y"], v["z"]]) + matrix_from_euler(*ang) @ tip_mm
    return {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}


def noise_floor_um(name: str, poses_rad: np.ndarray, tip_mm, seed: int = 12345, draws: int = 20) -> float:
    """RMS tool-tip error (um) the instrument alone shows on a perfect machine at ``poses_rad``."""
    tip = np.asarray(tip_mm, dtype=float)
    inst = make_instrument(name, seed)
    errs = []
    for _ in range(draws):
        for X in np.asarray(poses_rad, dtype=float):
            if name == "probe":      # the floor of a probe is where its spheres are
                Xs = X.copy()
                Xs[:3] += inst.spheres[inst.nearest_sphere(_tip(X, tip))] - _tip(X, tip)
                X = Xs
            r = inst.read(X, tip)
            m = measured_tip(r.values, r.target, tip, X)
            if not m:
                continue
            t = _tip(X, tip)
            errs.append(sum((m[k] - t["xyz".index(k)]) ** 2 for k in m))
    return float(1e3 * math.sqrt(np.mean(errs))) if errs else math.nan
