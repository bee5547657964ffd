"""``hexacnc bench model``: timing and convergence figures of the machine model.

Prints one JSON object:

* ``cycle``: per-cycle time of the full transform (IK + sag + thermal offsets +
  joint-angle and length checks + forward kinematics of the feedback) while
  tracking a realistic path at 2 kHz with a lagging, quantised drive; median
  and p99 in µs and as a fraction of a 0.5 ms cycle;
* ``fk_warm``: warm-start iterations (mean, max) of that loop and of the
  numpy :class:`~hexacnc.kinematics.ForwardTracker`;
* ``fk_cold``: iterations from the home pose to 2/15/30 deg tilt, with the
  correct angle-rate mapping and with the raw angular step of genhexkins;
* ``roundtrip``: max |FK(IK(x)) - x| over seeded random poses;
* ``sag``: sag size and the first-order model's distance from the exact equilibrium.
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import os
import time

import numpy as np

from ..config import load_config
from ..kinematics import FK_OK, ForwardTracker, Hexapod
from ..pose import euler_from_matrix, matrix_from_axis_angle, matrix_from_euler, pose_to_rad
from ..sag import first_order_error
from ..transform import CycleTransform

HELP = "model timing: full per-cycle transform, FK iterations (warm and cold), round trip, sag model error"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="machine description (default: embedded default)")
    parser.add_argument("--seconds", type=float, default=20.0, help="length of the tracked path in machine time")
    parser.add_argument("--roundtrip", type=int, default=5000, help="random poses for the FK(IK(x)) check")
    parser.add_argument("--seed", type=int, default=1)


def realistic_path(cfg, seconds: float, rate_hz: float = 2000.0) -> np.ndarray:
    """Platform poses (N,6) mm/rad: a milling-like path with tilts, smooth, within the workspace.

    A 60 mm Lissajous contour at up to ~200 mm/s with z steps blended by
    smooth ramps and a/b tilts of +-8 deg, c of +-10 deg.
    """
    n = int(seconds * rate_hz)
    t = np.arange(n) / rate_hz
    home = np.asarray(cfg.home_pose, dtype=float)
    w = 2 * math.pi * 0.5
    P = np.empty((n, 6))
    P[:, 0] = home[0] + 60 * np.sin(w * t)
    P[:, 1] = home[1] + 60 * np.sin(2 * w * t + 0.3)
    P[:, 2] = home[2] + 20 * np.tanh(3 * np.sin(0.2 * w * t))
    P[:, 3] = np.radians(home[3] + 8 * np.sin(0.5 * w * t))
    P[:, 4] = np.radians(home[4] + 8 * np.cos(0.37 * w * t))
    P[:, 5] = np.radians(home[5] + 10 * np.sin(0.23 * w * t))
    return P


def genhexkins_style_forward(hx: Hexapod, L: np.ndarray, X0: np.ndarray, tol: float, max_iter: int = 100) -> int:
    """Iterations of the LinuxCNC-style update: angular Newton step subtracted straight from a, b, c."""
    X = X0.copy()
    for it in range(max_iter + 1):
        r = L - hx.lengths_rad(X)
        if np.max(np.abs(r)) <= tol:
            return it
        d = np.linalg.solve(hx.jacobian_twist_rad(X), r)
        X += d          # omega treated as Euler-angle rates
    return max_iter


def bench_cycle(cfg, seconds: float) -> dict:
    hx = Hexapod(cfg)
    ct = CycleTransform(cfg, hx)
    P = realistic_path(cfg, seconds, 1.0 / cfg.cycle.period_s)
    ct.set_thermal_offsets_mm([0.003, -0.002, 0.004, 0.001, 0.0, 0.002])
    inc = float(cfg.bus.increments_per_mm)
    lag = 3
    n = P.shape[0]
    hist = [[0.0] * 6 for _ in range(lag + 1)]
    ct.reset_pose(P[0])
    ct.command(*P[0])
    ct._have_prev = 0
    for k in range(lag + 1):
        hist[k][:] = ct.cmd_mm
    times = np.empty(n)
    iters = np.empty(n, dtype=int)
    act = [0.0] * 6
    gc.collect()
    gc.disable()
    perf = time.perf_counter_ns
    try:
        for k in range(n):
            x = P[k]
            a0, a1, a2, a3, a4, a5 = float(x[0]), float(x[1]), float(x[2]), float(x[3]), float(x[4]), float(x[5])
            old = hist[k % (lag + 1)]
            for i in range(6):  # drive: command from `lag` cycles ago, quantised to one increment
                act[i] = round(old[i] * inc) / inc
            t0 = perf()
            code = ct.command(a0, a1, a2, a3, a4, a5)
            fcode = ct.feedback(act)
            t1 = perf()
            if code or fcode:
                raise RuntimeError(f"cycle {k}: {ct.describe(code or fcode)}")
            old[:] = ct.cmd_mm
            times[k] = (t1 - t0) * 1e-3
            iters[k] = ct.fk_iterations
    finally:
        gc.enable()
    skip = 10
    t = times[skip:]
    return {
        "cycles": int(n),
        "period_s": cfg.cycle.period_s,
        "median_us": round(float(np.median(t)), 2),
        "p99_us": round(float(np.percentile(t, 99)), 2),
        "p999_us": round(float(np.percentile(t, 99.9)), 2),
        "max_us": round(float(np.max(t)), 2),
        "median_fraction_of_0.5ms": round(float(np.median(t)) / 500.0, 4),
        "p99_fraction_of_0.5ms": round(float(np.percentile(t, 99)) / 500.0, 4),
        "target_p99_us": 50.0,
        "fk_iterations_mean": round(float(np.mean(iters[skip:])), 3),
        "fk_iterations_max": int(np.max(iters[skip:])),
        "feedback": f"drive = command delayed {lag} cycles, quantised to 1/{inc:g} mm",
    }


def bench_tracker(cfg, seconds: float) -> dict:
    hx = Hexapod(cfg)
    P = realistic_path(cfg, min(seconds, 5.0), 2000.0)
    P[:, 3:] = np.degrees(P[:, 3:])
    L = hx.inverse_batch(P)
    tr = ForwardTracker(hx, P[0])
    err = 0.0
    for k in range(P.shape[0]):
        r = tr.track(L[k])
        if r.status != FK_OK:
            raise RuntimeError(f"tracker failed at {k}: {r.status}")
        err = max(err, float(np.max(np.abs(r.pose - P[k]))))
    return {"calls": tr.calls, "iterations_mean": round(tr.mean_iterations, 3),
            "iterations_max": tr.max_iterations, "tolerance_mm": hx.tol_mm, "max_pose_error": err}


def bench_cold(cfg) -> dict:
    hx = Hexapod(cfg)
    home = np.asarray(cfg.home_pose, dtype=float)
    out = {}
    for tilt in (2.0, 15.0, 30.0):
        # tilt of the tool axis by `tilt` about the diagonal (1, 1, 0) axis of the base frame
        target = home.copy()
        target[3:] = np.degrees(euler_from_matrix(matrix_from_axis_angle([1.0, 1.0, 0.0], math.radians(tilt))
                                                  @ matrix_from_euler(*np.radians(home[3:]))))
        L = hx.lengths(target)
        r = hx.forward(L, guess=home)
        raw = genhexkins_style_forward(hx, L, pose_to_rad(home), hx.tol_mm)
        out[f"{tilt:g}deg"] = {"iterations": r.iterations, "status": r.status,
                               "genhexkins_style_iterations": raw,
                               "pose_error_mm": float(np.max(np.abs(r.pose[:3] - target[:3]))),
                               "pose_error_deg": float(np.max(np.abs(r.pose[3:] - target[3:])))}
    out["tolerance_mm"] = hx.tol_mm
    out["target_max_iterations"] = 6
    return out


def bench_roundtrip(cfg, n: int, seed: int) -> dict:
    hx = Hexapod(cfg)
    rng = np.random.default_rng(seed)
    P = rng.uniform(cfg.workspace_min, cfg.workspace_max, size=(n * 2, 6))
    P = P[~hx.batch_violations(P)][:n]
    L = hx.inverse_batch(P)
    emm = edeg = 0.0
    iters = []
    for k in range(P.shape[0]):
        r = hx.forward(L[k], guess=cfg.home_pose, tol_mm=1e-10)
        if r.status != FK_OK:
            raise RuntimeError(f"round trip failed at pose {P[k].tolist()}: {r.status}")
        emm = max(emm, float(np.max(np.abs(r.pose[:3] - P[k, :3]))))
        R1 = matrix_from_euler(*np.radians(P[k, 3:]))
        R2 = matrix_from_euler(*np.radians(r.pose[3:]))
        edeg = max(edeg, math.degrees(float(np.linalg.norm(R1 - R2))), float(np.max(np.abs(r.pose[3:] - P[k, 3:]))))
        iters.append(r.iterations)
    return {"poses": int(P.shape[0]), "seed": seed, "max_error_mm": emm, "max_error_deg": edeg,
            "fk_tolerance_mm": 1e-10, "cold_iterations_mean": round(float(np.mean(iters)), 2),
            "cold_iterations_max": int(np.max(iters)), "target": 1e-9}


def bench_sag(cfg, seed: int) -> dict:
    hx = Hexapod(cfg)
    rng = np.random.default_rng(seed)
    P = rng.uniform(cfg.workspace_min, cfg.workspace_max, size=(200, 6))
    P = P[~hx.batch_violations(P)][:60]
    out = first_order_error(hx, P)
    out.update({f"{k}_with_20kg_payload": v for k, v in first_order_error(hx, P[:20], payload_kg=20.0).items()
                if k.startswith("max_")})
    return out


def main(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    privileges = {"cpu_count": os.cpu_count()}
    try:
        os.sched_setaffinity(0, {max(os.sched_getaffinity(0))})
        privileges["pinned_cpu"] = max(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        privileges["pinned_cpu"] = None
    result = {
        "machine": cfg.name,
        "cycle": bench_cycle(cfg, args.seconds),
        "fk_warm_tracker": bench_tracker(cfg, args.seconds),
        "fk_cold": bench_cold(cfg),
        "roundtrip": bench_roundtrip(cfg, args.roundtrip, args.seed),
        "sag": bench_sag(cfg, args.seed),
        "environment": privileges,
    }
    print(json.dumps(result, indent=2))
    return 0
