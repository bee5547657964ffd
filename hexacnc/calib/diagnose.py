"""Model diagnosis: what the rigid model gets wrong, which physical causes explain it, the gain.

1. Baseline: the rigid 42-parameter model (plus the measurement-frame
   registration where the instrument is not in the base frame) refitted; its
   chi^2 against the instrument noise.
2. Identifiability (:mod:`.separability`): each candidate's signature in the
   sensitivity matrix of the measured coordinates and poses, projected onto the
   complement of the geometric Jacobian; the fraction no geometric parameter
   explains and the closest other candidate.
3. Selection (:mod:`.select`): forward search on the blocked cross-validated
   residual and the BIC, per-strut forms against the common ones, re-test of
   every named cause in the presence of the others, swaps against every other
   candidate.  Causes the data cannot tell apart are reported as inseparable
   (with what to measure to separate them), not named.
4. The extended model and the model without each cause are evaluated on the
   held-out set (optionally re-referencing the strut offsets on its first k
   rows): each cause's own held-out gain.  Every fitted parameter carries its
   standard error; :mod:`.uncertainty` maps the predicted tool-tip uncertainty.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import DataError
from ..kinematics import Hexapod
from . import limit_blas_threads
from .fitting import (DEFAULT_NOISE_MM, NL_DEGREES, Model, Options, bic, check_readings, cv_score,
                      fit_candidate, fit_model, folds, noise_defaults, set_nl, use_frame)
from .holdout import (evaluate_holdout, reference_groups, rereferenced_thetas, session_shift,
                      session_unseen)
from .identify import FitResult, fit, parameter_table, strongest_correlations, unidentifiable_directions
from .measurements import Measurements
from .model import VARIANTS, Context, Evaluator, base_cause, build_layout, initial_frame, rms_summary
from .select import Selection, select
from .separability import measured_letters, signature_analysis, what_to_measure
from .uncertainty import tool_tip_map

#: re-exported for the callers of the former single module (bench calib, calib commands, tests)
__all__ = ["DEFAULT_NOISE_MM", "NL_DEGREES", "Diagnosis", "Model", "Options", "bic", "check_readings", "cv_score",
           "diagnose", "evaluate_holdout", "fit_candidate", "fit_model", "hexapod_from_fit", "noise_defaults",
           "nominal_rms", "reference_groups", "rereferenced_thetas", "session_shift", "session_unseen", "set_nl",
           "signature_analysis", "suspicious_rows", "use_frame"]


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
    reasons = {c: ctx.applicable(c) for c in opts.causes}
    cands = [c for c in opts.causes if reasons[c] is None]
    sig_models = cands + [VARIANTS[c] for c in cands if c in VARIANTS and opts.variants]
    sig = signature_analysis(base, cfg, ctx, sig_models, frame0, opts)
    chi2_limit = 1.0 + 3.0 * math.sqrt(2.0 / base.dof)
    table: dict[str, dict] = {c: {"applicable": reasons[c] is None, "reason": reasons[c],
                                  "separable_fraction": sig["separable_fraction"].get(c),
                                  "closest": sig["closest"].get(c)} for c in opts.causes}
    selection = select(cfg, fit_meas, ctx, frame0, opts, known, baseline, cands, table, sig, chi2_limit)
    extended = selection.model
    set_nl(ctx, extended)
    timings["selection_s"] = time.perf_counter() - t0 - timings["baseline_s"]
    hold = _holdout_part(cfg, fit_meas, holdout, ctx, opts, baseline, extended, selection, noise_mm, noise_deg)
    causes_out, inseparable = _cause_entries(cfg, fit_meas, extended, selection, sig, known, baseline,
                                             hold, opts)
    result = _assemble(cfg, fit_meas, opts, baseline, extended, selection, sig, causes_out, inseparable, hold,
                       known, noise_mm, noise_deg, chi2_limit, frame0)
    timings["total_s"] = time.perf_counter() - t0
    result["timing_s"] = timings
    return Diagnosis(result, baseline, extended, ctx, hold.get("ctx"), hold.get("rows"), hold.get("b"),
                     hold.get("e"), timings, hold.get("info"))


def _holdout_part(cfg, fit_meas, holdout, ctx, opts, baseline, extended, selection, noise_mm, noise_deg) -> dict:
    """Held-out RMS of the baseline, the extended model and the extended model without each cause."""
    if holdout is None:
        return {}
    if opts.rereference_rows is None:
        k = min(6, holdout.n // 3) if session_unseen(fit_meas, holdout) else 0
    else:
        k = int(opts.rereference_rows)
    if k < 0 or k >= holdout.n:
        raise DataError(f"{holdout.path}: --rereference-rows {k} leaves no held-out row to evaluate "
                        f"({holdout.n} rows)")
    b_hold, b_res, rows = evaluate_holdout(cfg, baseline.fit, holdout, ctx, k, opts.rereference, fit_meas)
    e_hold, e_res, _ = evaluate_holdout(cfg, extended.fit, holdout, ctx, k, opts.rereference, fit_meas)
    without = {}
    for c, m in selection.without.items():
        set_nl(ctx, m)
        without[c] = evaluate_holdout(cfg, m.fit, holdout, ctx, k, opts.rereference, fit_meas)[0]
    variants = {}
    for b, ev in selection.variants.items():   # the other form of each variant, on the held-out set
        other = b if ev["chosen"] == "per_strut" else VARIANTS[b]
        key = [other if base_cause(x) == b else x for x in selection.chosen]
        m = next((mm for kk, mm in selection.fits.items() if list(kk[0]) == key), None)
        if m is not None:
            set_nl(ctx, m)
            variants[b] = evaluate_holdout(cfg, m.fit, holdout, ctx, k, opts.rereference, fit_meas)[0]
    set_nl(ctx, extended)
    groups = reference_groups(fit_meas, holdout, k)
    info = {"path": holdout.path, "rows": holdout.n, "rereference_rows": k,
            "rereferenced_rows_total": int(sum(len(g[0]) for g in groups)),
            "rereference_scope": ("first k rows of each held-out session not in the fit data"
                                  if len(groups) > 1 else "first k rows of the file"),
            "rereferenced": (opts.rereference if k else "nothing"), "rows_evaluated": int(len(rows)),
            "baseline_residuals": b_res, "extended_residuals": e_res}
    info.update(session_shift(cfg, extended.fit, holdout, ctx))
    return {"b": b_hold, "e": e_hold, "rows": rows, "info": info, "without": without, "variants": variants,
            "ctx": Context(cfg, holdout, noise_mm, noise_deg)}


def _cause_params(cfg, extended: Model, c: str) -> tuple[dict, dict, dict]:
    res = extended.fit
    cm = res.layout.cause_models[c]
    sl = res.layout.causes[c]
    C = res.covariance()
    idx = np.where(res.free)[0]
    pos = [int(np.where(idx == j)[0][0]) for j in range(sl.start, sl.stop)]
    sd = np.sqrt(np.maximum(np.diag(C)[pos], 0.0))
    params = {nm: float(v) for nm, v in zip(cm.names, res.theta[sl])}
    std = {nm: float(v) for nm, v in zip(cm.names, sd)}
    definition: dict = {}
    if c == "strut_nonlinearity":
        qh = res.evaluator.ctx.q_half
        for i in range(6):
            if f"p1_strut{i + 1}_mm" in params:   # the gain part of the map, as a scale error
                params[f"gain{i + 1}_ppm"] = params[f"p1_strut{i + 1}_mm"] / qh[i] * 1e6
        definition = {"degree": extended.nl_degree,
                      "t": "(q - stroke_center_mm) / stroke_half_mm, Legendre polynomials P_k(t)",
                      "stroke_center_mm": res.evaluator.ctx.q_center.tolist(), "stroke_half_mm": qh.tolist()}
    if c == "elastic_sag" and params["compliance_mm_per_kN"] > 0:
        params["equivalent_stiffness_N_per_mm"] = 1000.0 / params["compliance_mm_per_kN"]
    if c == "elastic_sag_per_strut":
        for i in range(6):
            v = params[f"compliance{i + 1}_mm_per_kN"]
            if v > 0:
                params[f"equivalent_stiffness{i + 1}_N_per_mm"] = 1000.0 / v
    return params, std, definition


def _cause_entries(cfg, fit_meas, extended, selection: Selection, sig, known, baseline, hold, opts):
    """Named causes (with evidence) and the groups of causes the data cannot tell apart."""
    table = selection.table
    measured = measured_letters(fit_meas)
    out, inseparable = [], []
    e_key = _hold_key(hold.get("e"))
    for c in selection.chosen:
        b = base_cause(c)
        params, std, definition = _cause_params(cfg, extended, c)
        rnd = table[b].get("selected_entry") or {"cv_gain": None, "delta_bic": None}
        if c != b and "per_strut" in rnd:
            rnd = rnd["per_strut"]
        wo = selection.without[c]
        if rnd.get("cv_gain") is None:   # joined through a swap: its gain over the model without it
            rnd = {"cv_gain": wo.cv_rms / extended.cv_rms, "delta_bic": extended.bic - wo.bic}
        swaps = selection.swaps.get(c, [])
        close_swaps = [a["name"] for a in swaps if a["delta_bic"] < opts.min_swap_delta_bic]
        sig_pairs = [p["b"] if p["a"] == c else p["a"] for p in sig["inseparable_pairs"]
                     if c in (p["a"], p["b"]) and not p["nested"]]
        sig_pairs = [base_cause(x) for x in sig_pairs if base_cause(x) != b and table.get(base_cause(x), {})
                     .get("applicable")]
        alike = sorted(set(close_swaps) | set(sig_pairs))
        hg = None
        if e_key is not None and hold["without"].get(c) is not None:
            w = hold["without"][c].get(e_key)
            hg = w / hold["e"][e_key] if w is not None and hold["e"][e_key] else None
        evidence = {"cv_gain": rnd["cv_gain"], "delta_bic": rnd["delta_bic"],
                    "cv_gain_in_presence_of_others": wo.cv_rms / extended.cv_rms,
                    "delta_bic_in_presence_of_others": extended.bic - wo.bic,
                    "holdout_gain": hg, "holdout_gain_metric": e_key,
                    "chi2_red_without": wo.fit.chi2_red if known else None,
                    "chi2_red_with": extended.fit.chi2_red if known else None,
                    "separable_fraction": sig["separable_fraction"].get(c),
                    "closest_candidate": sig["closest"].get(c),
                    "swap_delta_bic": {a["name"]: a["delta_bic"] for a in swaps},
                    "contribution_mm": _contribution_mm(cfg, extended.fit, c),
                    "cannot_be_told_apart_from": alike}
        entry = {"name": b, "form": "per_strut" if c != b else "common", "model_name": c,
                 "parameters": params, "parameter_std": std, "units": extended.fit.layout.cause_models[c].units,
                 "model": extended.fit.layout.cause_models[c].description, "definition": definition,
                 "evidence": evidence}
        if b in selection.variants:
            entry["variant"] = selection.variants[b]
            if b in hold.get("variants", {}) and e_key is not None:
                other = hold["variants"][b].get(e_key)
                entry["variant"]["holdout_rms_other_form"] = other
                entry["variant"]["holdout_rms_chosen_form"] = hold["e"][e_key]
        if alike:
            group = [b] + alike
            inseparable.append({"causes": group, "fitted_as": c, "evidence": {
                "swap_delta_bic": {a: evidence["swap_delta_bic"].get(a) for a in alike},
                "signature": [p for p in sig["inseparable_pairs"] if c in (p["a"], p["b"])]},
                "note": f"the data explain {b} and {' / '.join(alike)} equally well: not named; the model keeps "
                        f"{c} as a stand-in for the held-out prediction",
                "what_to_measure": what_to_measure(group, measured, fit_meas)})
            entry["inseparable"] = True
        out.append(entry)
    out.sort(key=lambda d: -d["evidence"]["contribution_mm"])
    return out, inseparable


def _hold_key(h: dict | None) -> str | None:
    if h is None:
        return None
    for k in ("strut_mm", "position_mm", "orientation_deg"):
        if h.get(k) is not None:
            return k
    return None


def verdict_text(causes_out: list[dict], inseparable: list[dict]) -> str:
    named = [c["name"] + (" (per strut)" if c["form"] == "per_strut" else "") for c in causes_out
             if not c.get("inseparable")]
    parts = [", ".join(named)] if named else []
    for g in inseparable:
        parts.append("inseparable: " + " or ".join(g["causes"]))
    return "; ".join(parts) if parts else "none"


def _assemble(cfg, fit_meas, opts, baseline, extended, selection, sig, causes_out, inseparable, hold, known,
              noise_mm, noise_deg, chi2_limit, frame0) -> dict:
    nul = {"position_mm": None, "orientation_deg": None, "strut_mm": None}
    b_hold, e_hold = hold.get("b"), hold.get("e")
    named = [c for c in causes_out if not c.get("inseparable")]
    result = {
        "baseline": {"rms_fit": baseline.fit.rms(), "rms_holdout": b_hold if b_hold is not None else dict(nul),
                     "chi2_red": baseline.fit.chi2_red if known else None, "dof": baseline.fit.dof,
                     "parameters": baseline.fit.layout.n},
        "causes": named,
        "inseparable_causes": inseparable,
        "fitted_causes": [c["model_name"] for c in causes_out],
        "extended": {"rms_fit": extended.fit.rms(), "rms_holdout": e_hold if e_hold is not None else dict(nul),
                     "chi2_red": extended.fit.chi2_red if known else None, "dof": extended.fit.dof,
                     "parameters": extended.fit.layout.n},
        "gain": {"holdout_rms_ratio": _ratio(b_hold, e_hold)},
        "verdict": verdict_text(causes_out, inseparable),
        "dropped_on_retest": selection.dropped,
        "noise": {"position_mm": noise_mm, "orientation_deg": noise_deg, "known": known,
                  "chi2_red_baseline": baseline.fit.chi2_red if known else None,
                  "chi2_red_extended": extended.fit.chi2_red if known else None,
                  "chi2_red_noise_limit": chi2_limit if known else None,
                  "estimated_scale_baseline": math.sqrt(baseline.fit.chi2_red),
                  "estimated_scale_extended": math.sqrt(extended.fit.chi2_red)},
        "data": {"fit": fit_meas.path, "rows": fit_meas.n, "observations": fit_meas.n_observations,
                 "measured": fit_meas.measured_names(), "frame_registration": frame0 is not None,
                 "sessions": fit_meas.sessions()},
        "holdout": None if not hold else {k_: v for k_, v in hold["info"].items() if not k_.endswith("residuals")},
        "candidates": selection.table,
        "identifiability": {c: {"separable_fraction": sig["separable_fraction"].get(c),
                                "closest": sig["closest"].get(c)} for c in sig["separable_fraction"]},
        "inseparable": sig["inseparable_pairs"],
        "cv": {"folds": len(folds(fit_meas.n, opts.folds)), "baseline_whitened_rms": baseline.cv_rms,
               "extended_whitened_rms": extended.cv_rms},
        "parameters": parameter_table(extended.fit),
        "uncertainty": {"parameters": "every fitted parameter with its standard error: see 'parameters' "
                                      "(std from the noise estimate and the Jacobian)",
                        "tool_tip_map": tool_tip_map(cfg, extended.fit)},
        "unidentifiable": unidentifiable_directions(extended.fit, max_dirs=8),
        "suspicious_rows": suspicious_rows(extended.fit, fit_meas),
        "strongest_correlations": strongest_correlations(extended.fit, 5),
    }
    if b_hold is not None:
        result["gain"].update({k2: _ratio1(b_hold.get(k2), e_hold.get(k2))
                               for k2 in ("position_mm", "orientation_deg", "strut_mm")})
    return result


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
