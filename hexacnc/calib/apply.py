"""``hexacnc calib apply RESULT --config machine.toml --out calibrated.toml``.

Takes the calibrated keys of a fit result (a config written by ``calib fit --out``, ``calib run``
+ fit, or ``diagnose --out-config``; or a ``--out-calibration`` fragment) and puts them into the
machine's own description, everything else left as it is:

* ``[geometry] base_joints_mm, platform_joints_mm, strut_offset_mm``
* the whole ``[calibration]`` section (replaced: the fit started from raw drive readings)
* ``[struts] stiffness_N_per_mm`` and ``[thermal] expansion_per_K`` where the result has them

The new description is checked by the config loader before anything is written, written
atomically, an existing ``--out`` kept as ``--out.YYYYmmddTHHMMSS.bak``; the changes are
returned as readable lines (per joint: old -> new and the move in mm).
"""
from __future__ import annotations

import copy
import datetime as _dt
import shutil
import tomllib
from pathlib import Path

import numpy as np

from ..config import parse_config
from ..errors import ConfigError, DataError
from .measurements import atomic_write_text
from .output import dumps_toml

GEOMETRY_KEYS = ("base_joints_mm", "platform_joints_mm", "strut_offset_mm")
OTHER_KEYS = {"struts": ("stiffness_N_per_mm",), "thermal": ("expansion_per_K",)}


def _read(path) -> dict:
    p = Path(path)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise DataError(f"{p}: cannot read: {exc.strerror or exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise DataError(f"{p}: not valid TOML: {exc}") from exc


def _fmt(v) -> str:
    a = np.asarray(v, dtype=float)
    return "[" + ", ".join(f"{x:.4f}" for x in a.ravel()) + "]" if a.ndim else f"{float(a):.6g}"


def _diff_key(section: str, key: str, old, new) -> list[str]:
    if old is None:
        return [f"[{section}] {key}: (absent) -> {_fmt(new) if not isinstance(new, str) else new}"]
    if isinstance(old, str) or isinstance(new, str):
        return [] if old == new else [f"[{section}] {key}: {old!r} -> {new!r}"]
    o = np.asarray(old, dtype=float)
    n = np.asarray(new, dtype=float)
    if o.shape != n.shape:
        o = np.broadcast_to(o, n.shape) if o.size == 1 else o
    if o.shape == n.shape and np.allclose(o, n, rtol=0, atol=1e-12):
        return []
    if n.ndim == 2 and o.shape == n.shape:
        out = []
        for i, (a, b) in enumerate(zip(o, n)):
            d = float(np.linalg.norm(b - a))
            if d > 0:
                out.append(f"[{section}] {key} {i + 1}: {_fmt(a)} -> {_fmt(b)}  (moved {d * 1e3:.1f} um)")
        return out
    if n.ndim == 1 and o.shape == n.shape:
        return [f"[{section}] {key} {i + 1}: {a:.6g} -> {b:.6g}  ({b - a:+.6g})"
                for i, (a, b) in enumerate(zip(o, n)) if a != b]
    return [f"[{section}] {key}: {_fmt(old)} -> {_fmt(new)}"]


def merge(result: dict, machine: dict) -> tuple[dict, list[str]]:
    """The machine's document with the result's calibrated keys, and the readable changes."""
    new = copy.deepcopy(machine)
    lines: list[str] = []
    geo = result.get("geometry", {})
    for k in GEOMETRY_KEYS:
        if k in geo:
            lines += _diff_key("geometry", k, machine.get("geometry", {}).get(k), geo[k])
            new.setdefault("geometry", {})[k] = geo[k]
    for sec, keys in OTHER_KEYS.items():
        for k in keys:
            if k in result.get(sec, {}):
                lines += _diff_key(sec, k, machine.get(sec, {}).get(k), result[sec][k])
                new.setdefault(sec, {})[k] = result[sec][k]
    if "calibration" in result:
        old = machine.get("calibration", {})
        cal = result["calibration"]
        for k in sorted(set(old) | set(cal)):
            if k not in cal:
                lines.append(f"[calibration] {k}: removed (was {_fmt(old[k]) if not isinstance(old[k], str) else old[k]})")
            else:
                lines += _diff_key("calibration", k, old.get(k), cal[k])
        new["calibration"] = copy.deepcopy(cal)
    if not geo and "calibration" not in result:
        raise DataError("the result has neither [geometry] nor [calibration]: not a calibration result")
    return new, lines


def apply_result(result_path, config_path, out_path) -> dict:
    res = _read(result_path)
    res.pop("truth", None)
    machine = _read(config_path)
    new, lines = merge(res, machine)
    try:
        parse_config(copy.deepcopy(new), str(out_path))
    except ConfigError as exc:
        raise DataError(f"{result_path} applied to {config_path} does not make a valid machine description: "
                        f"{exc}") from exc
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    text = dumps_toml(new, f"{Path(config_path).name} with the calibration of {result_path} "
                           f"(hexacnc calib apply, {stamp})")
    out = Path(out_path)
    kept = None
    if out.exists():
        kept = f"{out}.{_dt.datetime.now():%Y%m%dT%H%M%S}.bak"
        shutil.copy2(out, kept)
    atomic_write_text(out, text)
    return {"out": str(out), "kept": kept, "changes": lines, "changed_keys": len(lines),
            "config": str(config_path), "result": str(result_path)}
