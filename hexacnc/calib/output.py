"""Output of calibration: calibrated config TOML, JSON, report directories (all atomic)."""
from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ..config import parse_config
from ..errors import ConfigError, DataError
from .measurements import atomic_write_text


def _toml_key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() else json.dumps(k)


def _toml_value(v, indent: str = "") -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ConfigError(f"cannot write non-finite value {v} to TOML")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, np.ndarray):
        return _toml_value(v.tolist(), indent)
    if isinstance(v, (list, tuple)):
        if v and all(isinstance(x, (list, tuple, np.ndarray)) for x in v):
            inner = ",\n".join(indent + "    " + _toml_value(x) for x in v)
            return "[\n" + inner + ",\n" + indent + "]"
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise ConfigError(f"cannot write {type(v).__name__} to TOML")


def dumps_toml(doc: dict, header: str = "") -> str:
    lines = [("# " + ln) if ln else "#" for ln in header.splitlines()]
    if lines:
        lines.append("")
    top = {k: v for k, v in doc.items() if not isinstance(v, dict)}
    for k, v in top.items():
        lines.append(f"{_toml_key(k)} = {_toml_value(v)}")

    def table(prefix: str, t: dict) -> None:
        scalars = {k: v for k, v in t.items() if not isinstance(v, dict)}
        subs = {k: v for k, v in t.items() if isinstance(v, dict)}
        lines.append("")
        lines.append(f"[{prefix}]")
        for k, v in scalars.items():
            lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
        for k, v in subs.items():
            table(f"{prefix}.{_toml_key(k)}", v)

    for k, v in doc.items():
        if isinstance(v, dict):
            table(_toml_key(k), v)
    return "\n".join(lines) + "\n"


#: causes the running cycle applies, and the config keys that carry them
APPLIED_IN_CYCLE = {
    "strut_scale": "[calibration] strut_scale",
    "strut_nonlinearity": "[calibration] strut_nonlinearity_mm (+ _center_mm, _half_range_mm)",
    "elastic_sag": "[struts] stiffness_N_per_mm = 1000 / compliance_mm_per_kN",
    "thermal_expansion": "[thermal] expansion_per_K (strut part; a frame expansion is not applied)",
    "elastic_sag_per_strut": "[struts] stiffness_N_per_mm = 1000 / compliance_i_mm_per_kN, one per strut",
}
#: causes the config cannot carry, and why
NOT_APPLIED = {
    "backlash": "direction-dependent offset: not compensated by the cycle (fix the mechanics or the drive's "
                "backlash compensation)",
    "session_offset": "strut offsets of later sessions: re-home; the written strut_offset_mm is the first session's",
    "joint_offset": "non-intersecting joint axes: not in the cycle's kinematic model",
    "thermal_expansion_per_strut": "[thermal] expansion_per_K is one coefficient for all struts",
}


def cause_config(res, causes) -> tuple[dict, dict, list[dict]]:
    """Config values of the fitted causes of ``res`` (a :class:`~hexacnc.calib.identify.FitResult`).

    Returns ``(sections, applied, not_applied)``: ``sections`` maps a config section to the
    keys to set (``calibration`` always present; identity when no strut-space cause was
    fitted), ``applied`` maps a cause to the keys carrying it, ``not_applied`` lists the
    fitted causes the cycle cannot apply, with the reason.
    """
    import re
    lay = res.layout
    scale = np.ones(6)
    coef = None
    sections: dict = {"calibration": {}}
    applied: dict = {}
    not_applied: list[dict] = []
    for c in causes:
        if c not in lay.causes:
            continue
        th = np.asarray(res.theta[lay.causes[c]], dtype=float)
        names = lay.cause_models[c].names
        if c == "strut_scale":
            scale = scale + th * 1e-6
            applied[c] = APPLIED_IN_CYCLE[c]
        elif c == "strut_nonlinearity":
            orders = {}
            for nm, v in zip(names, th):
                m = re.fullmatch(r"p(\d+)_strut(\d+)_mm", nm)
                orders[(int(m.group(1)), int(m.group(2)) - 1)] = float(v)
            deg = max(k for k, _ in orders)
            coef = np.zeros((6, deg))
            for (k, i), v in orders.items():
                coef[i, k - 1] = v
            ctx = res.evaluator.ctx
            sections["calibration"]["strut_nonlinearity_center_mm"] = [float(v) for v in ctx.q_center]
            sections["calibration"]["strut_nonlinearity_half_range_mm"] = [float(v) for v in ctx.q_half]
            applied[c] = APPLIED_IN_CYCLE[c]
        elif c == "elastic_sag":
            comp = float(th[0])
            if comp > 0:
                sections.setdefault("struts", {})["stiffness_N_per_mm"] = 1000.0 / comp
                applied[c] = APPLIED_IN_CYCLE[c]
            else:
                not_applied.append({"name": c, "reason": f"fitted compliance {comp:.4g} mm/kN is not positive"})
        elif c == "elastic_sag_per_strut":
            if np.all(th > 0):
                sections.setdefault("struts", {})["stiffness_N_per_mm"] = [float(1000.0 / v) for v in th]
                applied[c] = APPLIED_IN_CYCLE[c]
            else:
                not_applied.append({"name": c, "reason": f"a fitted compliance is not positive: "
                                                         f"{', '.join(f'{v:.4g}' for v in th)} mm/kN"})
        elif c == "thermal_expansion":
            alpha = float(th[0]) * 1e-6
            if 0.0 <= alpha <= 1e-3:
                sections.setdefault("thermal", {})["expansion_per_K"] = alpha
                applied[c] = APPLIED_IN_CYCLE[c]
            else:
                not_applied.append({"name": c, "reason": f"fitted expansion {alpha:.4g}/K is outside [0, 1e-3]"})
        else:
            not_applied.append({"name": c, "reason": NOT_APPLIED.get(c, "no config key")})
    cal = sections["calibration"]
    if np.any(scale != 1.0):
        cal["strut_scale"] = [float(v) for v in scale]
    if coef is not None:
        cal["strut_nonlinearity_mm"] = [[float(v) for v in row] for row in coef]
        cal = {k: cal[k] for k in ("strut_scale", "strut_nonlinearity_mm", "strut_nonlinearity_center_mm",
                                   "strut_nonlinearity_half_range_mm") if k in cal}
        sections["calibration"] = cal
    return sections, applied, not_applied


def calibration_fragment_text(sections: dict, source: str, date: str, header: str = "") -> str:
    """``[calibration]`` (and any other changed section) as a TOML fragment."""
    doc = {}
    for name, keys in sections.items():
        t = dict(keys)
        if name == "calibration":
            t = {"source": source, "date": date, **t}
        doc[name] = t
    return dumps_toml(doc, header)


def calibrated_config_text(cfg, theta42: np.ndarray, header: str, sections: dict | None = None,
                           source: str = "", date: str = "") -> str:
    """The machine description with calibrated geometry; checked by the config loader before return.

    ``sections`` (from :func:`cause_config`) sets cause keys; its ``calibration`` table replaces
    any ``[calibration]`` of ``cfg`` (the fit starts from raw drive readings, so an old
    calibration does not carry over).  Without ``sections`` the input's ``[calibration]`` is
    dropped too: the geometry was fitted as if the map were the identity.
    """
    import copy
    doc = copy.deepcopy(cfg.raw)
    doc.pop("calibration", None)
    for name, keys in (sections or {}).items():
        if name == "calibration":
            continue
        doc.setdefault(name, {}).update(keys)
    cal = dict((sections or {}).get("calibration", {}))
    if cal or source:
        doc["calibration"] = {"source": source or "hexacnc calib", "date": date, **cal}
    g = doc.setdefault("geometry", {})
    g["base_joints_mm"] = [[round(float(x), 6) for x in row] for row in np.asarray(theta42[:18]).reshape(6, 3)]
    g["platform_joints_mm"] = [[round(float(x), 6) for x in row] for row in np.asarray(theta42[18:36]).reshape(6, 3)]
    g["strut_offset_mm"] = [round(float(x), 6) for x in theta42[36:42]]
    text = dumps_toml(doc, header)
    import tomllib
    try:
        parse_config(tomllib.loads(text), "<calibrated>")
    except ConfigError as exc:
        raise DataError(f"the calibrated geometry does not make a valid machine description: {exc}") from exc
    return text


def write_json(path: str | os.PathLike, obj) -> None:
    atomic_write_text(path, json.dumps(to_jsonable(obj), indent=2, allow_nan=False) + "\n")


def to_jsonable(o):
    if isinstance(o, dict):
        return {str(k): to_jsonable(v) for k, v in o.items() if not str(k).startswith("_")}
    if isinstance(o, (list, tuple)):
        return [to_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return to_jsonable(o.tolist())
    if isinstance(o, (np.floating, float)):
        f = float(o)
        return f if math.isfinite(f) else None
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


class ReportDir:
    """Collect report files in a temp directory; ``commit`` moves them into place at once."""

    def __init__(self, target: str | os.PathLike):
        self.target = Path(target)
        if self.target.exists() and not self.target.is_dir():
            raise DataError(f"{self.target}: report path exists and is not a directory")
        parent = self.target.parent if str(self.target.parent) else Path(".")
        try:
            parent.mkdir(parents=True, exist_ok=True)
            self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.", dir=parent))
        except OSError as exc:
            raise DataError(f"{self.target}: cannot create report directory: {exc.strerror or exc}") from exc

    def path(self, name: str) -> Path:
        return self.tmp / name

    def commit(self) -> list[str]:
        self.target.mkdir(parents=True, exist_ok=True)
        names = sorted(os.listdir(self.tmp))
        for nm in names:
            os.replace(self.tmp / nm, self.target / nm)
        shutil.rmtree(self.tmp, ignore_errors=True)
        return [str(self.target / nm) for nm in names]

    def abort(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)


def _utc_now() -> str:
    import datetime as _dt
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def fit_config_texts(cfg, res, causes, source: str, header_lines: list[str]) -> dict:
    """Config text and [calibration] fragment of a fit (geometry + causes the cycle applies).

    Returns ``{"config", "fragment", "applied", "not_applied", "source", "date"}``; both texts are
    checked by the config loader (the fragment together with the fitted geometry).
    """
    date = _utc_now()
    sections, applied, not_applied = cause_config(res, causes)
    lines = list(header_lines)
    lines.append(f"calibrated {date} by: {source}")
    if applied:
        lines.append("applied in the cycle: " + "; ".join(f"{c} -> {k}" for c, k in applied.items()))
    for na in not_applied:
        lines.append(f"NOT applied: {na['name']}: {na['reason']}")
    lay = res.layout
    if lay.frame is not None:
        fr = res.theta[lay.frame]
        lines.append("measurement frame (instrument <- base; target in platform), mm/rad: "
                     + ", ".join(f"{n}={v:.6g}" for n, v in zip(lay.names[lay.frame], fr)))
    header = "\n".join(lines)
    text = calibrated_config_text(cfg, res.theta[:42], header, sections, source=source, date=date)
    frag = calibration_fragment_text(sections, source, date,
                                     header + "\nbelongs to the geometry fitted with it (same run)")
    return {"config": text, "fragment": frag, "applied": applied, "not_applied": not_applied,
            "source": source, "date": date, "sections": sections}


def extended_config_texts(cfg, diag, command: str) -> dict:
    """:func:`fit_config_texts` of a diagnosis' extended model (selected causes)."""
    r = diag.result
    causes = list(r.get("fitted_causes", [c["name"] for c in r["causes"]]))   # the validated model's
    fit = diag.extended.fit
    rms = r["extended"]["rms_fit"]
    data = r["data"]
    src = (f"{command}: causes {', '.join(causes) or 'none'} (" + (f"strut_nonlinearity degree "
                                                                     f"{diag.extended.nl_degree}; "
                                                                     if "strut_nonlinearity" in causes else "")
           + f"{data['rows']} rows)")
    lines = [f"extended model of hexacnc diagnose: verdict {r['verdict']}",
             f"fit RMS: position {rms['position_mm']} mm, orientation {rms['orientation_deg']} deg, "
             f"strut {rms['strut_mm']} mm"]
    ho = r["extended"]["rms_holdout"]
    if r.get("holdout"):
        lines.append(f"held-out RMS ({r['holdout']['rows_evaluated']} rows, first {r['holdout']['rereference_rows']} "
                     f"re-referenced): strut {ho['strut_mm']} mm, position {ho['position_mm']} mm")
    return fit_config_texts(cfg, fit, causes, src, lines)
