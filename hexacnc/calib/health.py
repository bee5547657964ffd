"""Model health from a recording: following-error and torque patterns separated by cause.

Patterns (each a *finding* with its evidence; ``status`` is ``ok``, ``warning``
or ``insufficient_data``):

* ``payload_changed``: the drive torques at rest poses identify a payload mass
  (and centre of gravity, :mod:`.payload`) significantly different from the
  one the sag model assumes -> the sag compensation is wrong; a ``[carrier]``
  update and its effect on sag are proposed.
* ``thermal_not_compensated``: the strut temperatures moved, and the growth
  they imply (``expansion_per_K * L * dT``) is not matched by the thermal offsets
  the cycle applied.
* ``friction_changed`` (per strut): the Coulomb friction of one strut, from the
  torque (or, without torques, the following error) against the direction of
  motion, differs from the reference recording or from the other struts.
* ``stiffness_changed`` (per strut): the following error of one strut grows
  with its static force (an unmodelled compliance: a softer strut, a worn joint).

Per-strut regressions use samples in motion; the static force of each sample is
computed from the commanded pose with the payload the model assumes.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import DataError
from ..kinematics import Hexapod
from .payload import DriveTorqueModel, carrier_update, identify_payload, identify_payload_in_motion, rest_forces
from .recording import Recording, strut_rates

#: a per-strut coefficient is an outlier beyond this many robust standard deviations of the others
OUTLIER_Z = 6.0
#: and by at least this ratio (friction) or amount (compliance, mm/kN)
FRICTION_RATIO = 1.5
COMPLIANCE_MM_PER_KN = 0.2
THERMAL_TOL_MM = 0.005


#: a rest ends this long (s, recorder clock) before the drives are seen disabled and starts this long after
#: they are seen enabled again: the status reports a fault's disable (and a reset's enable) after the drives
#: already dropped (or not yet took) the load, so torques near it are of unloaded drives
ENABLE_GUARD_S = 0.5


def unloaded(rec: Recording) -> np.ndarray:
    """(N,) True where the drives were disabled, or within :data:`ENABLE_GUARD_S` of such a sample."""
    t = rec["t_s"]
    en = rec.data.get("drives_enabled")
    if en is None or not np.any(en == 0.0):
        return np.zeros(rec.n, dtype=bool)
    off = t[en == 0.0]
    k = np.searchsorted(off, t)                          # the nearest disabled samples before and after
    before = np.where(k > 0, t - off[np.maximum(k - 1, 0)], np.inf)
    after = np.where(k < len(off), off[np.minimum(k, len(off) - 1)] - t, np.inf)
    return np.minimum(before, after) <= ENABLE_GUARD_S


def rest_windows(rec: Recording, min_s: float = 0.3, v_mm_s: float = 0.05) -> list[np.ndarray]:
    """Sample indices of each rest (commanded struts still for ``min_s`` with the drives enabled, and not
    within :data:`ENABLE_GUARD_S` of a sample with them disabled: a fault or a disabled machine also leaves
    the commands still, but its drives hold no load), the first 40 % of each dropped."""
    t = rec["t_s"]
    L = rec["struts_cmd_mm"]
    if rec.n < 3:
        return []
    v = np.max(np.abs(np.gradient(L, t, axis=0)), axis=1)
    still = (v < v_mm_s) & ~unloaded(rec)
    out, k = [], 0
    while k < rec.n:
        if not still[k]:
            k += 1
            continue
        j = k
        while j < rec.n and still[j]:
            j += 1
        if t[j - 1] - t[k] >= min_s:
            idx = np.arange(k, j)
            out.append(idx[int(0.4 * len(idx)):])
        k = j
    return out


def _per_strut_fit(y: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares y = F b per strut (y (N,6), F (N,6,k)); coefficients and standard errors (6,k)."""
    k = F.shape[2]
    coef, se = np.zeros((6, k)), np.zeros((6, k))
    for i in range(6):
        A, b = F[:, i], y[:, i]
        ok = np.all(np.isfinite(A), axis=1) & np.isfinite(b)
        A, b = A[ok], b[ok]
        if len(b) <= k + 2:
            coef[i], se[i] = np.nan, np.nan
            continue
        c, *_ = np.linalg.lstsq(A, b, rcond=None)
        r = b - A @ c
        s2 = float(r @ r) / (len(b) - k)
        coef[i] = c
        se[i] = np.sqrt(np.maximum(np.diag(np.linalg.pinv(A.T @ A)) * s2, 0.0))
    return coef, se


def _outliers(values: np.ndarray, se: np.ndarray, ref: np.ndarray | None, ratio: float | None,
              delta: float | None) -> list[tuple[int, float, float]]:
    """(strut, value, reference) of struts off their reference (the reference recording, else the median
    of the other struts) by ``OUTLIER_Z`` combined standard errors and by ``ratio`` / ``delta``."""
    out = []
    for i in range(6):
        others = np.delete(values, i)
        r = ref[i] if ref is not None else float(np.median(others))
        spread = 0.0 if ref is not None else 1.4826 * float(np.median(np.abs(others - np.median(others))))
        s = math.sqrt(se[i] ** 2 + spread ** 2) + 1e-12
        z = abs(values[i] - r) / s
        big = (ratio is not None and (values[i] > ratio * r or values[i] < r / ratio)) or \
              (delta is not None and abs(values[i] - r) > delta)
        if z > OUTLIER_Z and big:
            out.append((i, float(values[i]), float(r)))
    return out


def strut_coefficients(rec: Recording, hx: Hexapod, payload_kg: float, k_N_per_permille: float) -> dict:
    """Per strut, from samples in motion: Coulomb friction (N) from torques or following error, and the
    following error's compliance to the static force (mm/kN)."""
    v, _ = strut_rates(rec)
    moving = np.abs(v) > 1.0
    idx = np.where(moving.any(axis=1))[0]
    step = max(1, len(idx) // 3000)      # bounded cost whatever the recording's length
    idx = idx[::step]
    out: dict = {"samples_in_motion": int(len(idx))}
    if len(idx) < 30:
        return out
    f = rest_forces(hx, rec["pose_cmd"][idx], payload_kg)
    sv = np.where(moving[idx], np.sign(v[idx]), np.nan)
    e = rec["following_error_mm"][idx]
    ones = np.ones_like(sv)
    Fe = np.stack([sv, v[idx], f * 1e-3, ones], axis=2)
    ce, se_e = _per_strut_fit(e, Fe)
    out["follow_compliance_mm_per_kN"], out["follow_compliance_se"] = ce[:, 2], se_e[:, 2]
    out["follow_friction_mm"], out["follow_friction_se"] = ce[:, 0], se_e[:, 0]
    if rec.available("torque_permille"):
        y = rec["torque_permille"][idx] * k_N_per_permille - f
        Ft = np.stack([sv, v[idx], ones], axis=2)
        ct, se_t = _per_strut_fit(y, Ft)
        out["friction_N"], out["friction_se_N"] = ct[:, 0], se_t[:, 0]
    return out


def _in_motion(rec, hx, model) -> dict:
    """Payload from the torques sampled while moving (drive torque TPDO3), when the recording has them."""
    v, a = strut_rates(rec)
    T = rec["torque_permille"].copy()
    T[unloaded(rec)] = np.nan          # drives disabled (a fault's stop) or about to be: they hold no load
    try:
        res = identify_payload_in_motion(hx, rec["pose_cmd"], T, v, a, model)
    except DataError as exc:
        return {"available": False, "reason": str(exc)}
    return {"available": True, "mass_kg": res.mass_kg, "mass_std_kg": res.mass_std_kg,
            "cog_platform_mm": res.cog_platform_mm.tolist(), "cog_std_mm": res.cog_std_mm.tolist(),
            "residual_rms_N": res.residual_rms_N, **res.extra}


def _payload_part(rec, hx, cfg, model, assumed, reference, windows) -> tuple[dict, list]:
    findings = []
    if not rec.available("torque_permille"):
        return {"available": False, "reason": "no drive torques (0x6077) in the recording"}, findings
    moving = _in_motion(rec, hx, model)
    if len(windows) < 4:
        return {"available": False, "reason": f"{len(windows)} rest poses (at least 4 needed)",
                "in_motion": moving}, findings
    P = np.array([rec["pose_cmd"][w].mean(axis=0) for w in windows])
    T = np.array([rec["torque_permille"][w].mean(axis=0) for w in windows])
    tare = None
    if reference is not None:
        rw = rest_windows(reference)
        if len(rw) >= 4 and reference.available("torque_permille"):
            tare = (np.array([reference["pose_cmd"][w].mean(axis=0) for w in rw]),
                    np.array([reference["torque_permille"][w].mean(axis=0) for w in rw]))
    # each rest's torque is a window mean: its noise averages over the window, its static friction does not
    model = dataclasses.replace(model, rest_samples=max(1, int(min(len(w) for w in windows))))
    res = identify_payload(hx, P, T, model, fit_offsets=tare is not None, tare=tare)
    out = {"available": True, "rest_poses": res.rest_poses, "tare_rest_poses": 0 if tare is None else len(tare[0]),
           "mass_kg": res.mass_kg, "mass_std_kg": res.mass_std_kg, "assumed_kg": assumed,
           "cog_platform_mm": res.cog_platform_mm.tolist(), "cog_std_mm": res.cog_std_mm.tolist(),
           "residual_rms_N": res.residual_rms_N,
           "torque_offsets": "fitted with the reference recording as tare" if tare is not None else
           "assumed zero (give --reference, a recording without the payload, to fit them)",
           "in_motion": moving}
    dm = res.mass_kg - assumed
    if abs(dm) > max(4.0 * res.mass_std_kg, 0.5):
        upd = carrier_update(cfg, res, assumed)
        out["proposed_update"] = upd
        findings.append({"cause": "payload_changed", "strut": None,
                         "evidence": {"mass_kg": res.mass_kg, "assumed_kg": assumed, "std_kg": res.mass_std_kg},
                         "message": f"payload {res.mass_kg:.2f} +- {res.mass_std_kg:.2f} kg at "
                                    f"{np.round(res.cog_platform_mm, 1).tolist()} mm (platform) where the sag "
                                    f"model assumes {assumed:g} kg: the sag compensation is wrong by "
                                    f"{upd['sag_change_at_home']['position_um']:.3g} um at home; update "
                                    f"[carrier] to mass_kg = {upd['carrier']['mass_kg']}"})
    return out, findings


def _thermal_part(rec: Recording, cfg) -> tuple[dict, list]:
    if not rec.available("temperature_C"):
        return {"available": False, "reason": "no temperatures in the recording"}, []
    T = rec["temperature_C"]
    L = rec["struts_act_mm"] if rec.available("struts_act_mm") else rec["struts_cmd_mm"]
    alpha = cfg.thermal.expansion_per_K
    T0 = cfg.thermal.reference_temperature_C
    expected = alpha * L * (T - T0)
    applied = rec["thermal_offsets_mm"] if rec.available("thermal_offsets_mm") else np.zeros_like(expected)
    gap = expected - applied
    gap = gap - np.nanmedian(gap[: max(1, len(gap) // 20)], axis=0)   # relative to the recording's start
    worst = float(np.nanmax(np.abs(gap)))
    dT = float(np.nanmax(np.nanmax(T, axis=0) - np.nanmin(T, axis=0)))
    out = {"available": True, "temperature_range_K": dT, "uncompensated_growth_max_mm": worst,
           "expansion_per_K": alpha}
    if worst > THERMAL_TOL_MM:
        i = int(np.nanargmax(np.nanmax(np.abs(gap), axis=0)))
        return out, [{"cause": "thermal_not_compensated", "strut": i + 1,
                      "evidence": {"temperature_range_K": dT, "uncompensated_growth_mm": worst},
                      "message": f"struts warmed by up to {dT:.2g} K; {worst * 1000:.3g} um of growth (strut {i + 1}) "
                                 "is not in the applied thermal offsets: thermal compensation off or lagging"}]
    return out, []


def analyse(cfg, rec: Recording, model: DriveTorqueModel | None = None, reference: Recording | None = None,
            assumed_payload_kg: float | None = None) -> dict:
    """Health report of one recording (optionally against a reference recording of the healthy machine)."""
    if rec.n < 10:
        raise DataError(f"{rec.meta.get('path', 'recording')}: {rec.n} samples, at least 10 needed")
    model = model or DriveTorqueModel()
    hx = Hexapod(cfg)
    if assumed_payload_kg is None:
        pl = rec["payload_kg"]
        assumed_payload_kg = float(np.nanmedian(pl)) if np.any(np.isfinite(pl)) else 0.0
    windows = rest_windows(rec)
    payload, findings = _payload_part(rec, hx, cfg, model, assumed_payload_kg, reference, windows)
    thermal, f2 = _thermal_part(rec, cfg)
    findings += f2
    k = model.force_N_per_permille
    sc = strut_coefficients(rec, hx, assumed_payload_kg, k)
    ref = strut_coefficients(reference, hx, assumed_payload_kg, k) if reference is not None else None
    findings += _strut_findings(sc, ref)
    have = payload.get("available") or thermal.get("available") or sc.get("samples_in_motion", 0) >= 30
    status = "insufficient_data" if not have else ("warning" if findings else "ok")
    return {"status": status, "warnings": [f["message"] for f in findings], "findings": findings,
            "causes": sorted({f["cause"] for f in findings}), "payload": payload, "thermal": thermal,
            "struts": {k_: (v.tolist() if isinstance(v, np.ndarray) else v) for k_, v in sc.items()},
            "rest_poses": len(windows), "samples": rec.n,
            "reference": None if reference is None else reference.meta.get("path", "given")}


def _strut_findings(sc: dict, ref: dict | None) -> list[dict]:
    out = []
    if "friction_N" in sc:
        vals, se = sc["friction_N"], sc["friction_se_N"]
        rv = ref.get("friction_N") if ref else None
        for i, v, r in _outliers(vals, se, rv, FRICTION_RATIO, None):
            out.append({"cause": "friction_changed", "strut": i + 1, "evidence": {"friction_N": v, "reference_N": r},
                        "message": f"strut {i + 1}: Coulomb friction {v:.3g} N against {r:.3g} N "
                                   f"({'reference recording' if rv is not None else 'the other struts'})"})
    elif "follow_friction_mm" in sc:
        vals, se = sc["follow_friction_mm"], sc["follow_friction_se"]
        rv = ref.get("follow_friction_mm") if ref else None
        for i, v, r in _outliers(vals, se, rv, FRICTION_RATIO, None):
            out.append({"cause": "friction_changed", "strut": i + 1, "evidence": {"follow_friction_mm": v,
                                                                                  "reference_mm": r},
                        "message": f"strut {i + 1}: following error against the motion {v * 1000:.3g} um "
                                   f"against {r * 1000:.3g} um: friction changed"})
    if "follow_compliance_mm_per_kN" in sc:
        vals, se = sc["follow_compliance_mm_per_kN"], sc["follow_compliance_se"]
        rv = ref.get("follow_compliance_mm_per_kN") if ref else None
        for i, v, r in _outliers(vals, se, rv, None, COMPLIANCE_MM_PER_KN):
            out.append({"cause": "stiffness_changed", "strut": i + 1,
                        "evidence": {"compliance_mm_per_kN": v, "reference": r},
                        "message": f"strut {i + 1}: following error grows with the strut force, {v:.3g} mm/kN "
                                   f"against {r:.3g}: stiffness changed (softer strut, worn joint)"})
    return out
