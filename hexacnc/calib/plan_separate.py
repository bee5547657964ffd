"""Poses (and payloads, temperatures, approach directions) that separate named causes.

``hexacnc calib plan --separate CAUSE[,CAUSE]``: the candidates are reachable,
well-conditioned poses, each under the conditions the causes respond to
(elastic sag: no payload / the given payload; thermal expansion: two strut
temperatures; backlash: approached extending / retracting).  The whitened
sensitivity of the measured coordinates to the geometry (+ frame) and to the
causes' parameters is computed at the nominal machine; a greedy selection with
exchange passes maximises the information on the cause parameters left after
the geometry is marginalised out (Ds-optimality: log det of the Schur
complement), which is what separates them from the geometry and from each other.
"""
from __future__ import annotations

import numpy as np

from ..errors import DataError
from ..kinematics import Hexapod
from .measurements import Measurements
from .model import CAUSES, T_REF_C, VARIANTS, Context, cause_model, jacobian_batch, strut_geometry
from .plan import column_scale, identification_rows, parse_measure
from .cyclerun import near_box_edge, unreachable
from .synth import sample_poses

KNOWN = CAUSES + tuple(VARIANTS.values())


def parse_separate(text: str) -> list[str]:
    names = [c.strip() for c in text.split(",") if c.strip()]
    bad = [c for c in names if c not in KNOWN]
    if not names or bad:
        raise DataError(f"--separate {text!r}: give causes from {', '.join(KNOWN)} (comma list)"
                        + (f"; unknown: {', '.join(bad)}" if bad else ""))
    return names


def _conditions(causes: list[str], payload_kg: float, dT: float) -> list[dict]:
    """Each candidate pose is offered under these conditions."""
    conds = [{"payload_kg": 0.0, "T_C": T_REF_C, "approach": 1.0}]
    if any(c.startswith("elastic_sag") for c in causes):
        conds += [dict(c, payload_kg=payload_kg) for c in conds]
    if any(c.startswith("thermal_expansion") for c in causes):
        conds += [dict(c, T_C=T_REF_C + dT) for c in conds]
    if "backlash" in causes:
        conds += [dict(c, approach=-1.0) for c in conds]
    return conds


def cause_rows(cfg, P: np.ndarray, causes: list[str], cond: dict, keep: np.ndarray, noise_mm: float,
               noise_deg: float) -> np.ndarray:
    """(N, m, k) whitened d(measured coordinates)/d(cause parameters) at the nominal machine, the scale
    that gives the cause columns unit mean sensitivity, and each cause's number of columns."""
    hx = Hexapod(cfg)
    X = P.copy()
    X[:, 3:] = np.radians(X[:, 3:])
    n = len(P)
    q = hx.inverse_batch(P) - hx.offset[None]
    m = Measurements("<plan>", q, np.zeros_like(q))
    m.payload_kg = np.full(n, cond["payload_kg"])
    m.T_strut = np.full((n, 6), cond["T_C"])
    m.session = np.array(["s1"] * (n // 2) + ["s2"] * (n - n // 2), dtype=object)
    ctx = Context(cfg, m, noise_mm, noise_deg)
    cols = []
    for c in causes:
        B = cause_model(c, ctx).build(ctx, X, hx.base, hx.plat)
        if c == "backlash":
            B = B * cond["approach"]
        cols.append(B)
    G = -np.concatenate(cols, axis=2)
    _, rp, s, L = strut_geometry(hx.base, hx.plat, X)
    J = jacobian_batch(rp, s / L[..., None], X)
    dX = -np.linalg.solve(J, G)
    dX[:, 3:] = np.degrees(dX[:, 3:])
    sig = np.array([noise_mm] * 3 + [noise_deg] * 3)
    dy = dX / sig[None, :, None]
    dy = dy[:, keep, :]
    return dy, np.sqrt(np.einsum("nij,nij->j", dy, dy) / n), [B.shape[2] for B in cols]


def _gain(rows: np.ndarray, Ainv: np.ndarray) -> np.ndarray:
    B = np.einsum("nip,pq->niq", rows, Ainv)
    Mk = np.einsum("niq,njq->nij", B, rows) + np.eye(rows.shape[1])[None]
    return np.linalg.slogdet(Mk)[1]


def _ds_gain(rows: np.ndarray, A: np.ndarray, ng: int) -> np.ndarray:
    """Increase of log det of the cause block's Schur complement when adding each candidate."""
    return _gain(rows, np.linalg.inv(A)) - _gain(rows[:, :, :ng], np.linalg.inv(A[:ng, :ng]))


def separation_report(Jw: np.ndarray, ng: int, spans: dict) -> dict:
    """Per cause: fraction of its signature outside the geometry, closest other cause (canonical
    correlation), and the RMS standard deviation of its parameters after marginalising the geometry and
    the other causes (in the plan's column units: smaller is better separated)."""
    U, s, _ = np.linalg.svd(Jw[:, :ng], full_matrices=False)
    Q = U[:, s > s[0] * 1e-9]
    bases, out = {}, {}
    for c, sl in spans.items():
        S = Jw[:, sl]
        S = S / np.maximum(np.linalg.norm(S, axis=0), 1e-300)
        Pj = S - Q @ (Q.T @ S)
        Up, sp, _ = np.linalg.svd(Pj, full_matrices=False)
        bases[c] = Up[:, sp > max(sp[0] * 1e-3, 1e-12)] if sp.size and sp[0] > 1e-12 else None
        out[c] = {"separable_fraction": float(np.linalg.norm(Pj) / max(np.linalg.norm(S), 1e-300))}
    A = Jw.T @ Jw + 1e-9 * np.eye(Jw.shape[1])
    S = A[ng:, ng:] - A[ng:, :ng] @ np.linalg.solve(A[:ng, :ng], A[:ng, ng:])
    sd = np.sqrt(np.maximum(np.diag(np.linalg.pinv(S)), 0.0))
    for c, sl in spans.items():
        out[c]["parameter_std_rms"] = float(np.sqrt(np.mean(sd[sl.start - ng:sl.stop - ng] ** 2)))
    for a in spans:
        for b in spans:
            if a != b and bases[a] is not None and bases[b] is not None:
                cs = float(np.linalg.svd(bases[a].T @ bases[b], compute_uv=False)[0])
                if cs > out[a].get("closest_correlation", -1.0):
                    out[a]["closest"], out[a]["closest_correlation"] = b, cs
    return out


def plan_separate(cfg, causes: list[str], n_poses: int, measure_set: str = "xyzabc", candidates: int = 1000,
                  seed: int = 0, noise_mm: float = 0.01, noise_deg: float = 0.001, frame: bool = False,
                  payload_kg: float | None = None, delta_T_K: float = 10.0, exchange_passes: int = 2) -> dict:
    keep = parse_measure(measure_set)
    if n_poses < 1:
        raise DataError(f"--poses must be positive, got {n_poses}")
    if payload_kg is None:
        payload_kg = max(float(cfg.mass_kg), 5.0)
    rng = np.random.default_rng(seed)
    hx = Hexapod(cfg)
    P = sample_poses(cfg, rng, max(candidates, 2 * n_poses), shrink=1.0)
    ok = np.array([hx.condition(p) <= cfg.kinematics.max_condition for p in P])
    P = P[ok & ~unreachable(cfg, P) & ~near_box_edge(cfg, P)]
    geo = identification_rows(cfg, P, keep, noise_mm, noise_deg, frame)
    geo = geo * column_scale(cfg, geo.shape[2])[None, None, :]
    ng = geo.shape[2]
    conds = _conditions(causes, payload_kg, delta_T_K)
    crs = []
    for cond in conds:
        cr, _, sizes = cause_rows(cfg, P, causes, cond, keep, noise_mm, noise_deg)
        crs.append(cr)
    # per cause column: unit RMS sensitivity over every candidate and condition (a column that is zero
    # under one condition, e.g. thermal growth at the reference temperature, keeps the others' scale)
    scale = np.sqrt(np.mean([np.einsum("nij,nij->j", cr, cr) / len(P) for cr in crs], axis=0))
    scale[scale <= 0] = 1.0
    parts = [np.concatenate([geo, cr / scale], axis=2) for cr in crs]
    rows = np.concatenate(parts)                       # (C*M, m, ng + k)
    which = np.repeat(np.arange(len(conds)), len(P))
    pose_idx = np.tile(np.arange(len(P)), len(conds))
    npar = rows.shape[2]
    A = (1e-6 * float(np.mean(np.einsum("nij,nij->j", rows, rows))) + 1e-12) * np.eye(npar)
    chosen: list[int] = []
    for _ in range(n_poses):   # greedy D-optimal on geometry and causes, then Ds exchanges
        g = _gain(rows, np.linalg.inv(A))
        g[chosen] = -np.inf
        k = int(np.argmax(g))
        chosen.append(k)
        A = A + rows[k].T @ rows[k]
    for _ in range(exchange_passes):
        for pos in range(len(chosen)):
            A_wo = A - rows[chosen[pos]].T @ rows[chosen[pos]]
            g = _ds_gain(rows, A_wo, ng)
            g[[c for c in chosen if c != chosen[pos]]] = -np.inf
            k_in = int(np.argmax(g))
            if k_in != chosen[pos] and g[k_in] > _ds_gain(rows[[chosen[pos]]], A_wo, ng)[0] + 1e-9:
                chosen[pos] = k_in
            A = A_wo + rows[chosen[pos]].T @ rows[chosen[pos]]
    spans, start = {}, ng
    for c, k in zip(causes, sizes):
        spans[c] = slice(start, start + k)
        start += k
    rnd = rng.choice(len(rows), size=n_poses, replace=False)
    sel = P[pose_idx[chosen]]
    return {"poses": sel, "readings_mm": hx.inverse_batch(sel) - hx.offset,
            "conditions": [conds[which[k]] for k in chosen], "separate": causes,
            "measure": "".join(c for c, k in zip("xyzabc", keep) if k), "n_poses": n_poses,
            "candidates": int(len(rows)), "payload_kg": payload_kg, "delta_T_K": delta_T_K,
            "separation_planned": separation_report(rows[chosen].reshape(-1, npar), ng, spans),
            "separation_random_plan": separation_report(rows[rnd].reshape(-1, npar), ng, spans),
            "criterion": "Ds-optimal: log det of the causes' information after marginalising the geometry"}


#: the CSV columns a separation plan adds after x..c, q1..q6 (the condition each pose is measured in)
CONDITION_COLUMNS = "payload_kg,T_strut_C,approach"


def condition_cells(c: dict) -> str:
    """The :data:`CONDITION_COLUMNS` cells of one pose's condition."""
    return f"{c['payload_kg']:g},{c['T_C']:g},{'extending' if c['approach'] > 0 else 'retracting'}"


def run_separate(cfg, args) -> dict:
    """``hexacnc calib plan --separate``: the plan for the causes of ``args.separate`` (checked)."""
    causes = parse_separate(args.separate)
    if args.payload_kg is not None and not args.payload_kg > 0:
        raise DataError(f"--payload-kg must be positive, got {args.payload_kg}")
    return plan_separate(cfg, causes, args.poses, args.measure, min(args.candidates, 1000), args.seed,
                        args.noise_mm, args.noise_deg, args.frame, args.payload_kg)
