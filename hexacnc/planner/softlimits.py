"""Cartesian soft limits: the ``[workspace]`` box (``min`` / ``max``: x, y, z mm, a, b, c deg).

The box is given, like ``home_pose``, for the platform pose; for the tool tip (tool length 0, machine frame)
it is the same box carried to the tip by the pose's own orientation: the tip ``t = X + R p_tip`` is within
its limits exactly when the platform position ``X`` is within the box (a, b, c are the same for both).  On
the default machine (tip 250 mm below the platform, +-150 mm box) an untilted tool tip may go +-150 mm in x
and y from the home tip.  Programs are refused before motion at the first sample outside, naming the line,
the tool tip and the bound (:func:`check_box`, limit ``"workspace max x"`` etc.); MDI and jog use the same
:func:`outside` test.
"""
from __future__ import annotations

import numpy as np

from ..errors import PlanError

AXES = "xyzabc"
#: tolerance of the check (mm, deg): programmed end points on the bound itself pass
TOLERANCE = 1e-6


def outside(cfg, platform_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(under, over): boolean (N,6) masks of platform poses (rows, mm and deg) below ``min`` / above ``max``."""
    lo = np.asarray(cfg.workspace_min, dtype=float)
    hi = np.asarray(cfg.workspace_max, dtype=float)
    X = np.atleast_2d(np.asarray(platform_deg, dtype=float))
    return X < lo[None] - TOLERANCE, X > hi[None] + TOLERANCE


def check_box(cfg, platform_rad: np.ndarray, tips_rad: np.ndarray, lines: np.ndarray) -> None:
    """Raise :class:`PlanError` at the first sample whose platform pose (rows of (N,6) mm/rad) is outside the
    workspace box, with its program line (``lines`` (N,)), the tool tip ``tips_rad`` there and the bound."""
    if platform_rad.shape[0] == 0:
        return
    X = np.array(platform_rad, dtype=float)
    X[:, 3:] = np.degrees(X[:, 3:])
    under, over = outside(cfg, X)
    bad = np.any(under | over, axis=1)
    if not bad.any():
        return
    k = int(np.nonzero(bad)[0][0])
    i = int(np.nonzero(under[k] | over[k])[0][0])
    side = "min" if under[k, i] else "max"
    bound = float((cfg.workspace_min if side == "min" else cfg.workspace_max)[i])
    T = np.array(tips_rad[k], dtype=float)
    T[3:] = np.degrees(T[3:])
    unit = "mm" if i < 3 else "deg"
    what = f"platform {AXES[i]} {X[k, i]:.3f} {unit}" if i < 3 else f"{AXES[i]} {X[k, i]:.3f} deg"
    raise PlanError(f"outside the workspace: {what} beyond [workspace] {side} {bound:g} {unit} with the tool tip "
                    f"at [{', '.join(f'{v:.3f}' for v in T)}] (machine frame)", line=int(lines[k]),
                    limit=f"workspace {side} {AXES[i]}")
