"""``hexacnc calib verify``: tool-tip errors on validation poses measured on the running machine.

Each pose is commanded as in ``calib run`` (approach, settle, checked reading); the error is the
instrument's tool tip (:func:`hexacnc.sim.instruments.measured_tip`) minus the commanded tool tip,
over the coordinates the instrument measures.  Figures in um: RMS over poses of the error's
length, its maximum, per-axis RMS.  ``compare`` puts a previous verification (before) beside.
With ``--json OUT`` the rows go to ``OUT.rows.jsonl`` as they are taken: a verification
interrupted (a lost daemon) resumes after its last row when run again with the same poses,
instrument and config; the file is removed once the summary is written.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..sim.instruments import measured_tip
from .cyclerun import RunOptions, measure_pose


def _resumed(rows_path, head: dict) -> list[dict]:
    """Rows of an interrupted verification of the same poses, instrument and config (else none: the
    file is started again)."""
    p = Path(rows_path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
        if lines and json.loads(lines[0]) == head:
            return [json.loads(ln) for ln in lines[1:] if ln.strip()]
    except (OSError, ValueError):
        pass
    p.write_text(json.dumps(head) + "\n", encoding="utf-8")
    return []


def verify_poses(client, cfg, poses_deg: np.ndarray, opts: RunOptions, rows_path=None) -> dict:
    """Measure every pose; ``rows_path``: rows appended as taken (JSON lines), and an interrupted
    verification of the same poses resumes after its last row."""
    from ..kinematics import Hexapod
    hx = Hexapod(cfg)
    tip_mm = np.asarray(cfg.tool.tip_platform_mm, dtype=float)
    head = {"poses": np.round(np.asarray(poses_deg, dtype=float), 6).tolist(), "instrument": opts.instrument,
            "config": str(cfg.path)}
    rows = _resumed(rows_path, head) if rows_path is not None else []
    for k, X in enumerate(poses_deg):
        if k < len(rows):
            continue
        r = measure_pose(client, cfg, hx, X, k, opts)
        if not r.values:
            row = {"pose": k + 1, "flag": r.flag}
        else:
            Xc = np.r_[X[:3], np.radians(X[3:])]
            m = measured_tip(r.values, r.target, tip_mm, Xc)
            err = {ax: (m[ax] - r.tip_cmd_mm["xyz".index(ax)]) * 1e3 for ax in m}
            row = {"pose": k + 1, "error_um": err, "flag": r.flag, "q_mm": r.q_mm, "tip_cmd_mm": r.tip_cmd_mm[:3]}
        rows.append(row)
        if rows_path is not None:
            with open(rows_path, "a", encoding="utf-8") as f:
                f.write(json.dumps(row) + "\n")
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
