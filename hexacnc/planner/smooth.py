"""CAM polyline smoothing: runs of short lines -> one C2 curve inside the G64 P tolerance.

CAM output approximates curved surfaces by thousands of short lines (``3D_Chips.ngc``: 4,700
lines of 0.01-0.3 mm, G64 P0.1).  Blending every corner separately makes the curvature rise from
zero and fall back to zero at every vertex: the strut jerk ``L''' s_dot^3`` of those spikes, not
the machine's acceleration, then sets the speed.  Here a run of such lines becomes a chain of
quintic Hermite pieces (kind :data:`~hexacnc.planner.path.SPLINE`, one per programmed line, with
its line number and feed) whose vertex positions, first and second derivatives (in the chord
length ``s``) minimise the path's jerk energy ``sum of int |P'''(s)|^2 ds`` plus a penalty
``mu |V_k - V_k(programmed)|^2`` per vertex: a smoothing spline, C2 along the run.  ``mu =
h / l^6`` smooths features shorter than ``l`` (:data:`LENGTH_TOL` tolerances) and keeps longer
ones.

Rules (each checked, so the programmed contract holds):

* a run is made of feed moves (G1, not rapids) that are straight lines with a tool-tip
  length ``<= [planner] smooth_max_segment_mm`` (0 switches smoothing off) and a G64 tolerance
  ``> 0``, joining at turns of at most :data:`MAX_TURN_DEG`, with the same tool and no stop,
  exact stop (G61) or stopping event between them;
* the vertices at both ends of a run keep their programmed position (the corner there is
  blended or stopped as between lines);
* each piece deviates from its programmed line by at most :data:`TOL_SHARE` of the tolerance,
  measured at 17 points against the point of the line at the same ``s`` (an upper bound of the
  distance, as for corner blends); a run that deviates more is smoothed less (``l`` halved, up
  to :data:`MAX_ROUNDS` times), then split at its worst piece;
* the tolerance left for a corner blend at a run end is the tolerance minus the piece's own
  deviation, so blend plus smoothing stay inside G64 P.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.linalg import solveh_banded

from . import quintic as P

#: largest turn (deg) between consecutive short lines that are smoothed into one curve
MAX_TURN_DEG = 30.0
#: share of the G64 P tolerance a smoothed piece may deviate from its line (the rest: corner blends)
TOL_SHARE = 0.5
#: smoothing length in units of the tolerance (features shorter than this are smoothed)
LENGTH_TOL = 10.0
#: points at which a piece's deviation is measured
DEV_POINTS = 17
#: rounds of halving the smoothing length before a run is split
MAX_ROUNDS = 6
#: weight pinning the run-end vertices, relative to the largest diagonal entry
PIN = 1e8

# quintic Hermite basis (ascending powers of w), order [P0, V0, A0, A1, V1, P1] as in quintic.quintic
_BASIS = np.array([[1, 0, 0, -10, 15, -6], [0, 1, 0, -6, 8, -3], [0, 0, 0.5, -1.5, 1.5, -0.5],
                   [0, 0, 0, 0.5, -1, 0.5], [0, 0, 0, -4, 7, -3], [0, 0, 0, 10, -15, 6]], dtype=float)


def _third_derivative_gram() -> np.ndarray:
    """``G[i, j] = int_0^1 H_i''' H_j''' dw`` (exact: Gauss-Legendre on quadratics)."""
    x, wq = np.polynomial.legendre.leggauss(4)
    w = 0.5 * (x + 1.0)
    wq = 0.5 * wq
    p = np.arange(6)
    d3 = (p * (p - 1) * (p - 2))[None, :] * _BASIS                        # coefficient of w^(p-3)
    vals = d3[:, 3:] @ np.vstack([w ** 0, w, w ** 2])                     # (6, 4)
    return (vals * wq[None, :]) @ vals.T


_G = _third_derivative_gram()


def _fit_run(V0: np.ndarray, h: np.ndarray, length: float):
    """Smoothing spline through the run's vertices ``V0`` (m+1, 6) with piece lengths ``h`` (m,).

    Returns (V, T, K) each (m+1, 6): positions, d/ds and d2/ds2 at the vertices; the end
    vertices are pinned to their programmed positions.
    """
    m = h.shape[0]
    n = 3 * (m + 1)
    ab = np.zeros((6, n))                          # lower banded storage: ab[i - j, j] = A[i, j]
    # per piece: u = [V_j, T_j, K_j, V_j+1, T_j+1, K_j+1] -> q = [V_j, h T_j, h^2 K_j, h^2 K_j+1, h T_j+1, V_j+1]
    S = np.zeros((m, 6, 6))
    S[:, 0, 0] = 1.0
    S[:, 1, 1] = h
    S[:, 2, 2] = h * h
    S[:, 3, 5] = h * h
    S[:, 4, 4] = h
    S[:, 5, 3] = 1.0
    M = np.einsum("mki,kl,mlj->mij", S, _G, S) / (h ** 5)[:, None, None]
    base = 3 * np.arange(m)
    for r in range(6):
        for c in range(r + 1):
            np.add.at(ab[r - c], base + c, M[:, r, c])
    mu = np.zeros(m + 1)
    hv = np.concatenate([[h[0]], 0.5 * (h[:-1] + h[1:]), [h[-1]]])
    mu[:] = hv / length ** 6
    pin = PIN * float(np.max(ab[0]))
    mu[0] = mu[-1] = pin
    ab[0, 0::3] += mu
    rhs = np.zeros((n, 6))
    rhs[0::3] = mu[:, None] * V0
    x = solveh_banded(ab, rhs, lower=True, check_finite=False)
    return x[0::3], x[1::3], x[2::3]


def _pieces(V, T, K, h):
    """Quintic coefficients (m, 36) of the pieces between consecutive vertices."""
    D = h[:, None]
    return np.hstack([V[:-1], T[:-1] * D, K[:-1] * D * D, K[1:] * D * D, T[1:] * D, V[1:]])


def _deviation(qc: np.ndarray, c0: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Max deviation (:func:`~hexacnc.planner.quintic.pose_deviation`) of pieces from their lines."""
    w = np.linspace(0.0, 1.0, DEV_POINTS)
    Q = P.quintic(w[None, :, None], qc[:, None, :])
    return P.pose_deviation(Q - (c0[:, None, :] + w[None, :, None] * d[:, None, :])).max(axis=1)


def smooth_runs(ra, stop_after_raw: set, max_segment_mm: float):
    """Return ``ra`` (:class:`~hexacnc.planner.rawmoves.RawArrays`) with short-line runs as SPLINE pieces.

    ``stop_after_raw``: raw move indices followed by a stopping event.  ``ra`` is not modified.
    """
    n = ra.kind.shape[0]
    if max_segment_mm <= 0.0 or n < 2:
        return ra
    c = ra.coef
    d = c[:, 6:12]
    lx = np.linalg.norm(d[:, :3], axis=1)
    el = (ra.kind == P.LINE) & ~ra.rapid & (ra.tolerance > 0) & (lx > 1e-9) & (ra.slen <= max_segment_mm)
    cosang = np.einsum("ij,ij->i", d[:-1, :3], d[1:, :3]) / np.maximum(lx[:-1] * lx[1:], 1e-300)
    stop_j = np.zeros(n - 1, dtype=bool)
    for i in stop_after_raw:
        if 0 <= i < n - 1:
            stop_j[i] = True
    join = (el[:-1] & el[1:] & ~ra.exact_stop[:-1] & ~stop_j & (ra.tool_mm[:-1] == ra.tool_mm[1:])
            & (cosang >= math.cos(math.radians(MAX_TURN_DEG))))
    if not join.any():
        return ra
    V0 = np.vstack([c[:, 0:6], c[-1:, 0:6] + d[-1:]])            # vertex k = start of move k
    kind = ra.kind.copy()
    coef = ra.coef.copy()
    tol = ra.tolerance.copy()
    todo = []
    # runs: maximal chains of moves i..j whose inner junctions all join
    i = 0
    while i < n - 1:
        if not join[i]:
            i += 1
            continue
        j = i
        while j < n - 1 and join[j]:
            j += 1
        todo.append((i, j))                                     # moves i..j (j - i >= 1 junctions)
        i = j
    while todo:
        a, b = todo.pop()
        h = ra.slen[a:b + 1]
        t0 = float(np.min(tol[a:b + 1]))
        length = LENGTH_TOL * t0
        for _ in range(MAX_ROUNDS):
            V, T, K = _fit_run(V0[a:b + 2], h, length)
            qc = _pieces(V, T, K, h)
            dev = _deviation(qc, c[a:b + 1, 0:6], d[a:b + 1])
            if np.all(dev <= TOL_SHARE * tol[a:b + 1]):
                break
            length *= 0.5
        else:
            # split at the worst piece: it stays a line, both sides are tried again
            w = a + int(np.argmax(dev / (TOL_SHARE * tol[a:b + 1])))
            if w - 1 > a:
                todo.append((a, w - 1))
            if b > w + 1:
                todo.append((w + 1, b))
            continue
        kind[a:b + 1] = P.SPLINE
        coef[a:b + 1] = 0.0
        coef[a:b + 1, :36] = qc
        tol[a:b + 1] = tol[a:b + 1] - dev
    return dataclasses.replace(ra, kind=kind, coef=coef, tolerance=tol)
