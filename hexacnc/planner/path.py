"""Path geometry of a program: blocks -> pieces (lines, helical arcs, corner blends).

Conventions
-----------
* Input blocks carry tool-tip poses ``[x, y, z, a, b, c]`` (mm / deg, machine =
  base frame).  Inside, angles are radians.
* The path parameter ``s`` is the tool-tip path length in mm; for a move that
  only rotates it is the angular distance ``|d(a, b, c)|`` in degrees (the feed
  is then read as deg/s, as LinuxCNC does for rotary-only moves).
* Orientation is interpolated **linearly in a, b, c** (each rotary axis moves
  linearly with the path, as on a 5-axis machine) - on lines and on arcs.
* Platform pose: ``t = tip - R(a, b, c) @ q_tool`` with the tool point
  ``q_tool = tip_platform_mm + tool_length_mm * axis_platform`` (platform frame).
* Corner blends: a quintic Hermite curve in (x, y, z, a, b, c) that joins the two
  trimmed segments with matching first and second derivatives in ``s`` (C2, so
  strut accelerations stay continuous); its deviation
  from the programmed path is bounded by the G64 P tolerance (mm for x, y, z and
  the same number in degrees for a, b, c), checked numerically on 17 points
  against the corresponding point of the programmed path (an upper bound of the
  distance to the path).

Piece kinds: 0 line, 1 arc, 2 blend, 3 spline (a smoothed short line of a CAM run, see
:mod:`hexacnc.planner.smooth`; a quintic like a blend).  Everything is vectorised over arrays of
(piece index, s).
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import PlanError
from ..kinematics import strut_lengths_batch
from ..pose import rotation_elements_batch
from ..gcode import blocks as B
from .blocktime import check_blocks
from .quintic import ARC, BLEND, LINE, NCOEF, SPLINE, pose_deviation, quintic_derivs  # noqa: F401 (re-exported)
from .quintic import quintic as _quintic
from .rawmoves import Raw, RawArrays, raw_arrays, raw_moves  # noqa: F401 (Raw, RawArrays, raw_moves re-exported)

_SQRT3 = math.sqrt(3.0)


def eval_raw(kind: np.ndarray, coef: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Tip pose (N,6) (mm, rad) at normalised parameters u (N,) for pieces given by kind (N,), coef (N,NCOEF)."""
    return eval_pieces(kind, coef, np.arange(u.shape[0]), u)


def eval_pieces(kind: np.ndarray, coef: np.ndarray, idx: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Tip poses (N,6) mm/rad of pieces ``idx`` (into kind (M,), coef (M,NCOEF)) at normalised u (N,).

    Only the coefficient columns a kind needs are gathered (memory bandwidth is the cost here).
    """
    return eval_pieces_multi(kind, coef, idx, [u])[0]


def eval_pieces_multi(kind: np.ndarray, coef: np.ndarray, idx: np.ndarray, us: list) -> list:
    """:func:`eval_pieces` at several parameter arrays ``us`` (each (N,)) of the same pieces ``idx``:
    the coefficients are gathered once.  Returns one (N,6) array per entry of ``us``."""
    outs = [np.empty((u.shape[0], 6)) for u in us]
    kd = kind[idx]
    m = np.nonzero(kd == LINE)[0]
    if m.size:
        ii = idx[m]
        c0 = coef[ii, 0:6]
        c1 = coef[ii, 6:12]
        for out, u in zip(outs, us):
            out[m] = c0 + u[m, None] * c1
    m = np.nonzero(kd == ARC)[0]
    if m.size:
        c = coef[idx[m], 0:22]
        for out, u in zip(outs, us):
            uu = u[m]
            r = c[:, 12] + c[:, 13] * uu
            ph = c[:, 14] * uu
            cp, sp = np.cos(ph), np.sin(ph)
            out[m, 0:3] = (c[:, 0:3] + (r * cp)[:, None] * c[:, 3:6] + (r * sp)[:, None] * c[:, 6:9]
                           + (c[:, 15] * uu)[:, None] * c[:, 9:12])
            out[m, 3:6] = c[:, 16:19] + uu[:, None] * c[:, 19:22]
    m = np.nonzero((kd == BLEND) | (kd == SPLINE))[0]
    if m.size:
        # quintic Hermite: coef = [P0, V0, A0, A1, V1, P1] (6 each) in the blend parameter w
        c = coef[idx[m]]
        for out, u in zip(outs, us):
            out[m] = _quintic(u[m][:, None], c)
    return outs


def eval_raw_derivs(kind: np.ndarray, coef: np.ndarray, u: np.ndarray):
    """Pose, d/du and d2/du2 (each (N,6), mm / rad) of lines, arcs and quintic pieces (analytic)."""
    n = u.shape[0]
    P = eval_raw(kind, coef, u)
    D1 = np.zeros((n, 6))
    D2 = np.zeros((n, 6))
    m = kind == LINE
    D1[m] = coef[m, 6:12]
    m = kind == ARC
    if m.any():
        c = coef[m]
        uu = u[m]
        r = c[:, 12] + c[:, 13] * uu
        ph = c[:, 14] * uu
        cp, sp = np.cos(ph)[:, None], np.sin(ph)[:, None]
        radial = cp * c[:, 3:6] + sp * c[:, 6:9]
        tang = -sp * c[:, 3:6] + cp * c[:, 6:9]
        dr, th = c[:, 13][:, None], c[:, 14][:, None]
        D1[m, 0:3] = dr * radial + (r[:, None] * th) * tang + c[:, 15][:, None] * c[:, 9:12]
        D1[m, 3:6] = c[:, 19:22]
        D2[m, 0:3] = 2 * dr * th * tang - (r[:, None] * th * th) * radial
    m = (kind == BLEND) | (kind == SPLINE)
    if m.any():
        D1[m], D2[m] = quintic_derivs(u[m], coef[m])
    return P, D1, D2


class Path:
    """The executed path: pieces with global ``s`` ranges.

    Arrays (M pieces): ``kind``, ``coef`` (M,NCOEF), ``s0`` (global start),
    ``slen`` (s-length of the piece), ``u0``/``uscale`` (piece-local parameter
    ``u = u0 + (s - s0) * uscale``), ``tool_point`` (M,3) platform frame,
    ``feed`` (s-units/s), ``rapid``, ``line``.
    """

    _FIELDS = (("kind", np.int8), ("coef", float), ("slen", float), ("u0", float), ("uscale", float),
               ("tool_mm", float), ("feed", float), ("rapid", bool), ("line", np.int64))

    def __init__(self, cfg, pieces, stops_after: dict[int, dict]):
        """``pieces``: a list of dicts, or a dict of arrays (M,), with the keys of ``_FIELDS``."""
        self.cfg = cfg
        for name, dt in self._FIELDS:
            v = pieces[name] if isinstance(pieces, dict) else [p[name] for p in pieces]
            setattr(self, name, np.asarray(v, dtype=dt))
        M = self.kind.shape[0]
        self.n = M
        self.coef = self.coef.reshape(M, NCOEF)
        self.s0 = np.concatenate([[0.0], np.cumsum(self.slen)[:-1]]) if M else np.zeros(0)
        axis = np.asarray(cfg.tool.axis_platform, dtype=float)
        tipp = np.asarray(cfg.tool.tip_platform_mm, dtype=float)
        self.tool_point = tipp[None, :] + self.tool_mm[:, None] * axis[None, :]
        self.total = float(self.s0[-1] + self.slen[-1]) if M else 0.0
        #: piece index -> stop/hold description at its end (see plan.py)
        self.stops_after = stops_after

    def piece_at(self, s: np.ndarray) -> np.ndarray:
        idx = np.searchsorted(self.s0, s, side="right") - 1
        return np.clip(idx, 0, self.n - 1)

    def tip(self, idx: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Tool-tip poses (N,6) mm/rad of pieces ``idx`` at global ``s`` (extrapolates outside the piece)."""
        u = self.u0[idx] + (s - self.s0[idx]) * self.uscale[idx]
        return eval_pieces(self.kind, self.coef, idx, u)

    def tips(self, idx: np.ndarray, ss: list) -> list:
        """:meth:`tip` at several position arrays ``ss`` (each (N,)) of the same pieces ``idx``."""
        u0, s0, sc = self.u0[idx], self.s0[idx], self.uscale[idx]
        return eval_pieces_multi(self.kind, self.coef, idx, [u0 + (s - s0) * sc for s in ss])

    def platform_struts(self, idx: np.ndarray, s: np.ndarray, plat: np.ndarray, base: np.ndarray):
        """(platform poses (N,6), strut lengths (N,6)) at ``s`` of pieces ``idx``."""
        return platform_struts(self.tip(idx, s), self.tool_point[idx], plat, base)

    def platform(self, idx: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Platform poses (N,6) mm/rad (tool tip converted through the tool point)."""
        P = self.tip(idx, s)
        return tip_to_platform(P, self.tool_point[idx])


#: the nine elements of ``Rz(c) Ry(b) Rx(a)`` as (N,) arrays (row-major), from (N,3) radians
rot_elems = rotation_elements_batch


def tip_to_platform(P: np.ndarray, q: np.ndarray, r=None) -> np.ndarray:
    """Platform poses from tip poses P (N,6) mm/rad and tool points q (N,3) platform frame.

    ``r``: :func:`rot_elems` of ``P[:, 3:]`` if already at hand (the platform has the same angles).
    """
    r = rot_elems(P[:, 3:]) if r is None else r
    out = P.copy()
    out[:, 0] -= r[0] * q[:, 0] + r[1] * q[:, 1] + r[2] * q[:, 2]
    out[:, 1] -= r[3] * q[:, 0] + r[4] * q[:, 1] + r[5] * q[:, 2]
    out[:, 2] -= r[6] * q[:, 0] + r[7] * q[:, 1] + r[8] * q[:, 2]
    return out


#: strut lengths (N,6) of platform poses (N,6) mm/rad: the kinematics core's batch inverse
strut_lengths = strut_lengths_batch


def platform_struts(P: np.ndarray, q: np.ndarray, plat: np.ndarray, base: np.ndarray):
    """(platform poses (N,6), strut lengths (N,6)) of tip poses P with tool points q: one rotation."""
    r = rot_elems(P[:, 3:])
    X = tip_to_platform(P, q, r)
    return X, strut_lengths(X, plat, base, r)


# ---------------------------------------------------------------------------
# building the path from blocks
# ---------------------------------------------------------------------------
STOP_EVENTS = (B.DWELL, B.PAUSE, B.OPTIONAL_PAUSE, B.END, B.SPINDLE, B.TOOL_CHANGE)


def _raw_at(kind, coef, slen, u):
    """Pose, d/ds, d2/ds2 of raw moves at normalised u (vectorised)."""
    Pp, D1, D2 = eval_raw_derivs(kind, coef, u)
    return Pp, D1 / slen[:, None], D2 / (slen * slen)[:, None]


def _blend_coefs(rk, rc, rl, ia, da, db):
    """Quintic Hermite blend coefficients (n, NCOEF) between raw ia and ia+1 trimmed by da / db."""
    ib = ia + 1
    Pa, Ta, Ka = _raw_at(rk[ia], rc[ia], rl[ia], 1.0 - da / rl[ia])
    Pb, Tb, Kb = _raw_at(rk[ib], rc[ib], rl[ib], db / rl[ib])
    D = (da + db)[:, None]
    return np.hstack([Pa, Ta * D, Ka * D * D, Kb * D * D, Tb * D, Pb])


def _blend_deviation(rk, rc, rl, ia, da, db):
    """Max deviation (mm for x, y, z; deg for a, b, c; the larger) of blends from the programmed path,
    measured against the point of the programmed path at the same s (an upper bound of the distance)."""
    nw = 17
    n = ia.shape[0]
    coef = _blend_coefs(rk, rc, rl, ia, da, db)
    w = np.linspace(0.0, 1.0, nw)
    W = np.tile(w, n)
    rep = np.repeat(np.arange(n), nw)
    Pb = _quintic(w[None, :, None], coef[:, None, :]).reshape(n * nw, 6)
    s = W * (da + db)[rep] - da[rep]
    onA = s <= 0
    ir = np.where(onA, ia[rep], ia[rep] + 1)
    u = np.where(onA, 1.0 + s / rl[ir], s / rl[ir])
    ref = eval_pieces(rk, rc, ir, u)
    return pose_deviation(Pb - ref).reshape(n, nw).max(axis=1)


def build_path(blocks, cfg) -> tuple[Path, list]:
    """Blocks -> :class:`Path` with corner blends; returns (path, events placed at piece indices).  Every block
    longer than ``[planner] max_block_s`` is refused once the blocks are checked, before anything is sampled
    (:func:`~hexacnc.planner.blocktime.check_blocks`)."""
    ra, events = raw_arrays(blocks, cfg)
    check_blocks(blocks, cfg)
    nr = ra.kind.shape[0]
    if nr == 0:
        return Path(cfg, [], {}), events
    axis = np.asarray(cfg.tool.axis_platform, dtype=float)
    tipp = np.asarray(cfg.tool.tip_platform_mm, dtype=float)
    stop_after_raw = set(i for i, blk in events if blk.kind in STOP_EVENTS)
    from .smooth import smooth_runs
    ra = smooth_runs(ra, stop_after_raw, cfg.planner.smooth_max_segment_mm)
    rk, rc, rl, tool, tol, exact = ra.kind, ra.coef, ra.slen, ra.tool_mm, ra.tolerance, ra.exact_stop
    qp = tipp[None, :] + tool[:, None] * axis[None, :]
    Pe, Te, _ = _raw_at(rk, rc, rl, np.ones(nr))
    Ps, Ts, _ = _raw_at(rk, rc, rl, np.zeros(nr))
    Xe = tip_to_platform(Pe, qp)
    Xs = tip_to_platform(Ps, qp)
    if nr > 1:
        gap = np.maximum(np.max(np.abs(Xe[:-1, :3] - Xs[1:, :3]), axis=1),
                         1e2 * np.max(np.abs(Xe[:-1, 3:] - Xs[1:, 3:]), axis=1))
        badj = np.nonzero(gap > 1e-6)[0]
        if badj.size:
            i = int(badj[0])
            raise PlanError(f"path is discontinuous: the move starts at platform pose "
                            f"{np.round(_deg(Xs[i + 1]), 6).tolist()} but the previous move (line {ra.line[i]}) "
                            f"ended at {np.round(_deg(Xe[i]), 6).tolist()}", line=int(ra.line[i + 1]),
                            limit="continuity", code="gcode")
    junction_stop = np.zeros(nr, dtype=bool)
    junction_stop[-1] = True
    blend_d = np.zeros((nr, 2))
    if nr > 1:
        ta, tb = Te[:-1], Ts[1:]
        dtan = tb - ta
        smooth = np.max(np.abs(dtan), axis=1) < 1e-7
        na = np.linalg.norm(ta[:, :3], axis=1)
        nb = np.linalg.norm(tb[:, :3], axis=1)
        cosang = np.einsum("ij,ij->i", ta[:, :3], tb[:, :3]) / np.maximum(na * nb, 1e-12)
        reverse = (na > 1e-9) & (nb > 1e-9) & (cosang < -0.996)
        jt = np.minimum(tol[:-1], tol[1:])
        forced = np.array([i in stop_after_raw for i in range(nr - 1)]) | exact[:-1] | (tool[:-1] != tool[1:])
        stop = forced | (~smooth & (reverse | (jt <= 0)))
        junction_stop[:-1] = stop
        cand = np.nonzero(~stop & ~smooth)[0]
        if cand.size:
            dx = np.linalg.norm(dtan[cand, :3], axis=1)
            dang = np.linalg.norm(np.degrees(dtan[cand, 3:]), axis=1)
            d = np.minimum(8.0 * jt[cand] / np.maximum(dx, 1e-12), 8.0 * jt[cand] / np.maximum(dang, 1e-12))
            da = np.minimum(d, 0.5 * rl[cand])
            db = np.minimum(d, 0.5 * rl[cand + 1])
            ok = np.zeros(cand.size, dtype=bool)
            for _ in range(30):
                todo = np.nonzero(~ok)[0]
                if todo.size == 0:
                    break
                dev = _blend_deviation(rk, rc, rl, cand[todo], da[todo], db[todo])
                good = dev <= jt[cand[todo]]
                ok[todo[good]] = True
                bad = todo[~good]
                da[bad] *= 0.6
                db[bad] *= 0.6
            fail = ~ok | (da < 1e-7) | (db < 1e-7)
            junction_stop[cand[fail]] = True
            good = cand[~fail]
            blend_d[good, 1] = da[~fail]
            blend_d[good + 1, 0] = db[~fail]
            bcoef = _blend_coefs(rk, rc, rl, good, da[~fail], db[~fail]) if good.size else np.zeros((0, NCOEF))
            bmap = {int(i): j for j, i in enumerate(good)}
        else:
            bmap = {}
    else:
        bmap = {}
    # pieces: every move (trimmed by its blends), each followed by its corner blend if any
    has_b = blend_d[:, 1] > 0
    mp = np.arange(nr) + np.concatenate([[0], np.cumsum(has_b)[:-1]])      # piece index of each move
    bi = np.nonzero(has_b)[0]                                               # moves followed by a blend
    bp = mp[bi] + 1
    M = nr + bi.size
    t0, t1 = blend_d[:, 0], blend_d[:, 1]
    pc = {name: np.zeros(M, dtype=dt) for name, dt in Path._FIELDS if name != "coef"}
    pc["coef"] = np.zeros((M, NCOEF))
    for name, v in (("kind", rk), ("coef", rc), ("slen", rl - t0 - t1), ("u0", t0 / rl), ("uscale", 1.0 / rl),
                    ("tool_mm", tool), ("feed", ra.feed), ("rapid", ra.rapid), ("line", ra.line)):
        pc[name][mp] = v
    if bi.size:
        D = t1[bi] + blend_d[bi + 1, 0]
        for name, v in (("kind", BLEND), ("coef", bcoef[[bmap[int(i)] for i in bi]]), ("slen", D), ("u0", 0.0),
                        ("uscale", 1.0 / D), ("tool_mm", tool[bi]), ("feed", np.minimum(ra.feed[bi], ra.feed[bi + 1])),
                        ("rapid", ra.rapid[bi] & ra.rapid[bi + 1]), ("line", ra.line[bi + 1])):
            pc[name][bp] = v
    pieces = pc
    stops_after: dict[int, dict] = {int(m): {"corner": True} for m in mp[junction_stop]}
    placed = [(int(mp[i]) if i >= 0 else -1, blk) for i, blk in events]
    return Path(cfg, pieces, stops_after), placed


def _deg(X: np.ndarray) -> np.ndarray:
    Y = np.array(X, dtype=float)
    Y[3:] = np.degrees(Y[3:])
    return Y


# ---------------------------------------------------------------------------
# derivative bounds for the check spacing
# ---------------------------------------------------------------------------
def piece_bounds(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per piece rigorous bounds in s: ``t1 >= |d tip/ds|``, ``t2 >= |d2 tip/ds2|``,
    ``a1 >= |d abc/ds|`` (rad per s-unit), ``a2 >= |d2 abc/ds2|``.  Returned as (t1, t2, a1, a2)."""
    M = path.n
    t1 = np.zeros(M)
    t2 = np.zeros(M)
    a1 = np.zeros(M)
    a2 = np.zeros(M)
    c = path.coef
    k = path.kind
    sc = path.uscale
    m = k == LINE
    t1[m] = np.linalg.norm(c[m, 6:9], axis=1) * sc[m]
    a1[m] = np.linalg.norm(c[m, 9:12], axis=1) * sc[m]
    m = k == ARC
    if m.any():
        r = np.maximum(np.abs(c[m, 12]), np.abs(c[m, 12] + c[m, 13]))
        th = np.abs(c[m, 14])
        dr = np.abs(c[m, 13])
        h = np.abs(c[m, 15])
        t1[m] = (th * r + dr + h) * sc[m]
        t2[m] = (th * th * r + 2 * th * dr) * sc[m] ** 2
        a1[m] = np.linalg.norm(c[m, 19:22], axis=1) * sc[m]
    m = (k == BLEND) | (k == SPLINE)
    if m.any():
        # Bernstein control points of the quintic: derivative bounds by the convex-hull property
        P0, V0, A0, A1, V1, P1 = (c[m, 6 * i:6 * i + 6] for i in range(6))
        Q = [P0, P0 + V0 / 5, P0 + 2 * V0 / 5 + A0 / 20, P1 - 2 * V1 / 5 + A1 / 20, P1 - V1 / 5, P1]
        d1 = [5 * (Q[i + 1] - Q[i]) for i in range(5)]
        d2 = [20 * (Q[i + 2] - 2 * Q[i + 1] + Q[i]) for i in range(4)]
        s1 = sc[m]
        t1[m] = np.max([np.linalg.norm(v[:, :3], axis=1) for v in d1], axis=0) * s1
        a1[m] = np.max([np.linalg.norm(v[:, 3:], axis=1) for v in d1], axis=0) * s1
        t2[m] = np.max([np.linalg.norm(v[:, :3], axis=1) for v in d2], axis=0) * s1 ** 2
        a2[m] = np.max([np.linalg.norm(v[:, 3:], axis=1) for v in d2], axis=0) * s1 ** 2
    return t1, t2, a1, a2


def sample_spacing(path: Path, plat: np.ndarray, Lmin: float, bound_mm: float):
    """Per piece: s spacing ``h`` and the bounds used.

    With ``q_i = p_i - q_tool`` the strut vector is ``s_i = tip + R q_i - b_i``;
    ``|omega| <= sqrt(3) |abc'|`` (columns of E are unit vectors),
    ``|omega'| <= 2 |abc'|^2 + sqrt(3) |abc''|``, so
    ``|L''| <= (t1 + W |q|)^2 / Lmin + t2 + (W' + W^2) |q| = M2``.
    Linear interpolation between samples ``h`` apart then errs by at most
    ``M2 h^2 / 8 <= sample_bound_mm``; joint angles move at most
    ``G = (t1 + W |q|) / Lmin + W`` rad per s-unit, so an angle between samples
    exceeds the larger sample value by at most ``G h / 2``.
    Returns (h, length_margin_mm, angle_margin_rad) per piece.
    """
    t1, t2, a1, a2 = piece_bounds(path)
    qn = np.max(np.linalg.norm(plat[None, :, :] - path.tool_point[:, None, :], axis=2), axis=1)
    W = _SQRT3 * a1
    W2 = 2 * a1 * a1 + _SQRT3 * a2
    sp = t1 + W * qn
    M2 = sp * sp / Lmin + t2 + (W2 + W * W) * qn
    h = np.sqrt(8.0 * bound_mm / np.maximum(M2, 1e-12))
    nint = np.maximum(1, np.ceil(path.slen / h - 1e-9)).astype(np.int64)
    h = path.slen / nint
    lmarg = M2 * h * h / 8.0
    G = sp / Lmin + W
    amarg = G * h / 2.0
    return h, nint, lmarg, amarg


def grid_offsets(path: Path, h: np.ndarray, nint: np.ndarray, grade: np.ndarray):
    """Check-grid points of every piece: uniform steps ``h`` (M,) (``nint`` (M,) intervals) plus the
    offsets ``grade`` from both piece ends that are below half the piece and below its step.

    Returns (pidx (N,), u (N,) s-offsets inside each piece, counts (M,)), sorted by piece then u;
    each piece's first point is 0 and its last ``slen`` (a zero-length piece keeps both); exact
    duplicates are removed from pieces that got end offsets.
    """
    M = path.n
    cu = nint.astype(np.int64) + 1
    start = np.concatenate([[0], np.cumsum(cu)[:-1]])
    pu = np.repeat(np.arange(M), cu)
    u = (np.arange(pu.shape[0]) - start[pu]) * h[pu]
    u[start + cu - 1] = path.slen
    ext = (grade[None, :] < 0.5 * path.slen[:, None]) & (grade[None, :] < h[:, None])
    pe, ge = np.nonzero(ext)
    if pe.size:
        p_all = np.concatenate([pu, pe, pe])
        u_all = np.concatenate([u, grade[ge], path.slen[pe] - grade[ge]])
        order = np.lexsort((u_all, p_all))
        p_all = p_all[order]
        u_all = u_all[order]
        keep = np.ones(p_all.shape[0], dtype=bool)
        keep[1:] = (p_all[1:] != p_all[:-1]) | (u_all[1:] != u_all[:-1]) | ~ext.any(axis=1)[p_all[1:]]
        pu = p_all[keep]
        u = u_all[keep]
    return pu, u, np.bincount(pu, minlength=M)
