"""``hexacnc diagnose``: what the rigid model gets wrong, the named cause, the gain on held-out data."""
from __future__ import annotations

import argparse
import sys

from ..errors import DataError

HELP = "find what the machine model gets wrong from measurements, name the cause, extend the model, measure the gain"


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, help="machine description (TOML)")
    p.add_argument("--data", required=True, help="measurements to fit (CSV, docs/measurements.md)")
    p.add_argument("--holdout", help="held-out measurements (CSV), never fitted")
    p.add_argument("--map", help="column mapping (TOML) for a foreign CSV layout; applies to --data and --holdout")
    p.add_argument("--holdout-map", help="column mapping for --holdout if it differs")
    p.add_argument("--noise-mm", type=float, help="instrument noise of x, y, z (1 sigma, mm)")
    p.add_argument("--noise-deg", type=float, help="instrument noise of a, b, c (1 sigma, deg)")
    p.add_argument("--json", required=True, help="output JSON (written atomically)")
    p.add_argument("--report", help="directory for PNG plots and summary.md")
    p.add_argument("--causes", default="all",
                   help="comma-separated candidates (default all: elastic_sag, thermal_expansion, strut_scale, "
                        "strut_nonlinearity, backlash, session_offset, joint_offset); elastic_sag and thermal_expansion "
                        "are also tried per strut")
    p.add_argument("--frame", choices=("auto", "base", "register"), default="auto",
                   help="measurement frame: register it (12 parameters: instrument frame and tracked target) "
                        "or take the base frame; auto: register when full poses are measured")
    p.add_argument("--rereference-rows", type=int, default=None,
                   help="spend the first K held-out rows re-referencing the strut offsets (another session); "
                        "default: 0, or 6 when the held-out sessions are not in the fit data")
    p.add_argument("--rereference", choices=("offsets", "offsets+frame"), default="offsets",
                   help="what the first K held-out rows re-reference")
    p.add_argument("--folds", type=int, default=5, help="blocked cross-validation folds (default 5)")
    p.add_argument("--max-causes", type=int, default=4, help="at most this many causes (default 4)")
    p.add_argument("--prior-mm", type=float, default=5.0, help="prior sigma of joint positions (mm)")
    p.add_argument("--out-config", help="write the extended model as a machine description (TOML, atomic): "
                                        "fitted geometry plus the selected causes the cycle applies "
                                        "([calibration] strut_scale / strut_nonlinearity_mm, ...)")
    p.add_argument("--out-calibration", help="write only the [calibration] (and other changed) sections as a "
                                             "TOML fragment (atomic); they belong to the geometry fitted with them")


def parse_causes(text: str) -> tuple[str, ...]:
    from ..calib.model import CAUSES
    if text.strip() == "all":
        return CAUSES
    out = tuple(c.strip() for c in text.split(",") if c.strip())
    bad = [c for c in out if c not in CAUSES]
    if bad:
        raise DataError(f"--causes: unknown cause(s) {', '.join(bad)}; known: {', '.join(CAUSES)}")
    return out


def main(args: argparse.Namespace) -> int:
    from ..calib.diagnose import Options, diagnose
    from ..calib.measurements import load_measurements
    from ..calib.output import ReportDir, write_json
    from ..calib.report import write_diagnosis_report
    from ..config import load_config

    for nm in ("noise_mm", "noise_deg"):
        v = getattr(args, nm)
        if v is not None and not v > 0:
            raise DataError(f"--{nm.replace('_', '-')} must be positive, got {v}")
    if args.folds < 2:
        raise DataError(f"--folds must be at least 2, got {args.folds}")
    cfg = load_config(args.config)
    meas = load_measurements(args.data, args.map, min_rows=8)
    hold = None
    if args.holdout:
        hold = load_measurements(args.holdout, args.holdout_map or args.map, min_rows=1)
    opts = Options(noise_mm=args.noise_mm, noise_deg=args.noise_deg, causes=parse_causes(args.causes),
                   frame=args.frame, folds=args.folds, max_causes=args.max_causes,
                   rereference_rows=args.rereference_rows, rereference=args.rereference,
                   prior_joint_mm=args.prior_mm)
    diag = diagnose(cfg, meas, hold, opts)
    res = diag.result
    written = None
    if args.out_config or args.out_calibration:
        from ..calib.output import extended_config_texts
        written = extended_config_texts(cfg, diag, " ".join(["hexacnc diagnose"] + _argv_words(args)))
        res["config_out"] = {"config": args.out_config, "calibration": args.out_calibration,
                             "applied": written["applied"], "not_applied": written["not_applied"],
                             "source": written["source"], "date": written["date"]}
    rd = ReportDir(args.report) if args.report else None
    try:
        if rd is not None:
            write_diagnosis_report(rd, diag, cfg)
        if written is not None:
            from ..csvio import write_text_atomic
            if args.out_config:
                write_text_atomic(args.out_config, written["config"])
            if args.out_calibration:
                write_text_atomic(args.out_calibration, written["fragment"])
        write_json(args.json, res)
    except BaseException:
        if rd is not None:
            rd.abort()
        raise
    files = rd.commit() if rd is not None else []
    b, e = res["baseline"], res["extended"]
    print(f"verdict: {res['verdict']}")
    for g in res.get("inseparable_causes", []):
        print(f"  not named: {' or '.join(g['causes'])} (this data cannot tell them apart); to separate them: "
              f"{g['what_to_measure']['poses']}")
    for key, r in (("baseline (rigid 42)", b), ("extended", e)):
        print(f"  {key:20s} fit {_r(r['rms_fit'])}   holdout {_r(r['rms_holdout'])}")
    if res.get("holdout"):
        h = res["holdout"]
        print(f"  holdout: first {h['rereference_rows']} of {h['rows']} rows re-referenced ({h['rereferenced']}); "
              f"gain {res['gain']['holdout_rms_ratio']}")
    if written is not None:
        print(f"  written: {', '.join(p_ for p_ in (args.out_config, args.out_calibration) if p_)} "
              f"(applied in the cycle: {', '.join(written['applied']) or 'geometry only'}"
              + (f"; not applicable: {', '.join(n['name'] for n in written['not_applied'])}"
                 if written["not_applied"] else "") + ")")
    print(f"  json: {args.json}" + (f"; report: {args.report} ({len(files)} files)" if files else ""))
    sys.stdout.flush()
    return 0


def _argv_words(args) -> list[str]:
    """The inputs that define the fit, for the provenance text."""
    out = [f"--config {args.config}", f"--data {args.data}"]
    if args.map:
        out.append(f"--map {args.map}")
    if args.causes != "all":
        out.append(f"--causes {args.causes}")
    return out


def _r(r: dict) -> str:
    def f(v):
        return "n/a" if v is None else f"{v:.4g}"
    return f"pos {f(r['position_mm'])} mm, ori {f(r['orientation_deg'])} deg, strut {f(r['strut_mm'])} mm"
