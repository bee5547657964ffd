"""Human-readable reports (Markdown + PNG) for ``calib fit`` and ``diagnose``."""
from __future__ import annotations

import numpy as np

from . import plots
from .output import ReportDir, write_json


def _fmt(v, unit=""):
    if v is None:
        return "n/a"
    return f"{v:.4g}{unit}"


def _rms_line(r: dict) -> str:
    return (f"position {_fmt(r.get('position_mm'), ' mm')}, orientation {_fmt(r.get('orientation_deg'), ' deg')}, "
            f"strut {_fmt(r.get('strut_mm'), ' mm')}")


def diagnosis_markdown(res: dict, pngs: list[str]) -> str:
    L = ["# Model diagnosis", ""]
    d = res["data"]
    L.append(f"Data: `{d['fit']}`, {d['rows']} poses, {d['observations']} measured coordinates "
             f"({', '.join(d['measured'])}); measurement frame "
             f"{'registered (fitted)' if d['frame_registration'] else 'taken as the base frame'}.")
    nz = res["noise"]
    if nz["known"]:
        L.append(f"Instrument noise: {nz['position_mm']:g} mm, {nz['orientation_deg']:g} deg. "
                 f"Rigid-model chi2/dof = {nz['chi2_red_baseline']:.3g} "
                 f"(noise alone would give up to {nz['chi2_red_noise_limit']:.3g}).")
    else:
        L.append("Instrument noise not given: causes are judged by cross-validation and BIC only; the rigid "
                 f"model's residual is {nz['estimated_scale_baseline']:.3g} x the assumed weighting noise "
                 f"({nz['position_mm']:g} mm).")
    L.append("")
    L.append("## Verdict")
    L.append("")
    if not res["causes"] and not res.get("inseparable_causes"):
        L.append("**none**: no candidate cause explains the residual better than noise and geometry; "
                 "the rigid 42-parameter model is adequate for this data.")
    else:
        L.append(f"**{res['verdict']}** (ordered by contribution).")
        L.append("")
        for c in res["causes"]:
            ev = c["evidence"]
            L.append(f"- **{c['name']}**: {c['model']}. Contribution {ev['contribution_mm']:.4g} mm RMS on the struts; "
                     f"cross-validated residual {ev['cv_gain']:.3g}x smaller with it; BIC change "
                     f"{ev['delta_bic']:.1f}.")
            top = sorted(((k, v) for k, v in c["parameters"].items() if isinstance(v, (int, float))
                          and k in c["parameter_std"]), key=lambda kv: -abs(kv[1]))[:6]
            if c["name"] == "strut_nonlinearity" and "gain1_ppm" in c["parameters"]:
                L.append("  Gain part of the map (scale error per strut, ppm): " + ", ".join(
                    f"{c['parameters'][f'gain{i}_ppm']:.0f}" for i in range(1, 7)))
            L.append("  Parameters: " + ", ".join(
                f"{k} = {v:.4g} ± {c['parameter_std'].get(k, float('nan')):.2g}" for k, v in top)
                + (" ..." if len(c["parameters"]) > 6 else ""))
            L.extend(_cause_extra(c))
        L.extend(_inseparable_lines(res))
    L.append("")
    L.append("## Residuals (RMS)")
    L.append("")
    L.append("| model | fit data | held-out |")
    L.append("|---|---|---|")
    L.append(f"| rigid 42-parameter | {_rms_line(res['baseline']['rms_fit'])} | {_rms_line(res['baseline']['rms_holdout'])} |")
    L.append(f"| extended | {_rms_line(res['extended']['rms_fit'])} | {_rms_line(res['extended']['rms_holdout'])} |")
    h = res.get("holdout")
    if h:
        L.append("")
        L.append(f"Held-out: `{h['path']}`, {h['rows']} poses; first {h['rereference_rows']} spent to re-reference "
                 f"({h['rereferenced']}), evaluated on {h['rows_evaluated']}. "
                 f"Gain (baseline/extended): {_fmt(res['gain']['holdout_rms_ratio'])}.")
        if h.get("session_shift_evident"):
            L.append("")
            L.append("Held-out session: " + h["session_shift_note"] + "; per-strut mean residual (mm): "
                     + ", ".join(f"{v:+.3g}" for v in h["strut_mean_residual_mm"]) + ".")
    if res.get("suspicious_rows"):
        L.append("")
        L.append("Suspicious rows (residual far beyond the others; check them, they were kept in the fit): "
                 + ", ".join(f"line {r['line']} ({r['residual_x_typical']:.0f}x typical)"
                             for r in res["suspicious_rows"][:10]) + ".")
    L.append("")
    L.append("## Candidates")
    L.append("")
    L.append("| cause | separable from geometry | CV gain (first round) | delta BIC | note |")
    L.append("|---|---|---|---|---|")
    for name, c in res["candidates"].items():
        r0 = (c.get("rounds") or [{}])[0]
        note = c.get("reason") or c.get("verdict") or ("selected" if c.get("selected_in_round") else "")
        L.append(f"| {name} | {_fmt(c.get('separable_fraction'))} | {_fmt(r0.get('cv_gain'))} | "
                 f"{_fmt(r0.get('delta_bic'))} | {note} |")
    pairs = [p for p in res.get("inseparable", []) if not p.get("nested")]
    nested = [p for p in res.get("inseparable", []) if p.get("nested")]
    if pairs:
        L.append("")
        L.append("Candidate pairs this data cannot separate: "
                 + "; ".join(f"{p['a']} / {p['b']}" for p in pairs) + ".")
    if nested:
        L.append("")
        L.append("Nested candidates (one model contains the other; the information criterion prefers the "
                 "smaller when it suffices): " + "; ".join(f"{p['a']} / {p['b']}" for p in nested) + ".")
    L.append("")
    L.append("'Separable from geometry': fraction of a candidate's signature that the 42 geometric parameters "
             "(and frame registration) cannot absorb; near 0 means a geometric error looks the same.")
    if pngs:
        L.append("")
        L.append("## Plots")
        L.append("")
        for p in pngs:
            L.append(f"![{p}]({p})")
    return "\n".join(L) + "\n"


def _cause_extra(c: dict) -> list[str]:
    """Own gains in the presence of the others, the per-strut / common choice."""
    ev = c["evidence"]
    out = [f"  In the presence of the other causes: CV residual {_fmt(ev.get('cv_gain_in_presence_of_others'))}x "
           f"smaller with it, BIC {_fmt(ev.get('delta_bic_in_presence_of_others'))}; held-out "
           f"{ev.get('holdout_gain_metric') or ''} RMS {_fmt(ev.get('holdout_gain'))}x smaller with it."]
    v = c.get("variant")
    if v:
        out.append(f"  Form: **{v['chosen'].replace('_', ' ')}** (per strut vs common: CV gain "
                   f"{_fmt(v['cv_gain_per_strut_over_common'])}, BIC change "
                   f"{_fmt(v['delta_bic_per_strut_minus_common'])}"
                   + (f"; held-out RMS chosen {_fmt(v.get('holdout_rms_chosen_form'))}, other "
                      f"{_fmt(v.get('holdout_rms_other_form'))}" if v.get("holdout_rms_other_form") is not None
                      else "") + ").")
    return out


def _inseparable_lines(res: dict) -> list[str]:
    out = []
    for g in res.get("inseparable_causes", []):
        out.append(f"- **not named: {' or '.join(g['causes'])}**: {g['note']}. To separate them:")
        for k, v in g["what_to_measure"].items():
            out.append(f"  - {k}: {v}")
    dr = res.get("dropped_on_retest") or []
    if dr:
        out.append("")
        out.append("Dropped on re-test (no longer earning their place next to the others): "
                   + ", ".join(f"{d['name']} (CV gain {d['cv_gain_in_presence_of_others']:.3g})" for d in dr) + ".")
    tm = res.get("uncertainty", {}).get("tool_tip_map")
    if tm:
        s = tm["sigma_position_mm"]
        out.append("")
        out.append(f"Predicted tool-tip uncertainty after calibration (1 sigma, {tm['points']} grid poses): "
                   f"median {s['median'] * 1000:.3g} um, 95 % {s['p95'] * 1000:.3g} um, max {s['max'] * 1000:.3g} um "
                   "(uncertainty_map.csv / .png).")
    return out


def write_diagnosis_report(rd: ReportDir, diag, cfg) -> None:
    res = diag.result
    pngs = []
    b_fit = diag.baseline.fit.residuals()
    e_fit = diag.extended.fit.residuals()
    panels = [("rigid 42-parameter model, fit data", b_fit), ("extended model, fit data", e_fit)]
    hi = diag.hold_info
    if hi:
        panels += [("rigid model, held-out", hi["baseline_residuals"]), ("extended model, held-out", hi["extended_residuals"])]
    plots.workspace_before_after(rd.path("residuals_workspace.png"), panels,
                                 "Residuals over the workspace, before and after")
    pngs.append("residuals_workspace.png")
    if plots.position_vectors(rd.path("residuals_vectors.png"), panels[:2],
                              "Position residuals (fit data), rigid model and extended model"):
        pngs.append("residuals_vectors.png")
    if plots.struts_vs_reading(rd.path("residuals_struts.png"), diag.ctx.q, b_fit, e_fit,
                               "Strut-length residual against the reading (fit data)"):
        pngs.append("residuals_struts.png")
    fitres = diag.extended.fit
    ev = fitres.evaluator
    base, plat, _, _ = ev.split(fitres.theta)
    for c in res["causes"]:
        name = c.get("model_name", c["name"])
        B = fitres.layout.cause_models[name].build(ev.ctx, ev.X, base, plat)
        dl = np.einsum("nik,k->ni", B, fitres.theta[fitres.layout.causes[name]])
        fn = f"cause_{name}.png"
        plots.cause_plot(rd.path(fn), name, diag.ctx.q, ev.X, dl, c["model"])
        pngs.append(fn)
    tm = res.get("uncertainty", {}).get("tool_tip_map")
    if tm and tm.get("rows"):
        from .uncertainty import plot_map, write_map_csv
        write_map_csv(rd.path("uncertainty_map.csv"), tm)
        plot_map(rd.path("uncertainty_map.png"), tm)
        pngs.append("uncertainty_map.png")
    (rd.path("summary.md")).write_text(diagnosis_markdown(res, pngs), encoding="utf-8")
    write_json(rd.path("diagnosis.json"), res)


def fit_markdown(rep: dict) -> str:
    L = ["# Calibration report", ""]
    L.append(f"Data: `{rep['data']['path']}`, {rep['data']['rows']} poses, {rep['data']['observations']} measured "
             f"coordinates ({', '.join(rep['data']['measured'])}).")
    L.append(f"Model: 42 geometric parameters{' + 12 frame registration' if rep['frame_registration'] else ''}"
             + (f" + causes {', '.join(rep['causes'])}" if rep["causes"] else "") + f"; noise {rep['noise']}.")
    L.append("")
    L.append(f"- nominal model: {_rms_line(rep['rms_nominal'])}")
    L.append(f"- calibrated: {_rms_line(rep['rms_fit'])}")
    if rep.get("holdout"):
        h = rep["holdout"]
        L.append(f"- held-out `{h['path']}` ({h['rows_evaluated']} of {h['rows']} rows, first "
                 f"{h['rereference_rows']} re-referencing the strut offsets): {_rms_line(h['rms'])}")
    L.append(f"- chi2/dof {rep['chi2_red']:.4g} with {rep['dof']:.1f} degrees of freedom; "
             f"{rep['iterations']} iterations, converged: {rep['converged']}")
    L.append("")
    L.append("## Largest parameter changes")
    L.append("")
    L.append("| parameter | calibrated | change | std |")
    L.append("|---|---|---|---|")
    for p in sorted(rep["parameters"], key=lambda p: -abs(p["change"]))[:15]:
        L.append(f"| {p['name']} | {p['value']:.5g} | {p['change']:+.4g} | {p['std']:.3g} |")
    L.append("")
    L.append("## Not identified by this data (held by the priors)")
    L.append("")
    if not rep["unidentifiable"]:
        L.append("Every parameter combination is constrained by the measurements more than by the prior.")
    for d in rep["unidentifiable"]:
        L.append(f"- singular value {d['singular_value']:.3g}: "
                 + " ".join(f"{c['weight']:+.2f}*{c['name']}" for c in d["combination"]))
    L.append("")
    L.append("## Strongest correlations")
    L.append("")
    for c in rep["correlations"]:
        L.append(f"- {c['a']} / {c['b']}: {c['correlation']:+.3f}")
    L.append("")
    L.append("![residuals](residuals_workspace.png)")
    return "\n".join(L) + "\n"
