"""``hexacnc calib synth-machine | run | apply | verify`` and ``hexacnc reload`` (the calibration cycle)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..errors import DataError


def configure(sub) -> None:
    sm = sub.add_parser("synth-machine", help="write a plausible true machine (simulation: hexacnc run --truth)",
                        description="write a seeded true machine around a configured one: joint positions off by "
                                    "0.1-0.3 mm, strut offsets 0.1-0.5 mm, stiffness +-20 %% per strut, strut gain "
                                    "errors 1e-4..1e-3, carrier mass +-5 %%, COG +-5 mm, half backlash 0-3 um "
                                    "(all times --magnitude)")
    sm.add_argument("--config", default=None, help="nominal machine (default: the embedded default)")
    sm.add_argument("--seed", type=int, required=True)
    sm.add_argument("--magnitude", type=float, default=1.0, help="scale of every tolerance (default 1)")
    sm.add_argument("--out", required=True, help="true machine (TOML)")
    sm.set_defaults(_calib=_synth_machine)

    from .send import add_connection_args
    rn = sub.add_parser("run", help="measure a plan on the running machine (resumable), write the measurement CSV",
                        description="run a measurement plan (hexacnc calib plan --out) on the running daemon: "
                                    "approach per pose, settle, instrument reading paired with the drive readings; "
                                    "rows appended as taken (re-run to resume); unreachable poses refused first")
    rn.add_argument("plan", help="plan CSV (x,y,z,a,b,c platform poses)")
    rn.add_argument("--out", required=True, help="measurement CSV (docs/measurements.md) + side-car OUT.json")
    _run_args(rn)
    add_connection_args(rn)
    rn.set_defaults(_calib=_run)

    ap = sub.add_parser("apply", help="put a fitted calibration into a machine description (atomic, old kept)")
    ap.add_argument("result", help="calibration result: config of calib fit --out / diagnose --out-config, "
                                   "or a --out-calibration fragment")
    ap.add_argument("--config", required=True, help="the machine description to calibrate")
    ap.add_argument("--out", required=True, help="calibrated machine description (an existing one is kept as .bak)")
    ap.set_defaults(_calib=_apply)

    vf = sub.add_parser("verify", help="measure validation poses, print the tool-tip errors (before/after)")
    vf.add_argument("--poses", required=True, help="validation poses CSV (x,y,z,a,b,c), not used for fitting")
    vf.add_argument("--before", help="JSON of an earlier verify (--json) to print beside")
    vf.add_argument("--json", help="write the figures as JSON")
    _run_args(vf)
    add_connection_args(vf)
    vf.set_defaults(_calib=_verify)


def _run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--instrument", choices=("tracker", "probe", "indicator"), default="tracker")
    p.add_argument("--settle-s", type=float, default=0.2, help="rest before each reading (default 0.2 s)")
    p.add_argument("--approach-mm", type=float, default=0.3,
                   help="every strut approaches each pose extending by this much (backlash; default 0.3)")
    p.add_argument("--retries", type=int, default=2, help="re-measurements of a flagged reading (default 2)")
    p.add_argument("--outlier-mm", type=float, default=2.0,
                   help="a reading this far from the model's pose is an outlier (default 2 mm)")
    p.add_argument("--wait-s", type=float, default=5.0, help="how long to wait for an external reading")
    p.add_argument("--probe-cycle", choices=("touch", "result"), default="touch",
                   help="probe: 5 G38.2 touches per artefact sphere (default), or the simulated cycle's result "
                        "(op measure)")
    p.add_argument("--reset-faults", type=int, default=0,
                   help="reset a drive fault and measure that pose again, at most N times (default 0: stop; "
                        "rows taken are kept either way)")
    p.add_argument("--quiet", "-q", action="store_true")


def _opts(args):
    from ..calib.cyclerun import RunOptions
    for nm in ("settle_s", "approach_mm", "outlier_mm", "wait_s"):
        v = getattr(args, nm)
        if not (0.0 <= v <= 600.0):
            raise DataError(f"--{nm.replace('_', '-')} {v}: expected 0..600")
    if not 0 <= args.retries <= 10:
        raise DataError(f"--retries {args.retries}: expected 0..10")
    if not 0 <= args.reset_faults <= 100:
        raise DataError(f"--reset-faults {args.reset_faults}: expected 0..100")
    return RunOptions(instrument=args.instrument, approach_mm=args.approach_mm, settle_s=args.settle_s,
                      retries=args.retries, outlier_mm=args.outlier_mm, wait_s=args.wait_s,
                      progress=not args.quiet, reset_faults=args.reset_faults, probe_cycle=args.probe_cycle)


def _synth_machine(args) -> int:
    from ..calib.measurements import atomic_write_text
    from ..calib.output import dumps_toml
    from ..config import load_config
    from ..sim.truth import synth_truth_doc
    cfg = load_config(args.config)
    doc = synth_truth_doc(cfg, args.seed, args.magnitude)
    atomic_write_text(args.out, dumps_toml(doc, f"true machine (simulation only) written by hexacnc calib "
                                                f"synth-machine --seed {args.seed} --magnitude {args.magnitude:g}"))
    print(json.dumps({"out": args.out, "seed": args.seed, "magnitude": args.magnitude, "nominal": cfg.path}))
    return 0


def _poses(args, path, cfg, opts):
    from ..calib.cyclerun import check_reachable, load_plan, probe_reach_offsets_mm, retarget_probe
    poses = load_plan(path)
    offs = None
    if opts.instrument == "probe":
        from ..sim.instruments import TouchProbe
        poses = retarget_probe(cfg, poses, TouchProbe().spheres)
        offs = probe_reach_offsets_mm() if opts.probe_cycle == "touch" else None
    check_reachable(cfg, poses, opts.approach_mm, str(path), offs)
    return poses


def _run(args) -> int:
    from ..calib.cyclerun import run_plan
    from ..config import load_config
    from .send import connect
    cfg = load_config(args.config)
    opts = _opts(args)
    poses = _poses(args, args.plan, cfg, opts)
    sig = {"tracker": (0.008, 0.0005), "probe": (0.0012, None), "indicator": (0.001, None)}[opts.instrument]
    meta = {"instrument": opts.instrument, "plan": str(args.plan), "config": cfg.path, "sigma_mm": sig[0],
            "sigma_deg": sig[1], "approach_mm": opts.approach_mm, "settle_s": opts.settle_s}
    if opts.instrument == "probe":
        opts.probe_log = str(args.out) + ".probes.jsonl"
    with connect(args, "hexacnc calib run") as client:
        res = run_plan(client, cfg, poses, args.out, opts, meta)
    flagged = [{"row": r.index + 1, "flag": r.flag} for r in res if r.flag]
    print(json.dumps({"out": args.out, "poses": len(poses), "taken_now": len(res), "flagged": flagged,
                      "fit": f"hexacnc calib fit --config {cfg.path} --data {args.out} --out calibrated.toml"},
                     indent=2))
    return 0


def _apply(args) -> int:
    from ..calib.apply import apply_result
    rep = apply_result(args.result, args.config, args.out)
    print(f"wrote {rep['out']}" + (f" (previous kept as {rep['kept']})" if rep["kept"] else ""))
    for ln in rep["changes"]:
        print("  " + ln)
    if not rep["changes"]:
        print("  no change")
    return 0


def _verify(args) -> int:
    from ..calib.measurements import atomic_write_text
    from ..calib.verify import compare_text, verify_poses
    from ..config import load_config
    from .send import connect
    cfg = load_config(args.config)
    opts = _opts(args)
    poses = _poses(args, args.poses, cfg, opts)
    before = None
    if args.before:
        try:
            before = json.loads(Path(args.before).read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise DataError(f"--before {args.before}: {exc}") from None
    rows = str(args.json) + ".rows.jsonl" if args.json else None
    with connect(args, "hexacnc calib verify") as client:
        rep = verify_poses(client, cfg, poses, opts, rows)
    if args.json:
        atomic_write_text(args.json, json.dumps(rep, indent=2) + "\n")
        Path(rows).unlink(missing_ok=True)
    print(compare_text(before, rep))
    for e in rep["excluded"]:
        print(f"  pose {e['pose']}: {e['flag']}", file=sys.stderr)
    return 0


def fit_from_run(args, cfg) -> int:
    """``calib fit`` on a ``calib run`` file (side-car present): base frame, fixed target."""
    from ..calib.cyclefit import fit_cycle
    from ..calib.measurements import atomic_write_text
    from .diagnose import parse_causes
    causes = list(parse_causes(args.causes)) if args.causes.strip() else ["strut_scale"]
    fit_sag = "elastic_sag" in causes
    causes = [c for c in causes if c != "elastic_sag"]
    bad = [c for c in causes if c not in ("strut_scale", "strut_nonlinearity")]
    if bad:
        raise DataError(f"--causes {','.join(bad)}: a calib run file is fitted with strut_scale, "
                        f"strut_nonlinearity and elastic_sag")
    cf = fit_cycle(cfg, args.data, causes, fit_sag, noise_mm=args.noise_mm, noise_deg=args.noise_deg,
                   prior_joint_mm=args.prior_mm, prior_offset_mm=args.prior_offset_mm)
    atomic_write_text(args.out, cf.written["config"])
    if args.out_calibration:
        atomic_write_text(args.out_calibration, cf.written["fragment"])
    rms = cf.result.rms()
    rep = {"out": args.out, "target": cf.meta["target"], "instrument": cf.meta.get("instrument"),
           "rows_used": cf.rows_used, "rows_excluded": cf.rows_excluded, "rms_fit": rms,
           "chi2_red": cf.result.chi2_red, "applied": cf.written["applied"],
           "iterations": cf.result.iterations}
    if args.json:
        from ..calib.output import write_json
        write_json(args.json, rep)
    print(json.dumps(rep, indent=2, default=float))
    return 0


# -- hexacnc reload ------------------------------------------------------------------------------
HELP = "load a machine description into the running daemon (validated; refused while moving)"


def configure_reload(p: argparse.ArgumentParser) -> None:
    from .send import add_connection_args
    p.add_argument("machine", help="machine description to load (e.g. the output of hexacnc calib apply)")
    add_connection_args(p)


def main_reload(args) -> int:
    from ..config import load_config
    from ..daemon.protocol import DaemonError
    from .send import connect
    load_config(args.machine)             # same check locally first: a clear error before any contact
    try:
        with connect(args, "hexacnc reload") as client:
            r = client.call("reload", config=str(Path(args.machine).resolve()), reply_timeout_s=120.0)
    except DaemonError as exc:
        print(f"hexacnc reload: refused: {exc}", file=sys.stderr)
        return 3
    print(f"reloaded {r.get('config')} ({r.get('machine')})")
    return 0

