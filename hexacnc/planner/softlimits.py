"""Cartesian soft limits: the tool tip (tool length 0, machine frame) within the ``[workspace]`` box.

``[workspace] min`` / ``max`` are a box of platform poses around ``home_pose``.  For the tool tip the same
box is carried to the tip: its x, y, z bounds shifted by the tip's offset from the platform at the home pose
(``tip_home - home_pose[:3]``), a, b, c as given (the tip's orientation is the platform's).  So the tool tip
may travel from its home position as far as the box lets the platform travel from ``home_pose``; on the
default machine (tip 250 mm below the platform) x and y within +-150 mm of the home tip, z from 150 mm
below to 150 mm above it.  Programs are refused before motion at the first sample outside, naming the line
and the bound (:func:`check_tip_box`); MDI and jog use the same :func:`tip_box`.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import PlanError
from ..pose import matrix_from_euler

AXES = "xyzabc"
#: tolerance of the check (mm, deg): the programmed end points on the bound itself pass
TOLERANCE = 1e-6


def tip_box(cfg) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (6,) of the tool-tip pose, machine frame, mm and deg."""
    home = np.asarray(cfg.home_pose, dtype=float)
    R = matrix_from_euler(*(math.radians(float(v)) for v in home[3:6]))
    shift = R @ np.asarray(cfg.tool.tip_platform_mm, dtype=float)
    lo = np.asarray(cfg.workspace_min, dtype=float).copy()
    hi = np.asarray(cfg.workspace_max, dtype=float).copy()
    lo[:3] += shift
    hi[:3] += shift
    return lo, hi


def check_tip_box(cfg, tips_rad: np.ndarray, lines: np.ndarray) -> None:
    """Raise :class:`PlanError` at the first tool-tip pose (rows of (N,6) mm/rad) outside :func:`tip_box`,
    with its program line (``lines`` (N,)) and the bound as ``limit``."""
    if tips_rad.shape[0] == 0:
        return
    lo, hi = tip_box(cfg)
    T = np.array(tips_rad, dtype=float)
    T[:, 3:] = np.degrees(T[:, 3:])
    under = T < lo[None] - TOLERANCE
    over = T > hi[None] + TOLERANCE
    bad = np.any(under | over, axis=1)
    if not bad.any():
        return
    k = int(np.nonzero(bad)[0][0])
    i = int(np.nonzero(under[k] | over[k])[0][0])
    side, bound = ("min", lo[i]) if under[k, i] else ("max", hi[i])
    unit = "mm" if i < 3 else "deg"
    raise PlanError(f"tool tip {AXES[i]} {T[k, i]:.3f} {unit} (machine frame) beyond the workspace {side} "
                    f"{bound:.3f} {unit} (tool tip at [{', '.join(f'{v:.3f}' for v in T[k])}]; [workspace] "
                    f"{side} carried to the tool tip)", line=int(lines[k]), limit=f"workspace {side} {AXES[i]}")
