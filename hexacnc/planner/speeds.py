"""Speed limits on the planning grid (step 3 of :mod:`hexacnc.planner.plan`): feed, angular velocity, strut
velocity, curvature jerk, the acceleration bounds' maximum velocity curve and the curvature steps at
tangent-continuous junctions, all as limits on ``x = s_dot^2``."""
from __future__ import annotations

import math

import numpy as np

from . import path as P
from .consts import ACC_SHARE, ETA_V, RHO_J, RHO_STEP
from .grid import Derivs, Grid
from .profile import ETA
from .toppvec import accel_coefficients


def feed_angular_limits(path: P.Path, cfg, pidx: np.ndarray, dtip: np.ndarray, Xg: np.ndarray) -> np.ndarray:
    """Limits on ``x = s_dot^2`` (N,) from the programmed feed and ``[planner] max_angular_velocity_deg_s`` at
    samples of pieces ``pidx`` with tool-tip rates ``dtip`` (N,6; mm and rad per s-unit) and platform poses
    ``Xg`` (N,6; mm, rad)."""
    xyz_speed = np.linalg.norm(dtip[:, :3], axis=1)
    ang_speed_deg = np.linalg.norm(np.degrees(dtip[:, 3:]), axis=1)
    meas = np.where(xyz_speed > 1e-6, xyz_speed, np.maximum(ang_speed_deg, 1e-12))
    xlim = (path.feed[pidx] / meas) ** 2
    # angular velocity |omega| = |E abc'| s_dot
    abc = Xg[:, 3:]
    cb_, sb_, cc_, sc_ = np.cos(abc[:, 1]), np.sin(abc[:, 1]), np.cos(abc[:, 2]), np.sin(abc[:, 2])
    da_, db_, dc_ = dtip[:, 3], dtip[:, 4], dtip[:, 5]
    wx = cc_ * cb_ * da_ - sc_ * db_
    wy = sc_ * cb_ * da_ + cc_ * db_
    wz = -sb_ * da_ + dc_
    wn = np.sqrt(wx * wx + wy * wy + wz * wz)
    wmax = math.radians(cfg.planner.max_angular_velocity_deg_s)
    with np.errstate(divide="ignore", over="ignore"):
        return np.minimum(xlim, np.where(wn > 1e-12, (wmax / np.maximum(wn, 1e-12)) ** 2, np.inf))


def speed_limits(path: P.Path, cfg, g: Grid, dv: Derivs, dt: float, vmax, amax, jmax):
    """Returns ``xlim`` (Ng,) and the acceleration bounds ``c, e, dd`` (Ng,6) of the TOPP pass."""
    Lp, Lppp = dv.Lp, dv.Lppp
    xlim = feed_angular_limits(path, cfg, g.pidx, dv.dtip, dv.Xg)
    with np.errstate(divide="ignore", over="ignore"):
        aLp = np.abs(Lp)
        xv = np.min(np.where(aLp > 1e-12, (ETA_V * 0.995 * vmax[None] / np.maximum(aLp, 1e-300)) ** 2, np.inf),
                    axis=1)
        aL3 = np.abs(Lppp)
        xj = np.min(np.where(aL3 > 1e-12, (RHO_J * ETA * jmax[None] / np.maximum(aL3, 1e-300)) ** (2.0 / 3.0),
                             np.inf), axis=1)
    xlim = np.minimum(np.minimum(xlim, xv), xj)
    c, e, dd, xmvc = accel_coefficients(Lp, dv.Lpp, ETA * ACC_SHARE * amax)
    xlim = np.minimum(xlim, xmvc)
    # curvature jumps at tangent-continuous junctions: an acceleration step dL'' x between two
    # cycles reads as a jerk dL'' x / dt, so x <= RHO_STEP J dt / |dL''|
    jn = np.nonzero(g.h == 0)[0]
    if jn.size:
        dLpp = np.abs(dv.Lpp[jn + 1] - dv.Lpp[jn])
        with np.errstate(divide="ignore"):
            xs = np.min(np.where(dLpp > 1e-12, RHO_STEP * jmax[None] * dt / np.maximum(dLpp, 1e-300), np.inf),
                        axis=1)
        xlim[jn] = np.minimum(xlim[jn], xs)
        xlim[jn + 1] = np.minimum(xlim[jn + 1], xs)
    return xlim, c, e, dd
