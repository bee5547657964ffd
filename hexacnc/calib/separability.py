"""Identifiability of candidate causes from the measured coordinates and poses, and what to measure.

The whitened data Jacobian of the measured coordinates (geometry, frame and
every candidate, at the baseline fit) is the sensitivity matrix.  For each
candidate: the fraction of its signature that the geometric parameters cannot
explain (projection onto the complement of their span), and, among the
candidates, the closest one (largest canonical correlation of the projected
signatures).  Candidates whose projected signatures coincide cannot be told
apart by any fit of this data.
"""
from __future__ import annotations

import numpy as np

from .identify import FitResult
from .model import Context, Evaluator, base_cause, build_layout

#: projected signatures closer than this (smallest canonical correlation) cannot be told apart
INSEPARABLE_COS = 0.98


def signature_analysis(base_fit: FitResult, cfg, ctx: Context, causes, frame0, opts) -> dict:
    """Separability of each candidate from geometry and from each other (whitened data Jacobian)."""
    lay = build_layout(cfg, ctx, list(causes), frame0, opts.prior_joint_mm, opts.prior_offset_mm)
    theta = lay.theta0.copy()
    for j, nm in enumerate(base_fit.layout.names):
        theta[lay.names.index(nm)] = base_fit.theta[j]
    ev = Evaluator(cfg, lay, ctx, base_fit.evaluator.X)
    _, J = ev.evaluate(theta)
    J = J[:base_fit.n_data]
    ng = 42 + (12 if lay.frame is not None else 0)
    U, s, _ = np.linalg.svd(J[:, :ng], full_matrices=False)
    Q = U[:, s > s[0] * 1e-9]
    out: dict = {"separable_fraction": {}, "inseparable_pairs": [], "closest": {}, "_basis": {}}
    for c in causes:
        S = J[:, lay.causes[c]]
        nrm = np.linalg.norm(S, axis=0)
        S = S[:, nrm > 0] / nrm[nrm > 0]
        if S.shape[1] == 0:
            out["separable_fraction"][c] = 0.0
            continue
        P = S - Q @ (Q.T @ S)
        out["separable_fraction"][c] = float(np.linalg.norm(P) / np.linalg.norm(S))
        Up, sp, _ = np.linalg.svd(P, full_matrices=False)
        out["_basis"][c] = Up[:, sp > max(sp[0] * 1e-3, 1e-12)] if sp.size and sp[0] > 1e-12 else None
    names = [c for c in causes if out["_basis"].get(c) is not None]
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            Qa, Qb = out["_basis"][a], out["_basis"][b]
            sv = np.linalg.svd(Qa.T @ Qb, compute_uv=False)
            cosmax = float(sv[0]) if len(sv) else 0.0
            cos_min = float(sv[min(Qa.shape[1], Qb.shape[1]) - 1]) if len(sv) else 0.0
            if base_cause(a) != base_cause(b):
                for x, y in ((a, b), (b, a)):
                    cur = out["closest"].get(x)
                    if cur is None or cosmax > cur["correlation"]:
                        out["closest"][x] = {"name": y, "correlation": cosmax}
            # inseparable: the smaller subspace lies (almost) inside the larger one
            if cos_min > INSEPARABLE_COS:
                out["inseparable_pairs"].append({"a": a, "b": b, "cos_max": cosmax, "cos_min": cos_min,
                                                 "nested": Qa.shape[1] != Qb.shape[1]})
    return out


def measured_letters(meas) -> str:
    m = np.asarray(meas.mask).any(axis=0)
    return "".join(ch for ch, k in zip("xyzabc", m) if k)


def what_to_measure(causes: list[str], measured: str, meas) -> dict:
    """What extra data would tell ``causes`` apart: poses, coordinates, payloads, temperatures."""
    names = sorted({base_cause(c) for c in causes})
    out: dict = {"poses": f"hexacnc calib plan --separate {','.join(names)} --measure {measured or 'xyzabc'} "
                          "--poses 30 (poses where the signatures differ most, beyond the geometry)"}
    if not all(ch in measured for ch in "abc"):
        out["coordinates"] = ("measure the orientation (a, b, c) as well as the position: the rotations carry "
                              "the per-strut pattern that positions alone mix with the geometry")
    if "elastic_sag" in names:
        pl = meas.payload_kg
        varied = pl is not None and float(np.ptp(pl)) > 0
        out["payloads"] = ("repeat poses with a different payload (payload_kg column), e.g. none and the rated "
                           "payload: only the load changes, so the sag is separated from every reading error"
                           + ("" if not varied else " (the payload already varies: add more of the heavy rows)"))
    if "thermal_expansion" in names:
        out["temperatures"] = ("repeat poses at strut temperatures at least 5 K apart (T_strut1..6 columns), "
                               "e.g. cold start and after a warm-up")
    if "session_offset" in names:
        out["sessions"] = "re-home between sessions and label each row's session (session column)"
    if "backlash" in names:
        out["approach"] = "approach each pose from both directions of every strut (alternate the row order)"
    return out
