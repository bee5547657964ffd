"""Measurement sets: the CSV contract (docs/measurements.md), column mappings, atomic output.

A measurement set is one row per measured pose, rows in the order they were
taken:

* ``q1..q6`` drive readings, mm (required);
* any subset of ``x, y, z`` (mm), ``a, b, c`` (deg, ``R = Rz(c) Ry(b) Rx(a)``)
  or ``qx, qy, qz, qw`` (unit quaternion); an empty cell means "not measured";
* optional ``t_s``, ``session``, ``T_frame``, ``T_strut1..T_strut6``,
  ``T_spindle`` (deg C), ``payload_kg``.

Foreign layouts are read through a column mapping (TOML) that names, for each
contract column, the source column, a scale and an offset
(``value = raw * scale + offset``); see :func:`load_mapping`.
"""
from __future__ import annotations

import csv
import io
import math
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..csvio import atomic_write_bytes as _atomic_write_bytes
from ..errors import DataError
from ..pose import euler_from_matrix, matrix_from_quaternion

Q_COLS = tuple(f"q{i}" for i in range(1, 7))
POSE_COLS = ("x", "y", "z", "a", "b", "c")
QUAT_COLS = ("qx", "qy", "qz", "qw")
TSTRUT_COLS = tuple(f"T_strut{i}" for i in range(1, 7))
OPTIONAL_COLS = ("t_s", "session", "T_frame") + TSTRUT_COLS + ("T_spindle", "payload_kg", "flag")
#: every column the contract knows
KNOWN_COLS = Q_COLS + POSE_COLS + QUAT_COLS + OPTIONAL_COLS
#: mapping-file keys that are not columns
_MAP_SECTIONS = ("columns", "ignore", "constants", "description")


@dataclass
class ColumnMap:
    """Contract column -> (source column, scale, offset); source columns to ignore."""
    source: dict[str, tuple[str, float, float]]
    ignore: tuple[str, ...] = ()
    constants: dict[str, object] = field(default_factory=dict)
    path: str = "<mapping>"


def load_mapping(path: str | os.PathLike) -> ColumnMap:
    """Read a column mapping (TOML).

    ::

        [columns]
        q1 = { column = "leg_length_1", scale = 75.6920 }   # rev -> mm
        x  = "position_x"                                   # scale 1, offset 0
        qx = { column = "orientation_x" }
        [constants]          # optional: a value for every row
        session = "A"
        ignore = ["comment"] # optional, top level: source columns to skip
    """
    p = Path(path)
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise DataError(f"{p}: cannot read column mapping: {exc.strerror or exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise DataError(f"{p}: column mapping is not valid TOML: {exc}") from exc
    unknown = sorted(set(doc) - set(_MAP_SECTIONS))
    if unknown:
        raise DataError(f"{p}: unknown key(s) {', '.join(unknown)} in column mapping; "
                        f"known: {', '.join(_MAP_SECTIONS)}")
    cols = doc.get("columns")
    if not isinstance(cols, dict) or not cols:
        raise DataError(f"{p}: column mapping needs a [columns] table (contract column = source column)")
    source: dict[str, tuple[str, float, float]] = {}
    for key, spec in cols.items():
        if key not in KNOWN_COLS:
            raise DataError(f"{p}: [columns] {key}: not a measurement column; known: {', '.join(KNOWN_COLS)}")
        if isinstance(spec, str):
            source[key] = (spec, 1.0, 0.0)
            continue
        if not isinstance(spec, dict) or "column" not in spec:
            raise DataError(f"{p}: [columns] {key}: expected a source column name or "
                            f"{{ column = \"...\", scale = .., offset = .. }}, got {spec!r}")
        extra = sorted(set(spec) - {"column", "scale", "offset"})
        if extra:
            raise DataError(f"{p}: [columns] {key}: unknown option(s) {', '.join(extra)} (column, scale, offset)")
        col = spec["column"]
        scale = spec.get("scale", 1.0)
        offset = spec.get("offset", 0.0)
        for nm, v in (("scale", scale), ("offset", offset)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
                raise DataError(f"{p}: [columns] {key}: {nm} {v!r} is not a finite number")
        if not isinstance(col, str) or not col:
            raise DataError(f"{p}: [columns] {key}: column must be a non-empty string, got {col!r}")
        if key == "session" and (scale != 1.0 or offset != 0.0):
            raise DataError(f"{p}: [columns] session is a label; scale/offset do not apply")
        source[key] = (col, float(scale), float(offset))
    ignore = doc.get("ignore", [])
    if not isinstance(ignore, list) or not all(isinstance(s, str) for s in ignore):
        raise DataError(f"{p}: ignore must be a list of source column names, got {ignore!r}")
    consts = doc.get("constants", {})
    if not isinstance(consts, dict):
        raise DataError(f"{p}: [constants] must be a table")
    for k, v in consts.items():
        if k not in OPTIONAL_COLS and k not in POSE_COLS:
            raise DataError(f"{p}: [constants] {k}: only optional or pose columns can be constant")
        if k in source:
            raise DataError(f"{p}: {k} is both mapped in [columns] and set in [constants]")
    return ColumnMap(source, tuple(ignore), dict(consts), str(p))


@dataclass
class Measurements:
    """One measurement set (rows in the order taken).

    ``y`` (N,6): measured ``x,y,z`` mm and ``a,b,c`` deg, NaN where not
    measured (quaternions are converted to ``a,b,c``).
    """
    path: str
    q: np.ndarray                       #: (N,6) drive readings, mm
    y: np.ndarray                       #: (N,6) measured pose coordinates mm/deg, NaN = not measured
    t_s: np.ndarray | None = None       #: (N,)
    session: np.ndarray | None = None   #: (N,) str labels
    T_frame: np.ndarray | None = None   #: (N,) degC
    T_strut: np.ndarray | None = None   #: (N,6) degC
    T_spindle: np.ndarray | None = None
    payload_kg: np.ndarray | None = None
    lines: np.ndarray | None = None     #: (N,) source file line of each row

    @property
    def n(self) -> int:
        return int(self.q.shape[0])

    @property
    def mask(self) -> np.ndarray:
        """(N,6) True where a coordinate is measured."""
        return np.isfinite(self.y)

    @property
    def n_observations(self) -> int:
        return int(self.mask.sum())

    def full_pose_rows(self) -> np.ndarray:
        return np.all(self.mask, axis=1)

    def measured_names(self) -> list[str]:
        m = self.mask.any(axis=0)
        return [c for c, k in zip(POSE_COLS, m) if k]

    def sessions(self) -> list[str]:
        if self.session is None:
            return []
        seen: list[str] = []
        for s in self.session:
            if s not in seen:
                seen.append(str(s))
        return seen

    def subset(self, idx) -> "Measurements":
        idx = np.asarray(idx)

        def sel(a):
            return None if a is None else a[idx]
        return Measurements(self.path, self.q[idx], self.y[idx], sel(self.t_s), sel(self.session),
                            sel(self.T_frame), sel(self.T_strut), sel(self.T_spindle), sel(self.payload_kg),
                            sel(self.lines))

    def strut_temperatures(self) -> np.ndarray | None:
        """(N,6) strut temperatures: ``T_strut*`` where given, else ``T_frame`` for all six."""
        if self.T_strut is not None:
            T = self.T_strut.copy()
            if self.T_frame is not None:
                bad = ~np.isfinite(T)
                T[bad] = np.broadcast_to(self.T_frame[:, None], T.shape)[bad]
            return T
        if self.T_frame is not None:
            return np.repeat(self.T_frame[:, None], 6, axis=1)
        return None

    def direction(self) -> np.ndarray:
        """(N,6) approach direction of each strut (+1 extending, -1 retracting) from the row order.

        Row 0 (and a strut that did not move) inherits the previous direction;
        the first move is taken as approached from the retracted (home) side:
        +1.  Session boundaries restart from home.
        """
        d = np.ones((self.n, 6))
        prev = np.ones(6)
        for k in range(self.n):
            new_session = k == 0 or (self.session is not None and self.session[k] != self.session[k - 1])
            if new_session:
                prev = np.ones(6)
                d[k] = prev
                continue
            dq = self.q[k] - self.q[k - 1]
            cur = np.where(dq > 1e-9, 1.0, np.where(dq < -1e-9, -1.0, prev))
            d[k] = cur
            prev = cur
        return d


def _parse_float(cell: str, where: str) -> float:
    try:
        v = float(cell)
    except ValueError:
        raise DataError(f"{where}: {cell!r} is not a number") from None
    return v


def load_measurements(path: str | os.PathLike, mapping: ColumnMap | str | os.PathLike | None = None,
                      min_rows: int = 1) -> Measurements:
    """Read a measurement CSV (contract columns, or a foreign layout through ``mapping``).

    Errors (:class:`DataError`) name the file, the line and the column.
    """
    p = Path(path)
    if mapping is not None and not isinstance(mapping, ColumnMap):
        mapping = load_mapping(mapping)
    header, reader = _read_header(p)
    src, consts = _sources(p, header, mapping)
    has_quat = _check_columns(p, src, consts)
    rows, lines = _data_rows(p, reader, header)
    if len(rows) < min_rows:
        raise DataError(f"{p}: {len(rows)} data row(s); at least {min_rows} needed")
    tab = _Table(p, header, mapping, src, consts, rows, lines)
    q = np.column_stack([tab.column(c, True) for c in Q_COLS])
    y = np.full((tab.n, 6), np.nan)
    for i, c in enumerate(POSE_COLS):
        col = tab.column(c, False)
        if col is not None:
            y[:, i] = col
    if has_quat:
        _orientation_from_quaternions(p, tab, y)
    if not np.isfinite(y).any(axis=1).any():
        raise DataError(f"{p}: no row has a measured coordinate (all cells of x,y,z,a,b,c/qx..qw empty)")
    out = Measurements(str(p), q, y, lines=np.array(lines))
    _optional_columns(p, tab, out)
    return out


def _read_header(p: Path):
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise DataError(f"{p}: cannot read measurements: {exc.strerror or exc}") from exc
    except UnicodeDecodeError:
        raise DataError(f"{p}: not a UTF-8 text file") from None
    reader = csv.reader(io.StringIO(text))
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise DataError(f"{p}: empty file; expected a header with q1..q6 and measured coordinates") from None
    except csv.Error as exc:
        raise DataError(f"{p}: malformed CSV header: {exc}") from exc
    if len(set(header)) != len(header):
        dup = sorted({h for h in header if header.count(h) > 1})
        raise DataError(f"{p}: duplicate column(s) in header: {', '.join(dup)}")
    return header, reader


def _sources(p: Path, header: list[str], mapping: ColumnMap | None) -> tuple[dict, dict]:
    """contract column -> (header index, scale, offset); the mapping's constants."""
    src: dict[str, tuple[int, float, float]] = {}
    if mapping is None:
        unknown = [h for h in header if h not in KNOWN_COLS]
        if unknown:
            raise DataError(f"{p}: unknown column(s) {', '.join(unknown)}; known: {', '.join(KNOWN_COLS)} "
                            f"(a foreign layout needs a column mapping, --map)")
        for h in header:
            src[h] = (header.index(h), 1.0, 0.0)
        return src, {}
    used = set()
    for key, (col, sc, off) in mapping.source.items():
        if col not in header:
            raise DataError(f"{p}: column {col!r} (mapped to {key} by {mapping.path}) is not in the header "
                            f"({', '.join(header)})")
        src[key] = (header.index(col), sc, off)
        used.add(col)
    unknown = [h for h in header if h not in used and h not in mapping.ignore]
    if unknown:
        raise DataError(f"{p}: column(s) {', '.join(unknown)} not mapped by {mapping.path}; "
                        f"map them or list them under ignore")
    return src, mapping.constants


def _check_columns(p: Path, src: dict, consts: dict) -> bool:
    """Required and consistent columns; True when the orientation comes as a quaternion."""
    missing = [c for c in Q_COLS if c not in src]
    if missing:
        raise DataError(f"{p}: missing required drive reading column(s) {', '.join(missing)}")
    has_pose = [c for c in POSE_COLS if c in src or c in consts]
    has_quat = [c for c in QUAT_COLS if c in src]
    if has_quat and len(has_quat) != 4:
        raise DataError(f"{p}: quaternion needs all of qx, qy, qz, qw; missing "
                        f"{', '.join(c for c in QUAT_COLS if c not in has_quat)}")
    if has_quat and any(c in has_pose for c in "abc"):
        raise DataError(f"{p}: give the orientation either as a,b,c or as qx,qy,qz,qw, not both")
    if not has_pose and not has_quat:
        raise DataError(f"{p}: no measured coordinate column (x, y, z, a, b, c or qx..qw); "
                        f"nothing to calibrate against")
    return bool(has_quat)


def _data_rows(p: Path, reader, header: list[str]) -> tuple[list[list[str]], list[int]]:
    rows: list[list[str]] = []
    lines: list[int] = []
    try:
        for lineno, rec in enumerate(reader, start=2):
            if not rec or all(not c.strip() for c in rec):
                continue
            if len(rec) != len(header):
                raise DataError(f"{p}: line {lineno}: {len(rec)} fields, the header has {len(header)}")
            rows.append(rec)
            lines.append(lineno)
    except csv.Error as exc:
        raise DataError(f"{p}: malformed CSV: {exc}") from exc
    return rows, lines


class _Table:
    """The data rows of one file, read column by column (scale and offset of the mapping applied)."""

    def __init__(self, p, header, mapping, src, consts, rows, lines):
        self.p, self.header, self.mapping, self.src, self.consts = p, header, mapping, src, consts
        self.rows, self.lines, self.n = rows, lines, len(rows)

    def column(self, key: str, required: bool, label: bool = False):
        p, n, rows, lines = self.p, self.n, self.rows, self.lines
        if key in self.consts:
            v = self.consts[key]
            if label:
                return np.array([str(v)] * n, dtype=object)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise DataError(f"{self.mapping.path}: [constants] {key} = {v!r} is not a number")
            return np.full(n, float(v))
        if key not in self.src:
            return None
        j, sc, off = self.src[key]
        name = self.header[j] if self.mapping is None else f"{self.header[j]} (-> {key})"
        if label:
            out = np.array([r[j].strip() for r in rows], dtype=object)
            for k, s in enumerate(out):
                if not s:
                    raise DataError(f"{p}: line {lines[k]}, column {name}: empty session label")
            return out
        out = np.full(n, np.nan)
        for k, r in enumerate(rows):
            cell = r[j].strip()
            if not cell:
                if required:
                    raise DataError(f"{p}: line {lines[k]}, column {name}: empty (a drive reading is required)")
                continue
            v = _parse_float(cell, f"{p}: line {lines[k]}, column {name}")
            if not math.isfinite(v):
                raise DataError(f"{p}: line {lines[k]}, column {name}: {cell!r} is not finite "
                                f"(leave the cell empty for 'not measured')")
            out[k] = v * sc + off
        return out


def _orientation_from_quaternions(p: Path, tab: _Table, y: np.ndarray) -> None:
    Q = np.column_stack([tab.column(c, False) for c in QUAT_COLS])
    for k in range(tab.n):
        fin = np.isfinite(Q[k])
        if not fin.any():
            continue
        if not fin.all():
            raise DataError(f"{p}: line {tab.lines[k]}: quaternion partly empty (qx..qw must be all or none)")
        nq = float(np.linalg.norm(Q[k]))
        if abs(nq - 1.0) > 0.05:
            raise DataError(f"{p}: line {tab.lines[k]}: quaternion norm {nq:.4f} is not 1 (qx,qy,qz,qw)")
        a, b, c = euler_from_matrix(matrix_from_quaternion(Q[k]))
        y[k, 3:] = np.degrees([a, b, c])


def _optional_columns(p: Path, tab: _Table, out: Measurements) -> None:
    """Time, session, temperatures, payload: read and checked."""
    lines = tab.lines
    out.t_s = tab.column("t_s", False)
    out.session = tab.column("session", False, label=True)
    out.T_frame = tab.column("T_frame", False)
    Ts = [tab.column(c, False) for c in TSTRUT_COLS]
    if any(t is not None for t in Ts):
        if any(t is None for t in Ts):
            raise DataError(f"{p}: strut temperatures need all of T_strut1..T_strut6")
        out.T_strut = np.column_stack(Ts)
    out.T_spindle = tab.column("T_spindle", False)
    out.payload_kg = tab.column("payload_kg", False)
    for nm in ("t_s", "T_frame", "T_spindle", "payload_kg"):
        a = getattr(out, nm)
        if a is not None and not np.all(np.isfinite(a)):
            k = int(np.where(~np.isfinite(a))[0][0])
            raise DataError(f"{p}: line {lines[k]}, column {nm}: empty; give it in every row or drop the column")
    if out.T_strut is not None and not np.all(np.isfinite(out.T_strut)) and out.T_frame is None:
        k = int(np.where(~np.all(np.isfinite(out.T_strut), axis=1))[0][0])
        raise DataError(f"{p}: line {lines[k]}: a strut temperature is empty and there is no T_frame to fall back on")
    if out.payload_kg is not None and np.any(out.payload_kg < 0):
        k = int(np.where(out.payload_kg < 0)[0][0])
        raise DataError(f"{p}: line {lines[k]}, column payload_kg: negative mass {out.payload_kg[k]}")


def write_measurements(path: str | os.PathLike, m: Measurements, quaternion: bool = False) -> None:
    """Write a contract CSV (atomically).  Empty cells where not measured."""
    cols = list(Q_COLS) + list(POSE_COLS)
    data: list[np.ndarray] = [m.q[:, i] for i in range(6)] + [m.y[:, i] for i in range(6)]
    extra: list[tuple[str, np.ndarray]] = []
    for nm in ("t_s", "session", "T_frame"):
        v = getattr(m, nm)
        if v is not None:
            extra.append((nm, v))
    if m.T_strut is not None:
        extra += [(c, m.T_strut[:, i]) for i, c in enumerate(TSTRUT_COLS)]
    for nm in ("T_spindle", "payload_kg"):
        v = getattr(m, nm)
        if v is not None:
            extra.append((nm, v))
    cols += [c for c, _ in extra]
    data += [v for _, v in extra]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for k in range(m.n):
        row = []
        for v in data:
            x = v[k]
            if isinstance(x, str):
                row.append(x)
            elif x is None or (isinstance(x, float) and not math.isfinite(x)):
                row.append("")
            else:
                row.append(repr(float(x)))
        w.writerow(row)
    atomic_write_text(path, buf.getvalue())


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` through a temp file in the same directory and ``os.replace``."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Atomic write that also creates missing parent folders (report directories)."""
    _atomic_write_bytes(path, data, make_parents=True)
