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
#: per piece, q = S u with u = [V_j, T_j, K_j, V_j+1, T_j+1, K_j+1] and q = [V_j, h T_j, h^2 K_j, h^2 K_j+1,
#: h T_j+1, V_j+1]: the row of S holding column i's one entry
_ROW = np.array([0, 1, 2, 5, 4, 3])


def _fit_runs(V0: np.ndarray, h: np.ndarray, nv: np.ndarray, length: np.ndarray):
    """Smoothing splines of several runs at once: one banded solve of their block-diagonal system (no entry
    couples two runs, so each run's solution is the one its own system gives).

    ``V0`` (sum nv, 6) the runs' vertices one run after the other, ``h`` (sum nv - len(nv),) their piece
    lengths, ``nv`` (r,) vertices per run, ``length`` (r,) each run's smoothing length.  Returns (V, T, K) each
    (sum nv, 6): positions, d/ds and d2/ds2 at the vertices; every run's end vertices are pinned to their
    programmed positions.  None where the factorisation breaks down in floating point.
    """
    nv = np.asarray(nv, dtype=np.int64)
    first = np.concatenate([[0], np.cumsum(nv)[:-1]])               # first vertex of each run
    last = first + nv - 1
    pv = np.repeat(first - np.concatenate([[0], np.cumsum(nv - 1)[:-1]]), nv - 1) + np.arange(h.shape[0])
    n = 3 * int(nv.sum())
    ab = np.zeros((6, n))                          # lower banded storage: ab[i - j, j] = A[i, j]
    # M = S^T G S / h^5 per piece; S has one entry per row and column (S[_ROW[i], i] = s), so each entry of
    # M is the product s_i G[_ROW[i], _ROW[j]] s_j, in the order S^T G S takes it
    one = np.ones_like(h)
    s = np.stack([one, h, h * h, h * h, h, one], axis=1)[:, _ROW]
    M = (s[:, :, None] * _G[np.ix_(_ROW, _ROW)][None]) * s[:, None, :] / (h ** 5)[:, None, None]
    base = 3 * pv
    for r in range(6):
        for c in range(r + 1):
            np.add.at(ab[r - c], base + c, M[:, r, c])
    # smoothing weight per vertex: the mean of its pieces' lengths (an end vertex: its piece's) / length^6
    hp = np.zeros(int(nv.sum()))
    np.add.at(hp, pv, 0.5 * h)
    np.add.at(hp, pv + 1, 0.5 * h)
    hp[first] = h[first - np.arange(nv.size)]
    hp[last] = h[last - np.arange(nv.size) - 1]
    mu = hp / np.repeat(length, nv) ** 6
    pin = PIN * np.maximum.reduceat(ab[0], 3 * first)
    mu[first] = pin
    mu[last] = pin
    ab[0, 0::3] += mu
    # positions relative to each run's first vertex (the solution moves with a translation of its vertices): the
    # low modes of this system are known to ~1e-16 cond (~1e14 on 4 um lines smoothed over 1 mm) of the
    # right-hand side, in machine coordinates ~1000 mm, around a run ~1-10 mm
    origin = np.repeat(V0[first], nv, axis=0)
    rhs = np.zeros((n, 6))
    rhs[0::3] = mu[:, None] * (V0 - origin)
    # symmetric diagonal scaling D A D y = D b, x = D y (unit diagonal): the entries of a position, a slope and a
    # curvature differ by h^-2 and h^-4, and a pinned vertex's by PIN more, so on micrometre lines (h^-5 ~ 1e15)
    # the unscaled factorisation broke down ("leading minor not positive definite")
    dg = 1.0 / np.sqrt(ab[0])
    for r in range(1, 6):
        ab[r, :n - r] *= dg[r:] * dg[:n - r]
    ab[0] = 1.0
    try:
        y = solveh_banded(ab, rhs * dg[:, None], lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    x = y * dg[:, None]
    return x[0::3] + origin, x[1::3], x[2::3]


def _fit_each(V0: np.ndarray, h: np.ndarray, nv: np.ndarray, length: np.ndarray):
    """:func:`_fit_runs` on all runs at once, or where that breaks down run by run: (V, T, K, fitted (r,) bool);
    a run whose own system breaks down gets NaN (its deviation is then not <= anything)."""
    fit = _fit_runs(V0, h, nv, length)
    if fit is not None:
        return (*fit, np.ones(nv.size, dtype=bool))
    out = [np.full_like(V0, np.nan) for _ in range(3)]
    fitted = np.zeros(nv.size, dtype=bool)
    v0 = np.concatenate([[0], np.cumsum(nv)])
    p0 = np.concatenate([[0], np.cumsum(nv - 1)])
    for r in range(nv.size):
        one = _fit_runs(V0[v0[r]:v0[r + 1]], h[p0[r]:p0[r + 1]], nv[r:r + 1], length[r:r + 1])
        if one is not None:
            fitted[r] = True
            for o, x in zip(out, one):
                o[v0[r]:v0[r + 1]] = x
    return (*out, fitted)


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
    # every pending run fitted in one solve per round; a run that stays out of its tolerance is smoothed less
    # (length halved) and after MAX_ROUNDS split at its worst piece (which stays a line), both sides tried anew
    pend = [(a, b, LENGTH_TOL * float(np.min(tol[a:b + 1])), 0) for a, b in todo]
    while pend:
        runs = np.array([(a, b) for a, b, _, _ in pend], dtype=np.int64)
        pieces = np.concatenate([np.arange(a, b + 1) for a, b in runs])
        verts = np.concatenate([np.arange(a, b + 2) for a, b in runs])
        nv = runs[:, 1] - runs[:, 0] + 2
        h = ra.slen[pieces]
        V, T, K, fitted = _fit_each(V0[verts], h, nv, np.array([L for _, _, L, _ in pend]))
        vi = np.concatenate([np.arange(o, o + k - 1) for o, k in zip(np.cumsum(nv) - nv, nv)])   # piece -> vertex
        D = h[:, None]
        qc = np.hstack([V[vi], T[vi] * D, K[vi] * D * D, K[vi + 1] * D * D, T[vi + 1] * D, V[vi + 1]])
        dev = _deviation(qc, c[pieces, 0:6], d[pieces])
        nxt = []
        o = 0
        for (a, b, length, rounds), ok in zip(pend, fitted):
            k = b - a + 1
            dv, q = dev[o:o + k], qc[o:o + k]
            o += k
            if not ok:
                continue                    # no smoothing spline in floating point: the run stays lines
            if np.all(dv <= TOL_SHARE * tol[a:b + 1]):
                kind[a:b + 1] = P.SPLINE
                coef[a:b + 1] = 0.0
                coef[a:b + 1, :36] = q
                tol[a:b + 1] = tol[a:b + 1] - dv
            elif rounds + 1 < MAX_ROUNDS:
                nxt.append((a, b, 0.5 * length, rounds + 1))
            else:
                w = a + int(np.argmax(dv / (TOL_SHARE * tol[a:b + 1])))
                for a2, b2 in ((a, w - 1), (w + 1, b)):
                    if b2 > a2:
                        nxt.append((a2, b2, LENGTH_TOL * float(np.min(tol[a2:b2 + 1])), 0))
        pend = nxt
    return dataclasses.replace(ra, kind=kind, coef=coef, tolerance=tol)
