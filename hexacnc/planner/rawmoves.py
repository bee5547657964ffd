"""Programmed moves before blending: G-code blocks -> raw lines and helical arcs as coefficient
arrays (tool tip, mm/rad), with their feeds, tolerances and exact-stop flags.

:func:`raw_arrays` is the vectorised builder the planner uses; :func:`raw_moves` the per-block
reference (and the path that names the first error). :mod:`hexacnc.planner.path` blends and
samples them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import PlanError
from ..gcode import blocks as B
from .quintic import ARC, LINE, NCOEF

_SQRT3 = math.sqrt(3.0)
_EPS_LEN = 1e-9


@dataclass
class Raw:
    """One programmed motion before blending (internal)."""
    kind: int
    line: int
    slen: float                 #: s-length (mm, or deg for rotary-only)
    coef: np.ndarray            #: (NCOEF,) geometry coefficients
    tool_mm: float
    feed: float                 #: s-units per second (upper bound)
    rapid: bool
    exact_stop: bool
    tolerance: float            #: blend tolerance (mm / deg)


def line_coef(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    c = np.zeros(NCOEF)
    c[0:6] = p0
    c[6:12] = p1 - p0
    return c


def arc_coef(blk, p0: np.ndarray, p1: np.ndarray) -> tuple[np.ndarray, float]:
    """Helical arc coefficients and s-length; raises PlanError on bad geometry."""
    ctr = np.asarray(blk.center, dtype=float)
    n = np.asarray(blk.normal, dtype=float)
    nn = float(np.linalg.norm(n))
    if ctr.shape != (3,) or n.shape != (3,) or nn < 1e-12 or not np.all(np.isfinite(ctr)):
        raise PlanError(f"arc with invalid centre {blk.center!r} or normal {blk.normal!r}", line=blk.line,
                        limit="arc geometry", code="gcode")
    n = n / nn
    v0 = p0[:3] - ctr
    h0 = float(v0 @ n)
    r0v = v0 - h0 * n
    r0 = float(np.linalg.norm(r0v))
    v1 = p1[:3] - ctr
    h1 = float(v1 @ n)
    r1v = v1 - h1 * n
    r1 = float(np.linalg.norm(r1v))
    if r0 < 1e-9 or r1 < 1e-9:
        raise PlanError("arc with zero radius (start or end on the centre)", line=blk.line,
                        limit="arc geometry", code="gcode")
    e1 = r0v / r0
    e2 = np.cross(n, e1)
    phi = math.atan2(float(r1v @ e2), float(r1v @ e1))
    turns = max(0, int(blk.turns or 0))
    if blk.clockwise:
        th = -((-phi) % (2 * math.pi))
        if th > -1e-9:
            th = -2 * math.pi
        th -= 2 * math.pi * turns
    else:
        th = phi % (2 * math.pi)
        if th < 1e-9:
            th = 2 * math.pi
        th += 2 * math.pi * turns
    c = np.zeros(NCOEF)
    c[0:3] = ctr + h0 * n
    c[3:6] = e1
    c[6:9] = e2
    c[9:12] = n
    c[12] = r0
    c[13] = r1 - r0
    c[14] = th
    c[15] = h1 - h0
    c[16:19] = p0[3:]
    c[19:22] = p1[3:] - p0[3:]
    rm = 0.5 * (r0 + r1)
    slen = math.hypot(abs(th) * rm, h1 - h0)
    if slen < _EPS_LEN:
        slen = float(np.linalg.norm(np.degrees(p1[3:] - p0[3:])))
    return c, slen


def pose_rad(v, what: str, line: int) -> np.ndarray:
    p = np.asarray(v, dtype=float)
    if p.shape != (6,) or not np.all(np.isfinite(p)):
        raise PlanError(f"{what} pose must be 6 finite numbers, got {v!r}", line=line, limit="input", code="gcode")
    p = p.copy()
    p[3:] = np.radians(p[3:])
    return p


# ---------------------------------------------------------------------------
# vectorised evaluation
# ---------------------------------------------------------------------------

def raw_moves(blocks, cfg) -> tuple[list, list]:
    """Motion blocks -> list of :class:`Raw`; events -> list of (index_of_preceding_raw, block).

    Zero-length moves are dropped; everything after an ``end`` block is ignored.
    """
    pc = cfg.planner
    rapid_feed = pc.rapid_feed_mm_min / 60.0
    default_feed = pc.default_feed_mm_min / 60.0
    raws: list[Raw] = []
    events: list[tuple[int, object]] = []
    for blk in blocks:
        kind = getattr(blk, "kind", None)
        line = int(getattr(blk, "line", 0) or 0)
        if kind in B.MOTION_KINDS:
            p0 = pose_rad(blk.start, "start", line)
            p1 = pose_rad(blk.end, "end", line)
            if kind == B.ARC:
                coef, slen = arc_coef(blk, p0, p1)
                k = ARC
            else:
                lx = float(np.linalg.norm(p1[:3] - p0[:3]))
                slen = lx if lx > _EPS_LEN else float(np.linalg.norm(np.degrees(p1[3:] - p0[3:])))
                coef = line_coef(p0, p1)
                k = LINE
            if slen < _EPS_LEN:
                continue
            if kind == B.RAPID:
                feed = rapid_feed
            elif blk.inverse_time_s is not None:
                if not blk.inverse_time_s > 0 or not math.isfinite(blk.inverse_time_s):
                    raise PlanError(f"inverse-time feed must give a positive time, got {blk.inverse_time_s!r}",
                                    line=line, limit="feed", code="gcode")
                feed = slen / float(blk.inverse_time_s)
            else:
                f = blk.feed_mm_s if blk.feed_mm_s is not None else default_feed
                if not f > 0 or not math.isfinite(f):
                    raise PlanError(f"feed must be positive, got {f!r} mm/s", line=line, limit="feed", code="gcode")
                feed = float(f)
            feed = min(feed, rapid_feed)
            tol = blk.blend_tolerance_mm if blk.blend_tolerance_mm is not None else pc.path_tolerance_mm
            raws.append(Raw(k, line, slen, coef, float(blk.tool_length_mm or 0.0), feed,
                            kind == B.RAPID, bool(blk.exact_stop), float(tol)))
        elif kind in (B.DWELL, B.PAUSE, B.OPTIONAL_PAUSE, B.END, B.SPINDLE, B.COOLANT, B.TOOL_CHANGE):
            events.append((len(raws) - 1, blk))
            if kind == B.END:
                break
        else:
            raise PlanError(f"unknown block kind {kind!r}", line=line, limit="input", code="gcode")
    return raws, events


@dataclass
class RawArrays:
    """The programmed motions before blending as arrays (n,) (``coef`` (n, NCOEF)); see :class:`Raw`."""
    kind: np.ndarray
    line: np.ndarray
    slen: np.ndarray
    coef: np.ndarray
    tool_mm: np.ndarray
    feed: np.ndarray
    rapid: np.ndarray
    exact_stop: np.ndarray
    tolerance: np.ndarray

    @classmethod
    def from_raws(cls, raws: list) -> "RawArrays":
        if not raws:
            return cls(*(np.zeros((0, NCOEF) if f == "coef" else 0, dtype=dt) for f, dt in (
                ("kind", np.int8), ("line", np.int64), ("slen", float), ("coef", float), ("tool_mm", float),
                ("feed", float), ("rapid", bool), ("exact_stop", bool), ("tolerance", float))))
        return cls(*(np.array([getattr(r, f) for r in raws], dtype=dt).reshape(len(raws), -1).squeeze(1)
                     if f != "coef" else np.array([r.coef for r in raws], dtype=float).reshape(len(raws), NCOEF)
                     for f, dt in (("kind", np.int8), ("line", np.int64), ("slen", float), ("coef", float),
                                   ("tool_mm", float), ("feed", float), ("rapid", bool), ("exact_stop", bool),
                                   ("tolerance", float))))


def _norms(v: np.ndarray) -> np.ndarray:
    """Row norms of v (n,k), bit for bit ``np.linalg.norm`` of each row (a batched dot product)."""
    return np.sqrt((v[:, None, :] @ v[:, :, None])[:, 0, 0])


def raw_arrays(blocks, cfg) -> tuple[RawArrays, list]:
    """:func:`raw_moves` as arrays, vectorised over the motion blocks.

    Any bad input (unknown kind, pose, feed, arc) hands over to :func:`raw_moves`, which raises the
    program's first error with its line.
    """
    pc = cfg.planner
    mot = []
    ev_at = []
    motion_kinds = B.MOTION_KINDS
    event_kinds = (B.DWELL, B.PAUSE, B.OPTIONAL_PAUSE, B.END, B.SPINDLE, B.TOOL_CHANGE, B.COOLANT)
    for blk in blocks:
        kind = getattr(blk, "kind", None)
        if kind in motion_kinds:
            mot.append(blk)
        elif kind in event_kinds:
            ev_at.append((len(mot) - 1, blk))
            if kind == B.END:
                break
        else:
            raws, events = raw_moves(blocks, cfg)          # raises the first error
            return RawArrays.from_raws(raws), events
    n = len(mot)
    if n == 0:
        return RawArrays.from_raws([]), [(-1, blk) for _, blk in ev_at]
    try:
        S = np.array([b.start for b in mot], dtype=float).reshape(n, -1)
        E = np.array([b.end for b in mot], dtype=float).reshape(n, -1)
        feed_in = np.array([b.feed_mm_s if b.feed_mm_s is not None else pc.default_feed_mm_min / 60.0
                            for b in mot], dtype=float)
        inv_t = np.array([b.inverse_time_s if b.inverse_time_s is not None else np.nan for b in mot], dtype=float)
        tool = np.array([b.tool_length_mm or 0.0 for b in mot], dtype=float)
        tol = np.array([b.blend_tolerance_mm if b.blend_tolerance_mm is not None else pc.path_tolerance_mm
                        for b in mot], dtype=float)
    except (TypeError, ValueError):
        S = E = None
    if S is None or S.shape != (n, 6) or E.shape != (n, 6) or not (np.all(np.isfinite(S)) and np.all(np.isfinite(E))):
        raws, events = raw_moves(blocks, cfg)
        return RawArrays.from_raws(raws), events
    kinds = [b.kind for b in mot]
    rapid = np.array([k == B.RAPID for k in kinds], dtype=bool)
    is_arc = np.array([k == B.ARC for k in kinds], dtype=bool)
    S[:, 3:] = np.radians(S[:, 3:])
    E[:, 3:] = np.radians(E[:, 3:])
    coef = np.zeros((n, NCOEF))
    coef[:, 0:6] = S
    coef[:, 6:12] = E - S
    lx = _norms(E[:, :3] - S[:, :3])
    slen = np.where(lx > _EPS_LEN, lx, _norms(np.degrees(E[:, 3:] - S[:, 3:])))
    kind = np.where(is_arc, ARC, LINE).astype(np.int8)
    try:
        for i in np.nonzero(is_arc)[0]:
            coef[i], slen[i] = arc_coef(mot[i], S[i], E[i])
    except PlanError:
        raws, events = raw_moves(blocks, cfg)
        return RawArrays.from_raws(raws), events
    keep = slen >= _EPS_LEN
    inv = ~rapid & np.isfinite(inv_t)
    with np.errstate(divide="ignore", invalid="ignore"):
        feed = np.where(rapid, pc.rapid_feed_mm_min / 60.0, np.where(inv, slen / np.where(inv, inv_t, 1.0), feed_in))
        feed = np.minimum(feed, pc.rapid_feed_mm_min / 60.0)
    check = keep & ~rapid
    if not (np.all((inv_t[check & inv] > 0)) and np.all(np.isfinite(inv_t[check & inv]))
            and np.all(feed_in[check & ~inv] > 0) and np.all(np.isfinite(feed_in[check & ~inv]))):
        raws, events = raw_moves(blocks, cfg)
        return RawArrays.from_raws(raws), events
    # events refer to the last kept move before them
    nkept = np.concatenate([[0], np.cumsum(keep)])
    events = [(int(nkept[i + 1]) - 1 if i >= 0 else -1, blk) for i, blk in ev_at]
    line = np.array([int(getattr(b, "line", 0) or 0) for b in mot], dtype=np.int64)
    exact = np.array([bool(b.exact_stop) for b in mot], dtype=bool)
    ra = RawArrays(kind[keep], line[keep], slen[keep], coef[keep], tool[keep], feed[keep], rapid[keep],
                   exact[keep], tol[keep])
    return ra, events


#: events that stop motion; coolant changes do not
