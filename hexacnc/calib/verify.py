"""``hexacnc calib verify``: tool-tip errors on validation poses measured on the running machine.

Each pose is commanded as in ``calib run`` (approach, settle, checked reading); the error is the
instrument's tool tip (:func:`hexacnc.sim.instruments.measured_tip`) minus the commanded tool tip,
over the coordinates the instrument measures.  Figures in um: RMS over poses of the error's
length, its maximum, per-axis RMS.  ``compare`` puts a previous verification (before) beside.
"""
from __future__ import annotations

import math

import numpy as np

from ..sim.instruments import measured_tip
from .cyclerun import RunOptions, measure_pose


def verify_poses(client, cfg, poses_deg: np.ndarray, opts: RunOptions) -> dict:
    from ..kinematics import Hexapod
    hx = Hexapod(cfg)
    tip_mm = np.asarray(cfg.tool.tip_platform_mm, dtype=float)
    rows = []
    for k, X in enumerate(poses_deg):
        r = measure_pose(client, cfg, hx, X, k, opts)
        if not r.values:
            rows.append({"pose": k + 1, "flag": r.flag})
            opts.progress and _bar(k + 1, len(poses_deg))
            continue
        Xc = np.r_[X[:3], np.radians(X[3:])]
        m = measured_tip(r.values, r.target, tip_mm, Xc)
        err = {ax: (m[ax] - r.tip_cmd_mm["xyz".index(ax)]) * 1e3 for ax in m}
        rows.append({"pose": k + 1, "error_um": err, "flag": r.flag, "q_mm": r.q_mm, "tip_cmd_mm": r.tip_cmd_mm[:3]})
        opts.progress and _bar(k + 1, len(poses_deg))
    return summarize(rows, opts.instrument, cfg.path)


def _bar(k: int, n: int) -> None:
    import sys
    sys.stderr.write(f"\rverify {k}/{n}")
    if k == n:
        sys.stderr.write("\n")
    sys.stderr.flush()


def summarize(rows: list[dict], instrument: str, config: str) -> dict:
    errs = [r["error_um"] for r in rows if "error_um" in r]
    norms = np.array([math.sqrt(sum(v * v for v in e.values())) for e in errs]) if errs else np.zeros(0)
    axes = {}
    for ax in "xyz":
        v = np.array([e[ax] for e in errs if ax in e])
        if v.size:
            axes[ax] = float(np.sqrt(np.mean(v ** 2)))
    return {"instrument": instrument, "config": config, "poses": len(rows), "measured": int(norms.size),
            "excluded": [r for r in rows if "error_um" not in r],
            "rms_um": float(np.sqrt(np.mean(norms ** 2))) if norms.size else None,
            "max_um": float(norms.max()) if norms.size else None,
            "axis_rms_um": axes, "rows": rows}


def compare_text(before: dict | None, after: dict) -> str:
    def line(name, s):
        if s is None:
            return f"{name:7s} -"
        ax = ", ".join(f"{k} {v:.1f}" for k, v in s["axis_rms_um"].items())
        return (f"{name:7s} RMS {s['rms_um']:.1f} um, max {s['max_um']:.1f} um over {s['measured']} poses "
                f"({ax}) - {s['config']}")
    out = ["tool-tip error on the validation poses (" + after["instrument"] + ")"]
    if before is not None:
        out.append(line("before", before))
    out.append(line("after" if before is not None else "now", after))
    if before is not None and before.get("rms_um") and after.get("rms_um") is not None:
        out.append(f"RMS reduced by {100.0 * (1.0 - after['rms_um'] / before['rms_um']):.1f} %")
    return "\n".join(out)
