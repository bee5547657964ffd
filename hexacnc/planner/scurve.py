"""Time-optimal rest-to-rest motion of one coordinate under constant velocity, acceleration and jerk bounds
(the seven-phase "S-curve"), vectorised over many moves.

A move of length ``D`` with bounds ``V, A, J`` (all > 0) accelerates with jerk ``+J`` for ``t1``, at ``a_p = J t1``
for ``t2``, with jerk ``-J`` for ``t1`` (velocity ``v_p``), cruises for ``t4`` and mirrors the ramp down.  Its time
is non-decreasing in ``D`` and non-increasing in each bound, and ``T(D, V, A, J) = T(kD, kV, kA, kJ)``: a move
scaled by ``k`` with bounds scaled by ``k`` takes the same time (what :mod:`hexacnc.planner.reststretch` relies
on).  Units: any length unit ``u``; ``V`` u/s, ``A`` u/s^2, ``J`` u/s^3, times s.
"""
from __future__ import annotations

import numpy as np


def _ramp(v, A, J):
    """(t1, t2) of the ramp from rest to velocity v (jerk phases t1, constant acceleration t2)."""
    t1 = np.minimum(A / J, np.sqrt(v / J))
    t2 = np.maximum(v / (J * t1) - t1, 0.0)
    return t1, t2


def peak_velocity(D, V, A, J):
    """Velocity ``v_p`` the move reaches (V, or less where a ramp up and down to V is longer than D)."""
    D, V, A, J = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (D, V, A, J)))
    vA = A * A / J                                    # velocity at which the acceleration saturates
    ta = np.where(V >= vA, V / A + A / J, 2.0 * np.sqrt(V / J))
    reach = V * ta <= D                               # the two ramps to V (each V ta / 2) fit
    d_a = 2.0 * vA * np.sqrt(vA / J)                  # both ramps to vA (each vA * 2 A/J / 2)
    with np.errstate(invalid="ignore"):
        v_sat = 0.5 * (-vA + np.sqrt(vA * vA + 4.0 * A * D))
        v_jerk = np.cbrt(0.5 * D * np.sqrt(J)) ** 2
    vp = np.where(D >= d_a, v_sat, v_jerk)
    return np.where(reach, V, np.minimum(vp, V))


def move_time(D, V, A, J):
    """Seconds of the time-optimal rest-to-rest move (0 for D <= 0)."""
    t1, t2, t4 = phases(D, V, A, J)
    return np.where(np.asarray(D, dtype=float) > 0, 2.0 * (2.0 * t1 + t2) + t4, 0.0)


def phases(D, V, A, J):
    """Phase durations (t1, t2, t4) of the moves (arrays): jerk phases t1, constant acceleration t2, cruise t4."""
    D = np.maximum(np.asarray(D, dtype=float), 0.0)
    vp = peak_velocity(D, V, A, J)
    t1, t2 = _ramp(vp, A, J)
    with np.errstate(divide="ignore", invalid="ignore"):
        t4 = np.where(vp > 0, np.maximum(D - vp * (2.0 * t1 + t2), 0.0) / np.where(vp > 0, vp, 1.0), 0.0)
    return t1, t2, t4


def positions(D: float, V: float, A: float, J: float, t: np.ndarray, phase: tuple | None = None) -> np.ndarray:
    """Positions (same shape as ``t``) of the move at times ``t`` (clipped to [0, D]; non-decreasing).
    ``phase``: its :func:`phases` (t1, t2, t4), if known."""
    t1, t2, t4 = (float(x) for x in (phase if phase is not None else phases(D, V, A, J)))
    dur = (t1, t2, t1, t4, t1, t2, t1)
    jerk = np.array([J, 0.0, -J, 0.0, -J, 0.0, J])
    edges = np.zeros(8)
    s, v, a = np.zeros(8), np.zeros(8), np.zeros(8)
    for k in range(7):
        h, j = dur[k], jerk[k]
        edges[k + 1] = edges[k] + h
        s[k + 1] = s[k] + v[k] * h + a[k] * h * h / 2.0 + j * h ** 3 / 6.0
        v[k + 1] = v[k] + a[k] * h + j * h * h / 2.0
        a[k + 1] = a[k] + j * h
    t = np.asarray(t, dtype=float)
    k = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, 6)
    tau = np.clip(t - edges[k], 0.0, np.asarray(dur)[k])
    out = s[k] + v[k] * tau + a[k] * tau * tau / 2.0 + jerk[k] * tau ** 3 / 6.0
    out = np.where(t >= edges[-1], D, out)
    return np.maximum.accumulate(np.clip(out, 0.0, D).ravel()).reshape(out.shape)
