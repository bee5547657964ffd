"""Recordings of the cycle's signals (``hexacnc record``), readable by numpy and pandas.

A recording is a set of equally long arrays (one row per sample) and a metadata
map.  Two file forms, chosen by the extension:

* ``.npz`` (``numpy.load``): one array per signal below, plus ``meta_json``
  (a JSON string: rate, decimation, trigger, source, units);
* ``.csv`` (``pandas.read_csv(path)``, ``numpy.genfromtxt(path, delimiter=",", names=True)``):
  a header line, then one column per scalar signal and ``NAME_1..NAME_6`` for
  per-strut ones; the metadata in the sidecar ``PATH.meta.json``.

Signals (NaN where the source does not provide them):

=========================  =======  ==================================================
name                       shape    meaning
=========================  =======  ==================================================
``t_s``                    (N,)     sample time (s, from the first sample)
``struts_cmd_mm``          (N,6)    commanded strut lengths
``struts_act_mm``          (N,6)    actual strut lengths (drive feedback)
``following_error_mm``     (N,6)    commanded - actual
``torque_permille``        (N,6)    drive torque actual value (0x6077, per mille of rated)
``current_permille``       (N,6)    drive current actual value (0x6078, per mille of rated)
``temperature_C``          (N,6)    strut temperatures (probes or the thermal observer's estimate)
``thermal_offsets_mm``     (N,6)    thermal offsets the cycle applied
``pose_cmd``               (N,6)    commanded platform pose (mm, deg)
``pose_act``               (N,6)    platform pose from the actual struts (forward kinematics; mm, deg)
``fk_residual_mm``         (N,)     position distance between pose_cmd and pose_act
``payload_kg``             (N,)     payload the cycle's sag model assumes (NaN: unknown)
``t_loop_s``               (N,)     the daemon loop's time of each sample (status ``loop_time_s``: cycle
                                    count x period, from the first sample); the time base of the
                                    commanded values, free of the stream's delivery jitter (NaN: unknown)
``drives_enabled``         (N,)     1 when the drives were enabled (status ``drives_enabled``), 0 when not
                                    (a fault, disabled: the drives hold no load), NaN: unknown
=========================  =======  ==================================================
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DataError

STRUT_SIGNALS = ("struts_cmd_mm", "struts_act_mm", "following_error_mm", "torque_permille", "current_permille",
                 "temperature_C", "thermal_offsets_mm", "pose_cmd", "pose_act")
SCALAR_SIGNALS = ("t_s", "fk_residual_mm", "payload_kg", "t_loop_s", "drives_enabled")
SIGNALS = SCALAR_SIGNALS[:1] + STRUT_SIGNALS + SCALAR_SIGNALS[1:]
#: bound on a recording's length (samples): memory stays bounded whatever the duration asked
MAX_SAMPLES = 2_000_000


@dataclass
class Recording:
    data: dict                                   #: name -> array (N,) or (N,6)
    meta: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(len(self.data["t_s"]))

    def __getitem__(self, name: str) -> np.ndarray:
        return self.data[name]

    def available(self, name: str) -> bool:
        a = self.data.get(name)
        return a is not None and bool(np.any(np.isfinite(a)))


def sample_times(rec: Recording) -> np.ndarray:
    """The samples' times (s) to differentiate the commanded values over: the daemon loop's (``t_loop_s``)
    when every sample has it and it never goes back, else the recorder's clock ``t_s`` (which carries the
    delivery jitter of the status stream: under load tens of ms, so rates from it are noisy)."""
    t = rec.data.get("t_loop_s")
    if t is not None and len(t) == rec.n and rec.n > 1 and np.all(np.isfinite(t)) and np.all(np.diff(t) >= 0) \
            and t[-1] > t[0]:
        return t - t[0]
    return rec["t_s"]


def strut_rates(rec: Recording, name: str = "struts_cmd_mm") -> tuple[np.ndarray, np.ndarray]:
    """(N,6) velocity (mm/s) and acceleration (mm/s^2) of the strut signal ``name`` over
    :func:`sample_times`; samples of the same loop time (one status snapshot read twice) share the rates
    of its first reading."""
    t = sample_times(rec)
    L = rec[name]
    first = np.r_[True, np.diff(t) > 0]
    tu, Lu = t[first], L[first]
    if len(tu) < 3:
        z = np.zeros_like(L)
        return z, z.copy()
    v = np.gradient(Lu, tu, axis=0)
    a = np.gradient(v, tu, axis=0)
    idx = np.cumsum(first) - 1
    return v[idx], a[idx]


def empty_like_signals(n: int) -> dict:
    return {nm: np.full((n, 6) if nm in STRUT_SIGNALS else n, np.nan) for nm in SIGNALS}


def validate(rec: Recording, where: str) -> None:
    n = rec.n
    for nm in SIGNALS:
        a = rec.data.get(nm)
        if a is None:
            rec.data[nm] = np.full((n, 6) if nm in STRUT_SIGNALS else n, np.nan)
            continue
        want = (n, 6) if nm in STRUT_SIGNALS else (n,)
        if a.shape != want:
            raise DataError(f"{where}: signal {nm} has shape {a.shape}, expected {want}")


def save(path: str | os.PathLike, rec: Recording) -> None:
    """Write atomically (temporary file renamed): nothing half-written."""
    validate(rec, str(path))
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    try:
        if p.suffix == ".npz":
            with open(tmp, "wb") as f:
                np.savez(f, meta_json=np.array(json.dumps(rec.meta)), **{k: rec.data[k] for k in SIGNALS})
        elif p.suffix == ".csv":
            _save_csv(tmp, rec)
            side = p.with_name(p.name + ".meta.json")
            side_tmp = side.with_name(side.name + ".tmp")
            side_tmp.write_text(json.dumps(rec.meta, indent=1), encoding="utf-8")
            os.replace(side_tmp, side)
        else:
            raise DataError(f"{path}: recording files end in .npz or .csv")
        os.replace(tmp, p)
    finally:
        if tmp.exists():
            tmp.unlink()


def _columns() -> list[str]:
    cols = []
    for nm in SIGNALS:
        cols += [f"{nm}_{i + 1}" for i in range(6)] if nm in STRUT_SIGNALS else [nm]
    return cols


def _save_csv(path: Path, rec: Recording) -> None:
    M = np.column_stack([rec.data[nm] for nm in SIGNALS])
    with open(path, "w", encoding="utf-8") as f:
        f.write(",".join(_columns()) + "\n")
        for row in M:
            f.write(",".join("nan" if not np.isfinite(v) else f"{v:.9g}" for v in row) + "\n")


def load(path: str | os.PathLike) -> Recording:
    p = Path(path)
    if not p.exists():
        raise DataError(f"{path}: no such recording")
    if p.suffix == ".npz":
        try:
            z = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise DataError(f"{path}: not a readable .npz recording ({exc})") from None
        meta = json.loads(str(z["meta_json"])) if "meta_json" in z.files else {}
        if "t_s" not in z.files:
            raise DataError(f"{path}: no t_s array: not a hexacnc recording")
        rec = Recording({k: np.asarray(z[k], dtype=float) for k in z.files if k in SIGNALS}, meta)
    elif p.suffix == ".csv":
        rec = _load_csv(p)
    else:
        raise DataError(f"{path}: recording files end in .npz or .csv")
    validate(rec, str(path))
    return rec


def _load_csv(p: Path) -> Recording:
    meta, rows, header = {}, [], None
    side = p.with_name(p.name + ".meta.json")
    if side.exists():
        try:
            meta = json.loads(side.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise DataError(f"{side}: line {exc.lineno}, column {exc.colno}: {exc.msg}") from None
    with open(p, encoding="utf-8") as f:
        for ln, line in enumerate(f, start=1):
            s = line.strip()
            if not s:
                continue
            cells = s.split(",")
            if header is None:
                header = cells
                continue
            if len(cells) != len(header):
                raise DataError(f"{p}: line {ln}: {len(cells)} cells, the header has {len(header)}")
            try:
                rows.append([float(c) for c in cells])
            except ValueError:
                bad = next(i for i, c in enumerate(cells) if not _is_float(c))
                raise DataError(f"{p}: line {ln}, column {bad + 1} ({header[bad]}): {cells[bad]!r} is not a number") \
                    from None
            if len(rows) > MAX_SAMPLES:
                raise DataError(f"{p}: more than {MAX_SAMPLES} samples")
    if header is None or "t_s" not in header:
        raise DataError(f"{p}: no header with a t_s column: not a hexacnc recording")
    M = np.array(rows, dtype=float).reshape(len(rows), len(header))
    col = {h: i for i, h in enumerate(header)}
    data = {}
    for nm in SIGNALS:
        if nm in STRUT_SIGNALS:
            idx = [col.get(f"{nm}_{i + 1}") for i in range(6)]
            if all(i is not None for i in idx):
                data[nm] = M[:, idx]
        elif nm in col:
            data[nm] = M[:, col[nm]]
    return Recording(data, meta)


def _is_float(c: str) -> bool:
    try:
        float(c)
        return True
    except ValueError:
        return False
