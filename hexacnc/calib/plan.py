"""Calibration test plan: reachable poses that maximise observability of the 42 parameters.

Candidates are drawn uniformly in the configured workspace box and kept
within strut-length, joint-angle and conditioning limits.  The identification
Jacobian of each candidate (measured coordinates w.r.t. the parameters, whitened
by the instrument noise) feeds a greedy D-optimal selection followed by
Fedorov-style exchange passes.  Observability indices after Sun & Hollerbach
(singular values s_1 >= ... >= s_L of the whitened, column-scaled Jacobian,
n poses):

* O1 = (s_1 ... s_L)^(1/L) / sqrt(n)   (D-optimality)
* O2 = s_L / s_1                       (inverse condition number)
* O3 = s_L                             (minimum singular value, E-optimality)
* O4 = s_L^2 / s_1                     (noise amplification index)
* O5 = 1 / sum(1/s_i)                  (A-optimality)

Combinations with singular value below ``1e-8 * s_1`` cannot be identified
by the plan at all; they are reported by name.
"""
from __future__ import annotations

import math

import numpy as np

from ..errormodel import PARAM_NAMES, reading_parameter_jacobian
from ..errors import DataError
from ..kinematics import Hexapod
from .model import FRAME_NAMES, jacobian_batch, measure, strut_geometry
from .cyclerun import near_box_edge, unreachable
from .synth import sample_poses

MEASURE_CHOICES = "xyzabc"


def parse_measure(text: str) -> np.ndarray:
    t = text.strip().lower()
    if not t or any(ch not in MEASURE_CHOICES for ch in t) or len(set(t)) != len(t):
        raise DataError(f"--measure {text!r}: give the measured coordinates as letters of xyzabc, e.g. xyzabc, z, ab")
    return np.array([c in t for c in MEASURE_CHOICES])


def identification_rows(cfg, poses_deg: np.ndarray, keep: np.ndarray, noise_mm: float, noise_deg: float,
                        frame: bool = False) -> np.ndarray:
    """(N, m, P) whitened d(measured coordinates)/d(parameters) at nominal geometry."""
    hx = Hexapod(cfg)
    P = np.asarray(poses_deg, dtype=float)
    X = P.copy()
    X[:, 3:] = np.radians(X[:, 3:])
    G = reading_parameter_jacobian(hx, P)
    _, rp, s, L = strut_geometry(hx.base, hx.plat, X)
    J = jacobian_batch(rp, s / L[..., None], X)
    dX = -np.linalg.solve(J, G)                        # (N,6,42), angles rad
    dy = dX.copy()
    dy[:, 3:] = np.degrees(dy[:, 3:])
    if frame:
        f0 = np.zeros(12)
        F = np.empty((len(P), 6, 12))
        for j in range(12):
            h = 1e-6
            fp = f0.copy()
            fp[j] += h
            fm = f0.copy()
            fm[j] -= h
            F[:, :, j] = (measure(X, fp) - measure(X, fm)) / (2 * h)
        dy = np.concatenate([dy, F], axis=2)
    sig = np.array([noise_mm] * 3 + [noise_deg] * 3)
    dy = dy / sig[None, :, None]
    return dy[:, keep, :]


def column_scale(cfg, n_params: int) -> np.ndarray:
    """Parameters in comparable units: mm, and radians times the platform radius for frame angles."""
    char = max(1.0, float(np.mean(np.linalg.norm(np.asarray(cfg.platform_joints_mm)[:, :2], axis=1))))
    d = np.ones(n_params)
    if n_params > 42:
        d[45:48] = 1.0 / char
        d[51:54] = 1.0 / char
    return d


def indices(Jw: np.ndarray, n_poses: int) -> dict:
    """Condition number and O1..O5 of a whitened, column-scaled identification Jacobian.

    O1..O5 are computed over the identifiable singular values (above ``1e-8 s_1``);
    ``unidentifiable`` counts the rest (the condition number is then infinite).
    """
    P = Jw.shape[1]
    s = np.linalg.svd(Jw, compute_uv=False)
    s = np.r_[s, np.zeros(max(0, P - len(s)))]
    smax = float(s[0])
    tol = smax * 1e-8
    good = s[s > tol]
    L = len(good)
    o = {"parameters": int(P), "rank": int(L), "unidentifiable": int(P - L),
         "singular_value_max": smax, "singular_value_min": float(s[-1])}
    if L == 0:
        return o
    o["condition_number"] = float(smax / s[-1]) if s[-1] > tol else math.inf
    o["condition_number_identifiable"] = float(smax / good[-1])
    o["O1"] = float(np.exp(np.mean(np.log(good))) / math.sqrt(n_poses))
    o["O2"] = float(good[-1] / smax)
    o["O3"] = float(good[-1])
    o["O4"] = float(good[-1] ** 2 / smax)
    o["O5"] = float(1.0 / np.sum(1.0 / good))
    return o


def null_space(Jw: np.ndarray, names: list[str], scale: np.ndarray, top: int = 6) -> list[dict]:
    _, s, Vt = np.linalg.svd(Jw, full_matrices=True)
    s = np.r_[s, np.zeros(Vt.shape[0] - len(s))]
    tol = s[0] * 1e-8
    out = []
    for k in np.where(s <= tol)[0]:
        v = Vt[k] * scale
        v /= np.linalg.norm(v)
        comp = np.argsort(-np.abs(v))[:top]
        out.append({"singular_value": float(s[k]),
                    "combination": [{"name": names[c], "weight": round(float(v[c]), 4)} for c in comp
                                    if abs(v[c]) > 0.05]})
    return out


def plan(cfg, n_poses: int, measure_set: str = "xyzabc", candidates: int = 2000, seed: int = 0,
         noise_mm: float = 0.01, noise_deg: float = 0.001, frame: bool = False, exchange_passes: int = 3) -> dict:
    keep = parse_measure(measure_set)
    if n_poses < 1:
        raise DataError(f"--poses must be positive, got {n_poses}")
    if candidates < n_poses:
        candidates = 4 * n_poses
    rng = np.random.default_rng(seed)
    P = sample_poses(cfg, rng, candidates, shrink=1.0)
    hx = Hexapod(cfg)
    cond_ok = np.array([hx.condition(p) <= cfg.kinematics.max_condition for p in P])
    P = P[cond_ok & ~unreachable(cfg, P) & ~near_box_edge(cfg, P)]     # calib run's moves stay within the box
    rows = identification_rows(cfg, P, keep, noise_mm, noise_deg, frame)     # (M, m, P)
    npar = rows.shape[2]
    scale = column_scale(cfg, npar)
    rows = rows * scale[None, None, :]
    names = list(PARAM_NAMES) + (list(FRAME_NAMES) if frame else [])
    m = rows.shape[1]
    # regularised information matrix: a weak prior keeps log det finite for rank-deficient plans
    eps = 1e-6 * float(np.mean(np.einsum("nij,nij->j", rows, rows))) + 1e-12
    A = eps * np.eye(npar)
    chosen: list[int] = []
    Ainv = np.linalg.inv(A)
    for _ in range(n_poses):
        B = np.einsum("nip,pq->niq", rows, Ainv)
        Mk = np.einsum("niq,njq->nij", B, rows) + np.eye(m)[None]
        gain = np.linalg.slogdet(Mk)[1]
        if chosen:
            gain[chosen] = -np.inf
        k = int(np.argmax(gain))
        chosen.append(k)
        A = A + rows[k].T @ rows[k]
        Ainv = np.linalg.inv(A)
    # exchange passes: replace the least useful pose by the best candidate while log det improves
    logdet = np.linalg.slogdet(A)[1]
    swaps = 0
    for _ in range(exchange_passes):
        improved = False
        for pos in range(len(chosen)):
            k_out = chosen[pos]
            A_wo = A - rows[k_out].T @ rows[k_out]
            Ainv_wo = np.linalg.inv(A_wo)
            B = np.einsum("nip,pq->niq", rows, Ainv_wo)
            Mk = np.einsum("niq,njq->nij", B, rows) + np.eye(m)[None]
            gain = np.linalg.slogdet(Mk)[1]
            gain[[c for c in chosen if c != k_out]] = -np.inf
            k_in = int(np.argmax(gain))
            new_logdet = np.linalg.slogdet(A_wo)[1] + gain[k_in]
            if k_in != k_out and new_logdet > logdet + 1e-9:
                chosen[pos] = k_in
                A = A_wo + rows[k_in].T @ rows[k_in]
                logdet = new_logdet
                swaps += 1
                improved = True
        if not improved:
            break
    Jw = rows[chosen].reshape(-1, npar)
    sel = P[chosen]
    # compare with a random plan of the same size
    rnd = rng.choice(len(P), size=min(n_poses, len(P)), replace=False)
    out = {
        "poses": sel,
        "readings_mm": hx.inverse_batch(sel) - hx.offset,
        "measure": "".join(c for c, k in zip(MEASURE_CHOICES, keep) if k),
        "n_poses": n_poses, "candidates": int(len(P)), "exchange_swaps": swaps,
        "frame_registration": frame,
        "noise": {"position_mm": noise_mm, "orientation_deg": noise_deg},
        "indices": indices(Jw, n_poses),
        "indices_random_plan": indices(rows[rnd].reshape(-1, npar), len(rnd)),
        "unidentifiable": null_space(Jw, names, scale),
    }
    nobs = int(keep.sum()) * n_poses
    if nobs < npar:
        out["warning"] = (f"{nobs} measured coordinates for {npar} parameters: at least "
                          f"{math.ceil(npar / int(keep.sum()))} poses are needed to have a chance")
    return out
