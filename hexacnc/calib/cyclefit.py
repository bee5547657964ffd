"""Fit of a ``calib run`` measurement file: the 42 parameters plus the causes the cycle applies.

The instrument's frame is the base frame (the tracker or artefact is registered to the machine
base) and the measured target is fixed: the platform frame (tracker) or the tool tip
``[tool] tip_platform_mm`` (touch probe, dial indicator) - the ``target`` of the file's side-car
``MEAS.csv.json`` written by ``calib run``.  Elastic sag is in the model at the configured
stiffness (the cycle compensates it with that stiffness), fitted only with ``fit_sag``.
Uses the public pieces of :mod:`hexacnc.calib.model` / :mod:`.identify` / :mod:`.output`.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError
from .identify import FitResult, fit
from .measurements import Measurements, load_measurements
from .model import Context, build_layout
from .output import fit_config_texts


@dataclass
class CycleFit:
    result: FitResult
    written: dict                 #: fit_config_texts output (config text, applied causes, ...)
    meta: dict
    rows_used: int
    rows_excluded: int


def read_meta(path) -> dict:
    p = Path(str(path) + ".json")
    if not p.exists():
        return {"target": "platform"}
    try:
        m = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise DataError(f"{p}: unreadable side-car of {path}: {exc}") from None
    if m.get("target") not in ("platform", "tool"):
        raise DataError(f"{p}: target {m.get('target')!r}: expected platform or tool")
    return m


def _used(meas: Measurements) -> Measurements:
    keep = np.where(meas.mask.any(axis=1))[0]
    return meas.subset(keep)


def fit_cycle(cfg, data_path, causes=("strut_scale",), fit_sag: bool = False, target: str | None = None,
              noise_mm: float | None = None, noise_deg: float | None = None,
              prior_joint_mm: float = 5.0, prior_offset_mm: float = 50.0) -> CycleFit:
    meta = read_meta(data_path)
    target = target or meta.get("target", "platform")
    raw = load_measurements(data_path, min_rows=3)
    meas = _used(raw)
    nm = float(noise_mm or meta.get("sigma_mm") or 0.005)
    nd = float(noise_deg or meta.get("sigma_deg") or 0.0005)
    ctx = Context(cfg, meas, nm, nd)
    tgt = np.asarray(cfg.tool.tip_platform_mm, dtype=float) if target == "tool" else np.zeros(3)
    frame0 = np.r_[np.zeros(6), tgt, np.zeros(3)]
    sag = cfg.mass_kg > 0
    all_causes = list(causes) + (["elastic_sag"] if sag else [])
    lay = build_layout(cfg, ctx, all_causes, frame0, prior_joint_mm, prior_offset_mm)
    n_free = lay.n - 12 - (0 if (fit_sag or not sag) else 1)
    if meas.n_observations < n_free:
        raise DataError(f"{data_path}: {meas.n_observations} measured coordinates in {meas.n} usable rows for "
                        f"{n_free} parameters; measure more poses")
    theta0 = lay.theta0.copy()
    free = np.ones(lay.n, dtype=bool)
    free[lay.frame] = False
    if sag:
        sl = lay.causes["elastic_sag"]
        theta0[sl] = 1000.0 / float(np.mean(cfg.stiffness_N_per_mm))     # mm/kN at the configured stiffness
        if not fit_sag:
            free[sl] = False
    res = fit(cfg, ctx, lay, theta_init=theta0, free=free)
    if not np.all(res.evaluator.converged):
        raise DataError(f"{data_path}: some rows give no pose of this machine even after fitting")
    written_causes = list(causes) + (["elastic_sag"] if (sag and fit_sag) else [])
    rms = res.rms()
    src = (f"hexacnc calib fit of {data_path} ({meas.n} rows, target {target}, causes "
           f"{', '.join(written_causes) or 'none'})")
    header = [f"calibrated from {data_path} by the hexacnc calibration cycle, starting from {cfg.path}",
              f"fit RMS: position {rms['position_mm']} mm, orientation {rms['orientation_deg']} deg"]
    written = fit_config_texts(cfg, res, written_causes, src, header)
    return CycleFit(res, written, dict(meta, target=target), meas.n, raw.n - meas.n)
