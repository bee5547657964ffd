"""Model diagnosis: what the rigid model gets wrong, which physical cause explains it, the gain.

1. Baseline: the rigid 42-parameter model (plus the measurement-frame
   registration where the instrument is not in the base frame) refitted; its
   chi^2 against the instrument noise.
2. Candidates (:data:`~hexacnc.calib.model.CAUSES`), each a few-parameter
   physical model fitted jointly with the geometry.  Each candidate's
   signature is projected onto the complement of the geometric Jacobian: what
   geometry can absorb cannot be told apart from it; candidates whose
   projected signatures coincide cannot be told apart from each other.
3. Forward selection: a candidate joins the model when it improves the
   blocked cross-validated residual (contiguous row blocks) by more than
   ``min_cv_gain`` and the Bayesian information criterion by more than
   ``min_delta_bic``, and, where the noise is known, while the current
   model's chi^2 is significantly above the noise.  ``none`` when nothing
   qualifies.
4. The extended model is refitted; baseline and extended are evaluated on
   the held-out set (optionally re-referencing the strut offsets on its first
   k rows).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import DataError
from . import limit_blas_threads
from ..kinematics import Hexapod
from .identify import FitResult, fit, strongest_correlations, unidentifiable_directions
from .measurements import Measurements
from .model import CAUSES, Context, Evaluator, build_layout, initial_frame, rms_summary

#: used for weighting only when the noise is not given
DEFAULT_NOISE_MM = 0.01


@dataclass
class Options:
    noise_mm: float | None = None
    noise_deg: float | None = None
    causes: tuple[str, ...] = CAUSES
    frame: str = "auto"                  #: auto | base | register
    folds: int = 5
    min_cv_gain: float = 0.03            #: relative CV RMS reduction a cause must bring
    min_delta_bic: float = 10.0
    max_causes: int = 3
    rereference_rows: int | None = None  #: None: auto (only for holdout sessions not seen in the fit)
    rereference: str = "offsets"         #: offsets | offsets+frame
    prior_joint_mm: float = 5.0
    prior_offset_mm: float = 50.0


@dataclass
class Model:
    causes: list[str]
    fit: FitResult
    cv_rms: float = math.nan             #: whitened CV residual RMS
    bic: float = math.nan
    nl_degree: int = 3                   #: strut_nonlinearity degree used by this model


@dataclass
class Diagnosis:
    result: dict
    baseline: Model
    extended: Model
    ctx: Context
    holdout_ctx: Context | None
    holdout_rows: np.ndarray | None
    baseline_holdout: dict | None = None
    extended_holdout: dict | None = None
    timings: dict = field(default_factory=dict)
    hold_info: dict | None = None          #: held-out residual arrays for the report


def noise_defaults(cfg, noise_mm, noise_deg) -> tuple[float, float, bool]:
    """Weights (mm, deg) and whether the noise is known."""
    known = noise_mm is not None or noise_deg is not None
    char = max(1.0, float(np.mean(np.linalg.norm(np.asarray(cfg.platform_joints_mm)[:, :2], axis=1))))
    if noise_mm is None and noise_deg is None:
        noise_mm = DEFAULT_NOISE_MM
    if noise_mm is None:
        noise_mm = math.radians(noise_deg) * char
    if noise_deg is None:
        noise_deg = math.degrees(noise_mm / char)
    if noise_mm <= 0 or noise_deg <= 0:
        raise DataError(f"instrument noise must be positive, got {noise_mm} mm, {noise_deg} deg")
    return float(noise_mm), float(noise_deg), known


def use_frame(meas: Measurements, how: str) -> bool:
    if how == "register":
        return True
    if how == "base":
        return False
    if how != "auto":
        raise DataError(f"frame must be auto, base or register, got {how!r}")
    return int(meas.full_pose_rows().sum()) >= 3


def fit_model(cfg, ctx: Context, causes, frame0: np.ndarray | None, opts: Options,
              warm: FitResult | None = None) -> FitResult:
    """Fit geometry (+frame) + causes; warm-started from a smaller model where given."""
    lay = build_layout(cfg, ctx, causes, frame0, opts.prior_joint_mm, opts.prior_offset_mm)
    theta = lay.theta0.copy()
    X0 = None
    if warm is not None:
        for j, nm in enumerate(warm.layout.names):
            if nm in lay.names:
                theta[lay.names.index(nm)] = warm.theta[j]
        X0 = warm.evaluator.X
    elif frame0 is not None:   # frames first: the nominal geometry seen through an unknown frame
        free = np.zeros(lay.n, dtype=bool)
        free[lay.frame] = True
        r0 = fit(cfg, ctx, lay, free=free, max_iter=30)
        theta, X0 = r0.theta, r0.evaluator.X
    res = fit(cfg, ctx, lay, theta_init=theta, X_init=X0)
    bad = ~res.evaluator.converged
    if bad.any():
        lines = ctx.meas.lines[bad] if ctx.meas.lines is not None else np.where(bad)[0] + 1
        raise DataError(f"{ctx.meas.path}: the readings of {int(bad.sum())} row(s) (line(s) "
                        f"{', '.join(str(int(x)) for x in lines[:10])}{' ...' if bad.sum() > 10 else ''}) give no "
                        f"pose of this machine even after fitting; are the readings in mm and does the config "
                        f"({cfg.path}) describe this machine?")
    return res


def check_readings(cfg, meas: Measurements, margin: float = 0.05) -> None:
    """Readings must put every strut inside its configured stroke (with a margin): else the units
    or the machine description are wrong, and a fit would only hide it."""
    L = meas.q + np.asarray(cfg.strut_offset_mm)[None]
    lo = np.asarray(cfg.min_length_mm)
    hi = np.asarray(cfg.max_length_mm)
    tol = margin * (hi - lo)
    bad = (L < lo - tol) | (L > hi + tol)
    if bad.any():
        k, i = (int(v) for v in np.argwhere(bad)[0])
        line = int(meas.lines[k]) if meas.lines is not None else k + 1
        raise DataError(f"{meas.path}: line {line}, q{i + 1} = {meas.q[k, i]:g} mm puts strut {i + 1} at "
                        f"{L[k, i]:.1f} mm, outside its stroke [{lo[i]:g}, {hi[i]:g}] mm of {cfg.path} "
                        f"({int(bad.any(axis=1).sum())} row(s) affected): wrong units (see --map scale) or "
                        f"the wrong machine description")


NL_DEGREES = (3, 5, 7)


def _set_nl(ctx: Context, model: "Model") -> None:
    """Context options of strut_nonlinearity for the layouts built from now on."""
    ctx.nl_degree = getattr(model, "nl_degree", ctx.nl_degree)
    ctx.nl_linear = "strut_scale" not in model.causes


def _fit_candidate(cfg, ctx: Context, chosen: list[str], c: str, frame0, opts: "Options", warm: FitResult,
                   known: bool, current_degree: int) -> "Model":
    """Fit chosen + [c]; strut_nonlinearity picks its polynomial degree by BIC.

    ``ctx``'s strut_nonlinearity options are restored before returning; the fitted
    layout keeps the ones it was built with.
    """
    keep_deg, keep_lin = ctx.nl_degree, ctx.nl_linear
    try:
        ctx.nl_linear = "strut_scale" not in chosen   # with a gain term unless strut_scale came first
        ctx.nl_degree = current_degree
        if c != "strut_nonlinearity":
            r = fit_model(cfg, ctx, chosen + [c], frame0, opts, warm=warm)
            r.noise_known = known
            m = Model(chosen + [c], r, bic=bic(r, known))
            m.nl_degree = current_degree
            return m
        best = None
        for deg in NL_DEGREES:
            ctx.nl_degree = deg
            r = fit_model(cfg, ctx, chosen + [c], frame0, opts, warm=warm)
            r.noise_known = known
            m = Model(chosen + [c], r, bic=bic(r, known))
            m.nl_degree = deg
            if best is None or m.bic < best.bic - 1e-9:
                best = m
        return best
    finally:
        ctx.nl_degree, ctx.nl_linear = keep_deg, keep_lin


def _folds(n: int, k: int) -> list[np.ndarray]:
    k = max(2, min(k, n // 4))
    edges = np.linspace(0, n, k + 1).astype(int)
    return [np.arange(edges[i], edges[i + 1]) for i in range(k)]


def cv_score(cfg, meas: Measurements, ctx: Context, model_fit: FitResult, causes, frame0, opts: Options) -> float:
    """Blocked K-fold CV: whitened RMS of the residuals of each block predicted from the others."""
    num, den = 0.0, 0
    for test in _folds(meas.n, opts.folds):
        train = np.setdiff1d(np.arange(meas.n), test)
        ctx_tr = Context(cfg, meas.subset(train), ctx.sigma[0], ctx.sigma[3], fit_sessions=ctx.sessions)
        ctx_te = Context(cfg, meas.subset(test), ctx.sigma[0], ctx.sigma[3], fit_sessions=ctx.sessions)
        lay = model_fit.layout
        # warm start from the full-data fit
        r = fit(cfg, ctx_tr, lay, theta_init=model_fit.theta, X_init=model_fit.evaluator.X[train], max_iter=20,
                rel_tol=1e-6)
        ev = Evaluator(cfg, lay, ctx_te, model_fit.evaluator.X[test])
        rv, _ = ev.evaluate(r.theta)
        nd = int(ctx_te.mask.sum())
        num += float(rv[:nd] @ rv[:nd])
        den += nd
    return math.sqrt(num / max(den, 1))


def bic(res: FitResult, noise_known: bool) -> float:
    n = res.n_data
    if noise_known:
        return res.cost + res.p_eff * math.log(n)
    return n * math.log(max(res.cost, 1e-300) / n) + res.p_eff * math.log(n)


def signature_analysis(base_fit: FitResult, cfg, ctx: Context, causes, frame0, opts: Options) -> dict:
    """Separability of each candidate from geometry and from each other (whitened data Jacobian)."""
    lay = build_layout(cfg, ctx, list(causes), frame0, opts.prior_joint_mm, opts.prior_offset_mm)
    theta = lay.theta0.copy()
    for j, nm in enumerate(base_fit.layout.names):
        theta[lay.names.index(nm)] = base_fit.theta[j]
    ev = Evaluator(cfg, lay, ctx, base_fit.evaluator.X)
    _, J = ev.evaluate(theta)
    J = J[:base_fit.n_data]
    ng = 42 + (12 if lay.frame is not None else 0)
    G = J[:, :ng]
    U, s, _ = np.linalg.svd(G, full_matrices=False)
    Q = U[:, s > s[0] * 1e-9]
    out: dict = {"separable_fraction": {}, "inseparable_pairs": [], "_basis": {}}
    for c in causes:
        S = J[:, lay.causes[c]]
        nrm = np.linalg.norm(S, axis=0)
        S = S[:, nrm > 0] / nrm[nrm > 0]
        if S.shape[1] == 0:
            out["separable_fraction"][c] = 0.0
            continue
        P = S - Q @ (Q.T @ S)
        frac = float(np.linalg.norm(P) / np.linalg.norm(S))
        out["separable_fraction"][c] = frac
        Up, sp, _ = np.linalg.svd(P, full_matrices=False)
        out["_basis"][c] = Up[:, sp > max(sp[0] * 1e-3, 1e-12)] if sp.size and sp[0] > 1e-12 else None
    names = [c for c in causes if out["_basis"].get(c) is not None]
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            Qa, Qb = out["_basis"][a], out["_basis"][b]
            cosmax = float(np.linalg.svd(Qa.T @ Qb, compute_uv=False)[0])
            # inseparable: the smaller subspace lies (almost) inside the larger one
            sv = np.linalg.svd(Qa.T @ Qb, compute_uv=False)
            cos_min = float(sv[min(Qa.shape[1], Qb.shape[1]) - 1]) if len(sv) else 0.0
            if cos_min > 0.98:
                out["inseparable_pairs"].append({"a": a, "b": b, "cos_max": cosmax, "cos_min": cos_min,
                                                 "nested": Qa.shape[1] != Qb.shape[1]})
    return out


def _session_unseen(fit_meas: Measurements, hold: Measurements) -> bool:
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


def diagnose(cfg, fit_meas: Measurements, holdout: Measurements | None = None, opts: Options | None = None) -> Diagnosis:
    opts = opts or Options()
    limit_blas_threads(1)
    t0 = time.perf_counter()
    noise_mm, noise_deg, known = noise_defaults(cfg, opts.noise_mm, opts.noise_deg)
    check_readings(cfg, fit_meas)
    if holdout is not None:
        check_readings(cfg, holdout)
    ctx = Context(cfg, fit_meas, noise_mm, noise_deg)
    frame0 = initial_frame(cfg, fit_meas) if use_frame(fit_meas, opts.frame) else None
    n_geom = 42 + (12 if frame0 is not None else 0)
    if fit_meas.n_observations < n_geom:
        raise DataError(f"{fit_meas.path}: {fit_meas.n_observations} measured coordinates in {fit_meas.n} rows "
                        f"for {n_geom} parameters; measure at least {n_geom} coordinates, ideally several times "
                        f"that (`hexacnc calib plan` picks the poses)")
    base = fit_model(cfg, ctx, [], frame0, opts)
    base.noise_known = known
    baseline = Model([], base, bic=bic(base, known))
    baseline.cv_rms = cv_score(cfg, fit_meas, ctx, base, [], frame0, opts)
    timings = {"baseline_s": time.perf_counter() - t0}
    # candidates
    reasons = {c: ctx.applicable(c) for c in opts.causes}
    cands = [c for c in opts.causes if reasons[c] is None]
    sig = signature_analysis(base, cfg, ctx, cands, frame0, opts)
    chi2_limit = 1.0 + 3.0 * math.sqrt(2.0 / base.dof)
    table: dict[str, dict] = {c: {"applicable": reasons[c] is None, "reason": reasons[c],
                                  "separable_fraction": sig["separable_fraction"].get(c)} for c in opts.causes}
    current = baseline
    chosen: list[str] = []
    while len(chosen) < opts.max_causes:
        if known and current.fit.chi2_red <= chi2_limit:
            break
        best = None
        for c in cands:
            if c in chosen:
                continue
            if c == "strut_scale" and "strut_nonlinearity" in chosen and ctx.nl_linear:
                table[c]["verdict"] = "nested in strut_nonlinearity (a gain error is the P1 term of its map)"
                continue
            if (sig["separable_fraction"].get(c) or 0.0) < 1e-4:
                table[c]["verdict"] = "absorbed by geometry: cannot be told apart from a geometric error"
                continue
            m = _fit_candidate(cfg, ctx, chosen, c, frame0, opts, current.fit, known, current.nl_degree)
            m.cv_rms = cv_score(cfg, fit_meas, ctx, m.fit, chosen + [c], frame0, opts)
            gain = current.cv_rms / m.cv_rms
            dbic = m.bic - current.bic
            entry = {"cv_gain": gain, "delta_bic": dbic, "chi2_red": m.fit.chi2_red,
                     "n_parameters": len(m.fit.layout.cause_models[c].names)}
            if c == "strut_nonlinearity":
                entry["degree"] = m.nl_degree
            table[c].setdefault("rounds", []).append(entry)
            ok = gain >= 1.0 + opts.min_cv_gain and dbic <= -opts.min_delta_bic
            # among the candidates that pass cross-validation, the information criterion decides
            # (a nested, larger model never wins over the smaller one that explains the data)
            if ok and (best is None or m.bic < best[1].bic):
                best = (c, m, entry)
        if best is None:
            break
        chosen.append(best[0])
        table[best[0]]["selected_in_round"] = len(chosen)
        current = best[1]
        _set_nl(ctx, current)
    timings["selection_s"] = time.perf_counter() - t0 - timings["baseline_s"]
    extended = current
    # holdout
    hold_info = None
    b_hold = e_hold = None
    rows = None
    hold_ctx = None
    k = 0
    if holdout is not None:
        if opts.rereference_rows is None:
            k = min(6, holdout.n // 3) if _session_unseen(fit_meas, holdout) else 0
        else:
            k = int(opts.rereference_rows)
        if k < 0 or k >= holdout.n:
            raise DataError(f"{holdout.path}: --rereference-rows {k} leaves no held-out row to evaluate "
                            f"({holdout.n} rows)")
        b_hold, b_res, rows = evaluate_holdout(cfg, baseline.fit, holdout, ctx, k, opts.rereference, fit_meas)
        e_hold, e_res, _ = evaluate_holdout(cfg, extended.fit, holdout, ctx, k, opts.rereference, fit_meas)
        hold_ctx = Context(cfg, holdout, noise_mm, noise_deg)
        groups = reference_groups(fit_meas, holdout, k)
        hold_info = {"path": holdout.path, "rows": holdout.n, "rereference_rows": k,
                     "rereferenced_rows_total": int(sum(len(g[0]) for g in groups)),
                     "rereference_scope": ("first k rows of each held-out session not in the fit data"
                                           if len(groups) > 1 else "first k rows of the file"),
                     "rereferenced": (opts.rereference if k else "nothing"), "rows_evaluated": int(len(rows)),
                     "baseline_residuals": b_res, "extended_residuals": e_res}
        hold_info.update(session_shift(cfg, extended.fit, holdout, ctx))
    nul = {"position_mm": None, "orientation_deg": None, "strut_mm": None}
    b_fit_rms = baseline.fit.rms()
    e_fit_rms = extended.fit.rms()
    causes_out = []
    for c in chosen:
        cm = extended.fit.layout.cause_models[c]
        sl = extended.fit.layout.causes[c]
        C = extended.fit.covariance()
        idx = np.where(extended.fit.free)[0]
        pos = [int(np.where(idx == j)[0][0]) for j in range(sl.start, sl.stop)]
        sd = np.sqrt(np.maximum(np.diag(C)[pos], 0.0))
        contrib = _contribution_mm(cfg, extended.fit, c)
        params = {nm: float(v) for nm, v in zip(cm.names, extended.fit.theta[sl])}
        definition: dict = {}
        if c == "strut_nonlinearity":
            qh = extended.fit.evaluator.ctx.q_half
            for i in range(6):
                if f"p1_strut{i + 1}_mm" in params:   # the gain part of the map, as a scale error
                    params[f"gain{i + 1}_ppm"] = params[f"p1_strut{i + 1}_mm"] / qh[i] * 1e6
            definition = {"degree": extended.nl_degree,
                          "t": "(q - stroke_center_mm) / stroke_half_mm, Legendre polynomials P_k(t)",
                          "stroke_center_mm": extended.fit.evaluator.ctx.q_center.tolist(),
                          "stroke_half_mm": qh.tolist()}
        if c == "elastic_sag" and params["compliance_mm_per_kN"] > 0:
            params["equivalent_stiffness_N_per_mm"] = 1000.0 / params["compliance_mm_per_kN"]
        entry = table[c]["rounds"][table[c]["selected_in_round"] - 1]
        causes_out.append({
            "name": c, "parameters": params,
            "parameter_std": {nm: float(v) for nm, v in zip(cm.names, sd)},
            "units": cm.units, "model": cm.description, "definition": definition,
            "evidence": {"cv_gain": entry["cv_gain"], "delta_bic": entry["delta_bic"],
                         "chi2_red_before": None,
                         "chi2_red_with": entry["chi2_red"] if known else None,
                         "separable_fraction": sig["separable_fraction"].get(c),
                         "contribution_mm": contrib,
                         "cannot_be_told_apart_from": [p["b"] if p["a"] == c else p["a"]
                                                       for p in sig["inseparable_pairs"]
                                                       if c in (p["a"], p["b"]) and not p["nested"]]},
        })
    # chi2 before each cause
    prev_chi = baseline.fit.chi2_red
    for co in causes_out:
        co["evidence"]["chi2_red_before"] = prev_chi if known else None
        prev_chi = co["evidence"]["chi2_red_with"] if known else None
    causes_out.sort(key=lambda d: -d["evidence"]["contribution_mm"])
    result = {
        "baseline": {"rms_fit": b_fit_rms, "rms_holdout": b_hold if b_hold is not None else dict(nul),
                     "chi2_red": baseline.fit.chi2_red if known else None, "dof": baseline.fit.dof,
                     "parameters": baseline.fit.layout.n},
        "causes": causes_out,
        "extended": {"rms_fit": e_fit_rms, "rms_holdout": e_hold if e_hold is not None else dict(nul),
                     "chi2_red": extended.fit.chi2_red if known else None, "dof": extended.fit.dof,
                     "parameters": extended.fit.layout.n},
        "gain": {"holdout_rms_ratio": _ratio(b_hold, e_hold)},
        "verdict": ", ".join(c["name"] for c in causes_out) if causes_out else "none",
        "noise": {"position_mm": noise_mm, "orientation_deg": noise_deg, "known": known,
                  "chi2_red_baseline": baseline.fit.chi2_red if known else None,
                  "chi2_red_extended": extended.fit.chi2_red if known else None,
                  "chi2_red_noise_limit": chi2_limit if known else None,
                  "estimated_scale_baseline": math.sqrt(baseline.fit.chi2_red),
                  "estimated_scale_extended": math.sqrt(extended.fit.chi2_red)},
        "data": {"fit": fit_meas.path, "rows": fit_meas.n, "observations": fit_meas.n_observations,
                 "measured": fit_meas.measured_names(), "frame_registration": frame0 is not None,
                 "sessions": fit_meas.sessions()},
        "holdout": None if hold_info is None else {k_: v for k_, v in hold_info.items() if not k_.endswith("residuals")},
        "candidates": table,
        "inseparable": sig["inseparable_pairs"],
        "cv": {"folds": len(_folds(fit_meas.n, opts.folds)), "baseline_whitened_rms": baseline.cv_rms,
               "extended_whitened_rms": extended.cv_rms},
        "unidentifiable": unidentifiable_directions(extended.fit, max_dirs=8),
        "suspicious_rows": suspicious_rows(extended.fit, fit_meas),
        "strongest_correlations": strongest_correlations(extended.fit, 5),
    }
    if "gain" in result and b_hold is not None:
        result["gain"].update({k2: _ratio1(b_hold.get(k2), e_hold.get(k2)) for k2 in ("position_mm", "orientation_deg", "strut_mm")})
    timings["total_s"] = time.perf_counter() - t0
    result["timing_s"] = timings
    return Diagnosis(result, baseline, extended, ctx, hold_ctx, rows, b_hold, e_hold, timings, hold_info)


def suspicious_rows(res: FitResult, meas: Measurements, limit: float = 5.0) -> list[dict]:
    """Rows whose residual is far outside the rest (robust scale): a lost target, a typo, a bump.

    Reported, never dropped silently: per row the RMS of the whitened residual over its
    measured coordinates, against ``limit`` times the median-absolute-deviation scale.
    """
    r = res.residuals()["coords"] / res.evaluator.ctx.sigma[None]
    m = np.isfinite(r)
    per_row = np.sqrt(np.nansum(r ** 2, axis=1) / np.maximum(m.sum(axis=1), 1))
    scale = 1.4826 * float(np.median(per_row)) + 1e-12
    out = []
    for k in np.argsort(-per_row):
        if per_row[k] <= limit * scale:
            break
        out.append({"line": int(meas.lines[k]) if meas.lines is not None else int(k) + 2,
                    "residual_x_typical": float(per_row[k] / scale)})
        if len(out) >= 20:
            break
    return out


def _ratio1(a, b):
    if a is None or b is None or b <= 0:
        return None
    return a / b


def _ratio(b: dict | None, e: dict | None):
    """baseline/extended holdout RMS: strut_mm where available, else position, else orientation."""
    if b is None or e is None:
        return None
    for k in ("strut_mm", "position_mm", "orientation_deg"):
        if b.get(k) is not None and e.get(k) is not None and e[k] > 0:
            return b[k] / e[k]
    return None


def _contribution_mm(cfg, res: FitResult, cause: str) -> float:
    """RMS (mm) of the cause's strut-length contribution with each strut's mean removed."""
    ev = res.evaluator
    base, plat, _, _ = ev.split(res.theta)
    B = res.layout.cause_models[cause].build(ev.ctx, ev.X, base, plat)
    dl = np.einsum("nik,k->ni", B, res.theta[res.layout.causes[cause]])
    dl = dl - dl.mean(axis=0)
    return float(np.sqrt(np.mean(dl ** 2)))


def nominal_rms(cfg, meas: Measurements, frame: bool) -> dict:
    """RMS of the nominal model (no fit; with a frame-only registration fit where ``frame``)."""
    ctx = Context(cfg, meas, DEFAULT_NOISE_MM, math.degrees(DEFAULT_NOISE_MM / 200.0))
    if not frame:
        lay = build_layout(cfg, ctx, [], None)
        return rms_summary(Evaluator(cfg, lay, ctx).residuals(lay.theta0))
    f0 = initial_frame(cfg, meas)
    lay = build_layout(cfg, ctx, [], f0)
    free = np.zeros(lay.n, dtype=bool)
    free[lay.frame] = True
    r = fit(cfg, ctx, lay, free=free)
    return r.rms()


def hexapod_from_fit(cfg, res: FitResult) -> Hexapod:
    return Hexapod.from_parameters(cfg, res.theta[:42])
