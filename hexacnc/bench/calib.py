"""``hexacnc bench calib``: identification speed, diagnosis speed, Cramér–Rao check, Jugglebot held-out figures."""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

HELP = "calibration benchmarks: 42-parameter fit time, diagnose time, errors vs Cramér–Rao bound, Jugglebot"

_REPO = Path(__file__).resolve().parent.parent.parent


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=None, help="machine for the synthetic parts (default: embedded default)")
    p.add_argument("--trials", type=int, default=20, help="Monte Carlo trials for the Cramér–Rao check")
    p.add_argument("--jugglebot", default=str(_REPO.parent / "shared" / "data" / "jugglebot"),
                   help="directory of the Jugglebot data (skipped when absent)")
    p.add_argument("--rereference-rows", type=int, default=6,
                   help="held-out rows spent re-referencing the strut offsets (Jugglebot validation is another session)")
    p.add_argument("--skip", default="", help="comma list of parts to skip: fit,diagnose,crb,jugglebot")


def bench_fit(cfg) -> dict:
    from ..calib import synth
    from ..calib.diagnose import Options, fit_model
    from ..calib.model import Context, initial_frame
    out = {}
    for reg in (False, True):
        s = synth.generate(cfg, 7, "none", n_fit=200, n_holdout=1, registration=reg, sessions=1)
        ctx = Context(cfg, s.fit, s.noise_mm, s.noise_deg)
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            f0 = initial_frame(cfg, s.fit) if reg else None
            r = fit_model(cfg, ctx, [], f0, Options())
            times.append(time.perf_counter() - t0)
        key = "registered_frame" if reg else "base_frame"
        out[key] = {"poses": 200, "parameters": r.layout.n, "time_s_median": float(np.median(times)),
                    "iterations": r.iterations, "chi2_red": r.chi2_red, "rms_fit": r.rms()}
    out["target_s"] = 2.0
    out["meets_target"] = out["base_frame"]["time_s_median"] < 2.0
    return out


def bench_diagnose(cfg) -> dict:
    from ..calib import synth
    from ..calib.diagnose import Options, diagnose
    # thermal columns and three sessions present: every candidate of the catalog applies
    s = synth.generate(cfg, 8, "thermal_expansion", n_fit=120, n_holdout=60)
    out = {}
    for frame in ("base", "register"):
        t0 = time.perf_counter()
        d = diagnose(cfg, s.fit, s.holdout, Options(noise_mm=s.noise_mm, noise_deg=s.noise_deg, frame=frame))
        dt = time.perf_counter() - t0
        r = d.result
        out[frame] = {"time_s": dt, "candidates_fitted": sum(1 for c in r["candidates"].values() if c["applicable"]),
                      "hidden": s.effect, "verdict": r["verdict"],
                      "holdout_position_mm": r["extended"]["rms_holdout"]["position_mm"],
                      "noise_floor_position_mm": s.noise_mm * np.sqrt(3)}
    out["poses"] = 120
    out["target_s"] = 60.0
    out["meets_target"] = max(v["time_s"] for k, v in out.items() if isinstance(v, dict)) < 60.0
    return out


def bench_crb(cfg, trials: int) -> dict:
    """Empirical parameter errors over noise realisations vs the Cramér–Rao bound (weak priors)."""
    from ..calib import synth
    from ..calib.diagnose import Options, fit_model
    from ..calib.identify import parameter_table
    from ..calib.model import Context
    base = synth.generate(cfg, 9, "none", n_fit=100, n_holdout=1, sessions=1)
    truth = base.theta_true
    errs = []
    crb = None
    rng = np.random.default_rng(90)
    opts = Options(prior_joint_mm=1e3, prior_offset_mm=1e4)   # (almost) no prior: the classical bound
    clean_y = base.fit.y.copy()
    # noise-free measurements from the same machine and poses, fresh noise each trial
    from ..calib.model import measure
    X = None
    for k in range(trials):
        m = base.fit.subset(np.arange(base.fit.n))
        if X is None:
            ctx0 = Context(cfg, m, base.noise_mm, base.noise_deg)
            r0 = fit_model(cfg, ctx0, [], None, opts)
            X = r0.evaluator.X
            # reconstruct the noise-free values from the true machine
            from ..calib.model import Evaluator, build_layout
            lay = build_layout(cfg, ctx0, [], None)
            ev = Evaluator(cfg, lay, ctx0, X)
            th = lay.theta0.copy()
            th[:42] = truth
            clean_y = measure(ev.poses(th), None)
        y = clean_y.copy()
        y[:, :3] += rng.normal(0, base.noise_mm, (m.n, 3))
        y[:, 3:] += rng.normal(0, base.noise_deg, (m.n, 3))
        m.y = y
        ctx = Context(cfg, m, base.noise_mm, base.noise_deg)
        r = fit_model(cfg, ctx, [], None, opts)
        errs.append(r.theta[:42] - truth)
        if crb is None:
            crb = np.array([p["std"] for p in parameter_table(r)])[:42]
    E = np.array(errs)
    emp = np.sqrt(np.mean(E ** 2, axis=0))
    ratio = emp / crb
    return {"poses": 100, "trials": trials, "parameters": 42,
            "crb_std_mm": {"median": float(np.median(crb)), "max": float(np.max(crb))},
            "empirical_rms_error_mm": {"median": float(np.median(emp)), "max": float(np.max(emp))},
            "ratio_empirical_over_crb": {"overall": float(np.sqrt(np.mean(emp ** 2) / np.mean(crb ** 2))),
                                         "median": float(np.median(ratio)), "max": float(np.max(ratio)),
                                         "min": float(np.min(ratio))},
            "note": f"per-parameter ratios scatter with {trials} trials (a chi distribution: about ±"
                    f"{100 / np.sqrt(2 * trials):.0f} % at 1 sigma)",
            "target_overall": 1.5, "meets_target": bool(np.sqrt(np.mean(emp ** 2) / np.mean(crb ** 2)) < 1.5)}


def bench_jugglebot(data_dir: Path, k: int) -> dict:
    from ..calib.diagnose import Options, diagnose, evaluate_holdout, fit_model, nominal_rms
    from ..calib.measurements import load_measurements
    from ..calib.model import Context, initial_frame
    from ..config import load_config
    cfg = load_config(_REPO / "config" / "jugglebot.toml")
    mp = _REPO / "config" / "jugglebot-columns.toml"
    m = load_measurements(data_dir / "calibration_108_poses.csv", mp)
    h = load_measurements(data_dir / "validation_60_poses.csv", mp)
    out: dict = {"fit_rows": m.n, "holdout_rows": h.n, "rereference_rows": k,
                 "note": f"held-out figures 'k0': all 60 rows, nothing re-referenced; 'k{k}': the first {k} "
                         f"rows re-reference the six strut offsets (new session), RMS over the other {h.n - k}"}
    out["nominal_no_registration"] = {"fit": nominal_rms(cfg, m, False), "holdout": nominal_rms(cfg, h, False)}
    out["nominal_registered_frame"] = {"fit": nominal_rms(cfg, m, True)}
    ctx = Context(cfg, m, 0.01, 0.01 / 219.075 * 57.29577951308232)
    f0 = initial_frame(cfg, m)
    for name, causes in (("refit_42", []), ("refit_48_free_scale", ["strut_scale"])):
        r = fit_model(cfg, ctx, causes, f0, Options())
        out[name] = {"fit": r.rms(), "holdout_k0": evaluate_holdout(cfg, r, h, ctx, 0, "offsets")[0],
                     f"holdout_k{k}": evaluate_holdout(cfg, r, h, ctx, k, "offsets")[0]}
    t0 = time.perf_counter()
    d = diagnose(cfg, m, h, Options(rereference_rows=k))
    d0 = diagnose(cfg, m, h, Options(rereference_rows=0))
    out["diagnose"] = {"verdict": d.result["verdict"],
                       "causes": [{"name": c["name"], "contribution_mm": c["evidence"]["contribution_mm"],
                                   "cv_gain": c["evidence"]["cv_gain"]} for c in d.result["causes"]],
                       "fit": d.result["extended"]["rms_fit"],
                       f"holdout_k{k}": d.result["extended"]["rms_holdout"],
                       "holdout_k0": d0.result["extended"]["rms_holdout"],
                       "time_s": (time.perf_counter() - t0) / 2}
    out["cycle"] = bench_jugglebot_cycle(cfg, m, h, d, k)
    return out


def bench_jugglebot_cycle(cfg, m, h, d, k: int) -> dict:
    """The diagnosis' baseline and extended fits written as configs, re-loaded, and the held-out
    data evaluated through the cycle's transform (:mod:`hexacnc.calib.cyclecheck`)."""
    import tempfile

    from ..calib.cyclecheck import holdout_through_cycle, rereferenced_config
    from ..calib.diagnose import rereferenced_thetas
    from ..calib.output import fit_config_texts
    from ..config import load_config
    from ..csvio import write_text_atomic
    out: dict = {"note": "each model written as a machine description (hexacnc diagnose --out-config), loaded by "
                         "the config loader, and the held-out poses put through CycleTransform: strut_mm = physical "
                         "length the cycle commands for the measured pose - physical length of the reading (the "
                         "diagnosis' definition); drive_mm = drive command - drive reading; position/orientation: "
                         "the cycle's FK of the readings vs the measured pose. Sag compensation off (rigid fit). "
                         f"k{k}: strut offsets re-referenced on the first {k} held-out rows (re-homing), written "
                         "into the config, RMS over the rest"}
    models = (("refit_42", d.baseline.fit, []),
              ("diagnose_extended", d.extended.fit, list(d.result["fitted_causes"])))
    with tempfile.TemporaryDirectory(prefix="hexacnc-bench-") as tmp:
        for name, fit, causes in models:
            t0 = time.perf_counter()
            w = fit_config_texts(cfg, fit, causes, f"hexacnc bench calib ({name})", [])
            path = Path(tmp) / f"{name}.toml"
            write_text_atomic(path, w["config"])
            c2 = load_config(path)
            frame = fit.theta[fit.layout.frame] if fit.layout.frame is not None else None
            entry = {"causes_applied": sorted(w["applied"]), "calibration_identity": c2.calibration.identity,
                     "holdout_k0": holdout_through_cycle(c2, h, frame)}
            for theta, rows in rereferenced_thetas(cfg, fit, h, d.ctx, k, "offsets", m):
                c3 = rereferenced_config(c2, theta[36:42])
                fr = theta[fit.layout.frame] if fit.layout.frame is not None else None
                entry[f"holdout_k{k}"] = holdout_through_cycle(c3, h, fr, rows)
                entry[f"holdout_k{k}_sag_compensated_strut_mm"] = holdout_through_cycle(c3, h, fr, rows,
                                                                                        sag=True)["strut_mm"]
            from .model import bench_cycle   # per-cycle cost of the written config (command + feedback)
            bc = bench_cycle(c2, 5.0)
            entry["cycle_time_us"] = {"median": bc["median_us"], "p99": bc["p99_us"],
                                      "fk_iterations_mean": bc["fk_iterations_mean"],
                                      "path": "bench model's realistic path, 5 s at the cycle rate"}
            entry["diagnose_holdout_k%d_strut_mm" % k] = (d.result["baseline" if name == "refit_42" else "extended"]
                                                         ["rms_holdout"]["strut_mm"])
            entry["time_s"] = time.perf_counter() - t0
            out[name] = entry
    b = out["refit_42"].get(f"holdout_k{k}", {}).get("strut_mm")
    e = out["diagnose_extended"].get(f"holdout_k{k}", {}).get("strut_mm")
    out[f"holdout_k{k}_strut_ratio"] = (b / e) if b and e else None
    return out


def main(args: argparse.Namespace) -> int:
    from ..calib import limit_blas_threads
    from ..config import load_config
    limit_blas_threads(1)
    cfg = load_config(args.config)
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    res: dict = {"machine": cfg.name}
    if "fit" not in skip:
        res["fit_42_params_200_full_poses"] = bench_fit(cfg)
    if "diagnose" not in skip:
        res["diagnose_whole_catalog"] = bench_diagnose(cfg)
    if "crb" not in skip:
        res["cramer_rao"] = bench_crb(cfg, args.trials)
    if "jugglebot" not in skip:
        d = Path(args.jugglebot)
        res["jugglebot"] = (bench_jugglebot(d, args.rereference_rows) if (d / "calibration_108_poses.csv").exists()
                            else {"skipped": f"no data at {d}"})
    from ..calib.output import to_jsonable
    print(json.dumps(to_jsonable(res), indent=2))
    return 0
