"""Held-out evaluation: re-referencing new sessions, held-out RMS, whole-session shifts."""
from __future__ import annotations

import math

import numpy as np

from ..errors import DataError
from .identify import FitResult, fit
from .measurements import Measurements
from .model import Context, Evaluator, rms_summary


def session_unseen(fit_meas: Measurements, hold: Measurements) -> bool:
    if hold.session is None:
        return False
    known = set(fit_meas.sessions())
    return any(s not in known for s in hold.sessions())


def reference_groups(fit_meas: Measurements | None, hold: Measurements, k: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(rows that re-reference, rows evaluated) per group of held-out rows.

    k = 0: one group, nothing re-referenced.  Held-out sessions not seen in the fit
    data: each such session spends its own first k rows.  Otherwise the first k rows
    of the file re-reference everything.
    """
    allrows = np.arange(hold.n)
    if k <= 0:
        return [(allrows[:0], allrows)]
    known = set(fit_meas.sessions()) if fit_meas is not None else set()
    if hold.session is not None and fit_meas is not None and any(s not in known for s in hold.sessions()):
        groups = []
        for lab in hold.sessions():
            idx = np.where(hold.session == lab)[0]
            groups.append((idx[:k], idx[k:]) if lab not in known else (idx[:0], idx))
        return groups
    return [(allrows[:k], allrows[k:])]


def rereferenced_thetas(cfg, res: FitResult, hold: Measurements, ctx_fit: Context, k: int, how: str = "offsets",
                        fit_meas: Measurements | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """(parameters, rows evaluated) per group of :func:`reference_groups`: the fitted parameters with
    the strut offsets (and with ``offsets+frame`` the frame) re-fitted on the group's first k rows."""
    lay = res.layout
    out = []
    for ref_rows, ev_rows in reference_groups(fit_meas, hold, k):
        theta = res.theta.copy()
        if len(ref_rows):
            cref = Context(cfg, hold.subset(ref_rows), ctx_fit.sigma[0], ctx_fit.sigma[3],
                           fit_sessions=ctx_fit.sessions)
            free = np.zeros(lay.n, dtype=bool)
            free[36:42] = True
            if how == "offsets+frame" and lay.frame is not None:
                free[lay.frame] = True
            theta = fit(cfg, cref, lay, theta_init=theta, free=free, max_iter=40).theta
        out.append((theta, ev_rows))
    return out


def evaluate_holdout(cfg, res: FitResult, hold: Measurements, ctx_fit: Context, k: int, how: str,
                     fit_meas: Measurements | None = None) -> tuple[dict, dict, np.ndarray]:
    """RMS on the held-out rows after re-referencing the strut offsets (and optionally the frame)
    on the first k rows of each new session (see :func:`reference_groups`); k=0: nothing."""
    lay = res.layout
    parts = []
    rows_all = []
    for theta, ev_rows in rereferenced_thetas(cfg, res, hold, ctx_fit, k, how, fit_meas):
        if not len(ev_rows):
            continue
        cte = Context(cfg, hold.subset(ev_rows), ctx_fit.sigma[0], ctx_fit.sigma[3], fit_sessions=ctx_fit.sessions)
        parts.append(Evaluator(cfg, lay, cte).residuals(theta))
        rows_all.append(ev_rows)
    if not parts:
        raise DataError(f"{hold.path}: re-referencing with {k} rows per new session leaves no held-out row to evaluate")
    resid = {key: np.concatenate([p_[key] for p_ in parts]) for key in parts[0]}
    return rms_summary(resid), resid, np.concatenate(rows_all)


def session_shift(cfg, res: FitResult, hold: Measurements, ctx_fit: Context) -> dict:
    """Is the held-out set offset as a whole (another session: re-homing, a moved instrument)?

    Per-strut mean of the held-out strut residual under the fitted model with nothing
    re-referenced, against its standard error (full poses only).
    """
    _, resid, _ = evaluate_holdout(cfg, res, hold, ctx_fit, 0, "offsets")
    s = resid["struts"]
    rows = np.all(np.isfinite(s), axis=1)
    if rows.sum() < 3:
        return {}
    mean = s[rows].mean(axis=0)
    se = s[rows].std(axis=0, ddof=1) / math.sqrt(rows.sum())
    z = np.abs(mean) / np.maximum(se, 1e-12)
    return {"strut_mean_residual_mm": mean.tolist(), "strut_mean_residual_z": z.tolist(),
            "session_shift_evident": bool(np.any(z > 5.0)),
            "session_shift_note": ("the held-out struts are offset as a whole (up to "
                                   f"{float(np.max(np.abs(mean))):.3g} mm, {float(np.max(z)):.0f} standard errors): "
                                   "strut offsets moved between the sessions (re-homing) or the instrument moved; "
                                   "no model fitted to the other session can predict that, re-reference with "
                                   "--rereference-rows") if np.any(z > 5.0) else "no significant shift"}
