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


def calibrated_config_text(cfg, theta42: np.ndarray, header: str) -> str:
    """The machine description with calibrated geometry; checked by the config loader before return."""
    import copy
    doc = copy.deepcopy(cfg.raw)
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
