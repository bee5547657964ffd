"""``hexacnc calib``: calibration test plan, identification of the 42 parameters, synthetic sets."""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import sys

import numpy as np

from ..errors import DataError

HELP = ("calibration: plan measurement poses, run them on the machine, identify the 42 geometric parameters, "
        "apply and verify a calibrated config")


def configure(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="calib_cmd", metavar="SUBCOMMAND")
    sub.required = True
    pl = sub.add_parser("plan", help="pick reachable poses that maximise observability",
                        description="pick reachable poses that maximise observability (greedy D-optimal + exchange)")
    pl.add_argument("--config", required=True)
    pl.add_argument("--poses", type=int, required=True, help="number of poses to measure")
    pl.add_argument("--measure", default="xyzabc", help="measured coordinates: letters of xyzabc (e.g. xyzabc, z, ab)")
    pl.add_argument("--candidates", type=int, default=2000, help="random reachable candidates (default 2000)")
    pl.add_argument("--seed", type=int, default=0)
    pl.add_argument("--noise-mm", type=float, default=0.01)
    pl.add_argument("--noise-deg", type=float, default=0.001)
    pl.add_argument("--frame", action="store_true", help="the instrument frame will be registered (12 more parameters)")
    pl.add_argument("--out", help="write the poses as CSV (x,y,z,a,b,c,q1..q6)")
    pl.add_argument("--json", help="write the plan report as JSON (also printed)")
    pl.add_argument("--separate", metavar="CAUSE[,CAUSE]",
                    help="plan the extra poses (and payloads, temperatures, approach directions) that separate "
                         "these causes from the geometry and from each other (Ds-optimal); the CSV gains "
                         "payload_kg, T_strut_C and approach columns")
    pl.add_argument("--payload-kg", type=float, default=None,
                    help="with --separate elastic_sag: the payload to alternate with none (default: carrier mass)")
    pl.set_defaults(_calib=_plan)

    ft = sub.add_parser("fit", help="identify the 42 parameters from measurements, write a calibrated config",
                        description="identify the 42 geometric parameters (plus the measurement frame) from "
                                    "measurements; write a calibrated machine description and a report")
    ft.add_argument("--config", required=True)
    ft.add_argument("--data", required=True, help="measurements (CSV, docs/measurements.md)")
    ft.add_argument("--map", help="column mapping (TOML) for a foreign CSV layout")
    ft.add_argument("--out", required=True, help="calibrated machine description (TOML)")
    ft.add_argument("--holdout", help="held-out measurements (CSV, same mapping): RMS of the calibrated model on them")
    ft.add_argument("--rereference-rows", type=int, default=0,
                    help="spend the first K held-out rows re-referencing the strut offsets (another session)")
    ft.add_argument("--report", help="report directory (report.md, report.json, residuals_workspace.png)")
    ft.add_argument("--json", help="write the fit report as JSON")
    ft.add_argument("--noise-mm", type=float, default=None, help="instrument noise of x,y,z (mm)")
    ft.add_argument("--noise-deg", type=float, default=None, help="instrument noise of a,b,c (deg)")
    ft.add_argument("--frame", choices=("auto", "base", "register"), default="auto")
    ft.add_argument("--causes", default="", help="fit these cause models jointly (comma list); the TOML holds "
                                                   "the geometry and the causes the cycle applies ([calibration] "
                                                   "strut_scale, strut_nonlinearity_mm; elastic_sag as stiffness; "
                                                   "thermal_expansion as [thermal] expansion_per_K); others are "
                                                   "reported only")
    ft.add_argument("--out-calibration", help="also write the [calibration] (and other changed) sections as a "
                                              "TOML fragment (atomic)")
    ft.add_argument("--prior-mm", type=float, default=5.0, help="prior sigma of joint positions (mm)")
    ft.add_argument("--prior-offset-mm", type=float, default=50.0, help="prior sigma of strut offsets (mm)")
    ft.set_defaults(_calib=_fit)

    sy = sub.add_parser("synth", help="write a seeded synthetic measurement set with a hidden effect",
                        description="write a seeded synthetic fit + holdout measurement set (random manufacturing "
                                    "errors, instrument noise, one hidden effect or none)")
    sy.add_argument("--config", required=True)
    sy.add_argument("--seed", type=int, default=0)
    sy.add_argument("--effect", default="none")
    sy.add_argument("--poses", type=int, default=120)
    sy.add_argument("--holdout-poses", type=int, default=60)
    sy.add_argument("--measure", default="xyzabc")
    sy.add_argument("--noise-mm", type=float, default=0.005)
    sy.add_argument("--noise-deg", type=float, default=0.0005)
    sy.add_argument("--registration", action="store_true", help="instrument frame not the base frame")
    sy.add_argument("--out", required=True, help="fit CSV")
    sy.add_argument("--holdout", required=True, help="holdout CSV")
    sy.add_argument("--truth", help="JSON with the hidden effect and its parameters")
    sy.set_defaults(_calib=_synth)

    from . import calibcycle
    calibcycle.configure(sub)


def main(args: argparse.Namespace) -> int:
    from ..calib import limit_blas_threads
    limit_blas_threads(1)
    return args._calib(args)


def _plan(args) -> int:
    from ..calib.output import to_jsonable, write_json
    from ..calib.measurements import atomic_write_text
    from ..calib.plan import plan
    from ..config import load_config
    cfg = load_config(args.config)
    header, cells = "x,y,z,a,b,c,q1,q2,q3,q4,q5,q6", None
    if args.separate:               # the poses carry the condition each is measured in
        from ..calib.plan_separate import CONDITION_COLUMNS, condition_cells, run_separate
        res = run_separate(cfg, args)
        header += "," + CONDITION_COLUMNS
        cells = [condition_cells(c) for c in res["conditions"]]
    else:
        res = plan(cfg, args.poses, args.measure, args.candidates, args.seed, args.noise_mm, args.noise_deg,
                   args.frame)
    if args.out:
        lines = [header]
        for k, (p, q) in enumerate(zip(res["poses"], res["readings_mm"])):
            lines.append(",".join(f"{v:.6f}" for v in list(p) + list(q)) + ("," + cells[k] if cells else ""))
        atomic_write_text(args.out, "\n".join(lines) + "\n")
    rep = {k: v for k, v in res.items() if k not in ("poses", "readings_mm")}
    if args.out:
        rep["poses_csv"] = args.out
    if args.json:
        write_json(args.json, rep)
    print(json.dumps(to_jsonable(rep), indent=2))
    return 0


def _is_run_file(args) -> bool:
    from pathlib import Path
    return Path(str(args.data) + ".json").exists() and args.frame == "auto" and not args.map


def _fit(args) -> int:
    from ..calib.diagnose import Options, check_readings, fit_model, nominal_rms, noise_defaults, use_frame
    from ..calib.identify import parameter_table, strongest_correlations, unidentifiable_directions
    from ..calib.measurements import atomic_write_text, load_measurements
    from ..calib.model import Context, initial_frame
    from ..calib.output import ReportDir, calibrated_config_text, to_jsonable, write_json
    from ..calib import plots
    from ..calib.report import fit_markdown
    from ..config import load_config
    from .diagnose import parse_causes
    cfg = load_config(args.config)
    if _is_run_file(args):
        from .calibcycle import fit_from_run       # a calib run file: base frame, its target
        return fit_from_run(args, cfg)
    meas = load_measurements(args.data, args.map, min_rows=3)
    causes = list(parse_causes(args.causes)) if args.causes.strip() else []
    noise_mm, noise_deg, known = noise_defaults(cfg, args.noise_mm, args.noise_deg)
    check_readings(cfg, meas)
    ctx = Context(cfg, meas, noise_mm, noise_deg)
    for c in causes:
        why = ctx.applicable(c)
        if why:
            raise DataError(f"--causes {c}: cannot be fitted to {meas.path}: {why}")
    frame = use_frame(meas, args.frame)
    frame0 = initial_frame(cfg, meas) if frame else None
    opts = Options(prior_joint_mm=args.prior_mm, prior_offset_mm=args.prior_offset_mm)
    from ..calib.model import build_layout
    n_par = build_layout(cfg, ctx, causes, frame0).n
    if meas.n_observations < n_par:
        raise DataError(f"{meas.path}: {meas.n_observations} measured coordinates in {meas.n} rows for {n_par} "
                        f"parameters; measure more poses (at least {n_par} coordinates, ideally several times "
                        f"that; `hexacnc calib plan` picks them)")
    hold = None
    if args.holdout:
        hold = load_measurements(args.holdout, args.map, min_rows=1)
        check_readings(cfg, hold)
        if not 0 <= args.rereference_rows < hold.n:
            raise DataError(f"{hold.path}: --rereference-rows {args.rereference_rows} leaves no held-out row "
                            f"to evaluate ({hold.n} rows)")
    res = fit_model(cfg, ctx, causes, frame0, opts)
    res.noise_known = known
    rms = res.rms()
    nom = nominal_rms(cfg, meas, frame)
    rep = {
        "data": {"path": meas.path, "rows": meas.n, "observations": meas.n_observations,
                 "measured": meas.measured_names()},
        "config": cfg.path, "frame_registration": frame, "causes": causes,
        "noise": {"position_mm": noise_mm, "orientation_deg": noise_deg, "known": known},
        "rms_nominal": nom, "rms_fit": rms,
        "chi2": res.cost, "dof": res.dof, "chi2_red": res.chi2_red,
        "iterations": res.iterations, "converged": res.converged,
        "parameters": parameter_table(res),
        "correlations": strongest_correlations(res, 10),
        "unidentifiable": unidentifiable_directions(res),
    }
    if frame:
        rep["frame"] = {nm: float(v) for nm, v in zip(res.layout.names[42:54], res.theta[42:54])}
    if hold is not None:
        from ..calib.diagnose import evaluate_holdout
        hrms, _, hrows = evaluate_holdout(cfg, res, hold, ctx, args.rereference_rows, "offsets", meas)
        rep["holdout"] = {"path": hold.path, "rows": hold.n, "rereference_rows": args.rereference_rows,
                          "rows_evaluated": int(len(hrows)), "rms": hrms}
    header = (f"calibrated by hexacnc calib fit on {_dt.datetime.now(_dt.timezone.utc):%Y-%m-%d %H:%M} UTC\n"
              f"from {meas.path} ({meas.n} poses) starting from {cfg.path}\n"
              f"fit RMS: position {rms['position_mm']} mm, orientation {rms['orientation_deg']} deg, "
              f"strut {rms['strut_mm']} mm")
    if causes:
        header += "\nfitted jointly with " + ", ".join(causes)
    from ..calib.output import fit_config_texts
    src = f"hexacnc calib fit --config {args.config} --data {args.data}" + (f" --map {args.map}" if args.map else "") \
        + (f" --causes {','.join(causes)}" if causes else "") + f" ({meas.n} rows)"
    written = fit_config_texts(cfg, res, causes, src, header.splitlines())
    text = written["config"]
    rep["config_out"] = {"config": args.out, "calibration": args.out_calibration, "applied": written["applied"],
                         "not_applied": written["not_applied"], "source": written["source"],
                         "date": written["date"]}
    rd = ReportDir(args.report) if args.report else None
    try:
        if rd is not None:
            write_json(rd.path("report.json"), rep)
            rd.path("report.md").write_text(fit_markdown(to_jsonable(rep)), encoding="utf-8")
            plots.workspace_before_after(rd.path("residuals_workspace.png"), [("calibrated model", res.residuals())],
                                         "Residuals of the calibrated model over the workspace")
        if args.json:
            write_json(args.json, rep)
        if args.out_calibration:
            atomic_write_text(args.out_calibration, written["fragment"])
        atomic_write_text(args.out, text)
    except BaseException:
        if rd is not None:
            rd.abort()
        raise
    if rd is not None:
        rd.commit()
    print(json.dumps(to_jsonable({"out": args.out, "rms_nominal": nom, "rms_fit": rms,
                                  "rms_holdout": rep["holdout"]["rms"] if hold is not None else None,
                                  "chi2_red": res.chi2_red,
                                  "unidentifiable_directions": len(rep["unidentifiable"]),
                                  "iterations": res.iterations}), indent=2))
    return 0


def _synth(args) -> int:
    from ..calib.model import CAUSES
    from ..calib.output import write_json
    from ..calib.synth import generate, write_set
    from ..config import load_config
    if args.effect != "none" and args.effect not in CAUSES:
        raise DataError(f"--effect {args.effect!r}: not none or one of {', '.join(CAUSES)}")
    cfg = load_config(args.config)
    s = generate(cfg, args.seed, args.effect, args.poses, args.holdout_poses, args.measure, args.noise_mm,
                 args.noise_deg, registration=args.registration)
    write_set(s, args.out, args.holdout)
    truth = {"effect": s.effect, "parameters": s.effect_params, "magnitude_mm": s.magnitude_mm,
             "noise_mm": s.noise_mm, "noise_deg": s.noise_deg,
             "geometry": np.asarray(s.theta_true).tolist()}
    if args.truth:
        write_json(args.truth, truth)
    print(json.dumps({"fit": args.out, "holdout": args.holdout, "effect": s.effect,
                      "magnitude_mm": s.magnitude_mm}))
    sys.stdout.flush()
    return 0
