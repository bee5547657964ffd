"""Held-out measurements through the running cycle's own transform.

:func:`holdout_through_cycle` takes a machine description *as written* by
``hexacnc diagnose --out-config`` / ``hexacnc calib fit --out`` (loaded by the
config loader), builds the cycle's :class:`~hexacnc.transform.CycleTransform`
from it and, for each measured full pose (mapped into the base frame through
the measurement frame of the fit), compares what the cycle does with what the
machine did:

* ``strut_mm``: physical strut length the cycle commands for the measured pose
  (``phys_mm``) minus the physical length of the drive's reading under the same
  calibrated map, the diagnosis' ``strut_mm`` definition;
* ``drive_mm``: the drive command the cycle sends (``cmd_mm``) minus the drive
  reading (both drive-scale lengths, ``strut_offset + q``);
* ``position_mm``/``orientation_deg``: the cycle's forward kinematics of the
  readings (``feedback``), seen through the measurement frame, against the
  measured pose (the diagnosis' definitions: 3-D RMS per row).

The cycle's sag compensation is off by default (``sag=False``): the geometry
was fitted as a rigid model, so the carrier weight is already in it on average.
"""
from __future__ import annotations

import numpy as np

from ..errors import DataError
from .measurements import Measurements
from .model import measure, unmeasure


def holdout_through_cycle(cfg, hold: Measurements, frame: np.ndarray | None, rows=None,
                          sag: bool = False) -> dict:
    """RMS figures of the held-out ``rows`` (default all full-pose rows) through ``cfg``'s cycle."""
    from ..transform import OK, CycleTransform
    ct = CycleTransform(cfg, sag=sag)
    full = hold.full_pose_rows()
    idx = np.arange(hold.n) if rows is None else np.asarray(rows, dtype=int)
    idx = idx[full[idx]]
    if not len(idx):
        raise DataError(f"{hold.path}: no full-pose row to evaluate through the cycle")
    Xb = unmeasure(hold.y[idx], None if frame is None else np.asarray(frame, dtype=float))
    off = np.asarray(cfg.strut_offset_mm, dtype=float)
    D = hold.q[idx] + off[None]                      # drive-scale lengths of the readings
    phys_read = ct.strut_map.strut_from_drive(D)
    dl, dd = [], []
    fk_rows, fk_poses = [], []
    refused: list[dict] = []
    for k in range(len(idx)):
        X = [float(v) for v in Xb[k]]
        ct._have_prev = 0                            # each row is a standstill, not a move from the last
        code = ct.command(*X)
        if code != OK:
            refused.append({"row": int(idx[k]), "reason": ct.describe(code)})
            continue
        dl.append(np.array(ct.phys_mm) - phys_read[k])
        dd.append(np.array(ct.cmd_mm) - D[k])
        ct.reset_pose(X)
        if ct.feedback([float(v) for v in D[k]]) == OK:
            fk_rows.append(k)
            fk_poses.append(list(ct.pose_act))
        else:
            refused.append({"row": int(idx[k]), "reason": ct.describe(7)})
    dp = da = []
    if fk_rows:
        F = None if frame is None else np.asarray(frame, dtype=float)
        e = measure(np.array(fk_poses), F) - hold.y[idx[fk_rows]]
        e[:, 3:] = (e[:, 3:] + 180.0) % 360.0 - 180.0
        dp, da = list(e[:, :3]), list(e[:, 3:])
    def rms(a, per_row: bool):
        if not a:
            return None
        A = np.array(a)
        return float(np.sqrt(np.mean(np.sum(A ** 2, axis=1)))) if per_row else float(np.sqrt(np.mean(A ** 2)))
    return {"rows_evaluated": len(dl), "rows_refused": refused, "calibrated_map": ct.calibrated,
            "sag_compensation": ct.sag_enabled,
            "strut_mm": rms(dl, False), "drive_mm": rms(dd, False),
            "position_mm": rms(dp, True), "orientation_deg": rms(da, True)}


def rereferenced_config(cfg, offsets_mm):
    """``cfg`` with new strut offsets (re-homing), re-checked by the loader."""
    import copy

    from ..config import parse_config
    doc = copy.deepcopy(cfg.raw)
    doc.setdefault("geometry", {})["strut_offset_mm"] = [float(v) for v in offsets_mm]
    return parse_config(doc, f"{cfg.path} (strut offsets re-referenced)")
