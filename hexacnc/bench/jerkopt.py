"""Jerk-limited time optimum along a fixed path: the peer ``jerk_optimum`` of ``hexacnc bench plan``.

Independent of the planner's method (only its executed path and the strut kinematics are shared):
minimum time along the path from rest to rest subject to every strut's |v|, |a|, |jerk| limit, as a
nonlinear program over the path parameter solved by IPOPT (``casadi``, a bench extra, never a runtime
dependency).

Discretisation (direct multiple shooting on a fixed grid in ``s``): nodes ``s_0 < ... < s_N``; per node
the path speed ``v_k`` and acceleration ``a_k``; per interval a constant path jerk ``j_k`` and a free
duration ``T_k``, tied exactly by the triple integrator
``h_k = v_k T + a_k T^2/2 + j_k T^3/6``, ``v_{k+1} = v_k + a_k T + j_k T^2/2``, ``a_{k+1} = a_k + j_k T``.
Strut i at node k: ``|L'_i v| <= V_i``, ``|L''_i v^2 + L'_i a| <= A_i`` and for the jerk of both adjacent
intervals ``|L'''_i v^3 + 3 L''_i v a + L'_i j| <= J_i``.  Where pieces meet with a curvature step
(``L''`` jumps), the strut acceleration steps by ``dL''_i v^2``; sampled at the cycle period that reads as a
jerk ``dL''_i v^2 / dt``, so the step is bounded by ``J_i dt``.  Optional per-node path-speed bound
(feeds, angular velocity).  Objective ``sum T_k``.  ``L'``, ``L''``, ``L'''`` by central differences of
the exact inverse kinematics inside each piece.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from .jerkfloor import _sections

#: the message when casadi is missing
INSTALL = "the jerk-limited optimum needs casadi (IPOPT): pip install casadi, or pip install 'hexacnc[bench]'"
#: the bench's note on the ``jerk_optimum`` block
NOTE = ("minimum time along the executed path, rest to rest between the plan's rest points, under every strut's "
        "|v|, |a|, |jerk| limit (100 %) and the cycle-sampled curvature step |dL''| s_dot^2 <= j_max dt at piece "
        "junctions; multiple shooting over the path parameter (nodes every 0.25 mm, >= 6 per piece, >= 300 per "
        "section; constant path jerk per interval), IPOPT via casadi; jerk_optimum_ratio = hexacnc / optimum; "
        "utilisation: the optimum's trajectory sampled at the cycle period through exact inverse kinematics, "
        "finite differences (limits hold at the nodes: between them it may exceed slightly)")
#: grid step (mm) on long stretches and nodes per path piece (every piece's ends are nodes)
GRID_STEP_MM = 0.25
PIECE_NODES = 6
#: the shortest interval (mm) of the geometric grading towards a section's rest points
END_GRADE_MM = 1e-4
#: nodes at least per rest-to-rest section (the jerk switches at nodes: a coarse grid costs time)
MIN_SECTION_NODES = 300
#: cap on the nodes of one NLP (a longer section is solved with a coarser uniform step)
MAX_NODES = 6000


def have_casadi() -> bool:
    try:
        import casadi  # noqa: F401
    except ImportError:
        return False
    return True


@dataclasses.dataclass
class PathDerivs:
    """Strut derivatives on the nodes of a rest-to-rest section; ``*a`` arriving, ``*b`` departing
    (they differ where two pieces meet; elsewhere equal)."""
    s: np.ndarray                  #: (n,) node positions
    L1a: np.ndarray                #: (n, m) dL/ds arriving
    L2a: np.ndarray
    L3a: np.ndarray
    L1b: np.ndarray                #: departing
    L2b: np.ndarray
    L3b: np.ndarray
    sd_max: np.ndarray | None = None   #: (n,) path-speed bound (inf: none)


@dataclasses.dataclass
class Optimum:
    duration_s: float
    s: np.ndarray                  #: node positions
    v: np.ndarray                  #: path speed at the nodes
    a: np.ndarray                  #: path acceleration at the nodes
    j: np.ndarray                  #: path jerk per interval
    T: np.ndarray                  #: interval durations
    status: str
    iterations: int
    solve_s: float


def one_axis(d_mm: float, nodes: int = 400) -> PathDerivs:
    """A 1-DOF problem: one 'strut' equal to the path parameter over ``d_mm`` (for checks against Ruckig)."""
    s = np.linspace(0.0, float(d_mm), nodes + 1)
    one = np.ones((s.shape[0], 1))
    zero = np.zeros((s.shape[0], 1))
    return PathDerivs(s, one, zero, zero, one, zero, zero)


def section_derivs(path, hx, a: float, b: float, step_mm: float = GRID_STEP_MM,
                   piece_nodes: int = PIECE_NODES, sd_max_fn=None) -> PathDerivs:
    """Nodes on [a, b] of the executed path (every piece's ends, ``piece_nodes`` intervals per piece, at
    most ``step_mm`` apart) and the strut derivatives there, each side of a piece boundary from its own
    piece.  ``sd_max_fn(s, piece)`` -> path-speed bound (optional)."""
    from ..planner import path as P
    m = np.nonzero((path.s0 < b) & (path.s0 + path.slen > a))[0]
    m = m[path.slen[m] > 0]
    pieces, ss = [], []
    for i in m:
        lo, hi = max(a, float(path.s0[i])), min(b, float(path.s0[i] + path.slen[i]))
        if hi - lo <= 1e-12:
            continue
        n = max(piece_nodes, int(np.ceil((hi - lo) / step_mm)))
        si = np.linspace(lo, hi, n + 1)
        # geometric nodes towards the rest points (the motion starts and ends with short intervals)
        end_g = np.geomspace(END_GRADE_MM, step_mm, 10)[:-1]
        extra = [a + end_g[a + end_g < hi]] if lo == a else []
        extra += [b - end_g[b - end_g > lo]] if hi == b else []
        if extra:
            si = np.unique(np.concatenate([si] + extra))
        ss.append(si)
        pieces.append(np.full(si.shape[0], i))
    s_all = np.concatenate(ss)
    p_all = np.concatenate(pieces)
    # derivatives inside each piece: central differences with a step well inside the piece
    d = np.minimum(1e-3, path.slen[p_all] / 16.0)
    L = [P.strut_lengths(path.platform(p_all, s_all + k * d), hx.plat, hx.base) for k in (-2, -1, 0, 1, 2)]
    dc = d[:, None]
    L1 = (L[3] - L[1]) / (2 * dc)
    L2 = (L[3] - 2 * L[2] + L[1]) / (dc * dc)
    L3 = (L[4] - 2 * L[3] + 2 * L[1] - L[0]) / (2 * dc ** 3)
    sd = None if sd_max_fn is None else np.asarray(sd_max_fn(s_all, p_all), dtype=float)
    # one node per boundary: arriving derivatives from the piece before, departing from the piece after
    first = np.concatenate([[True], p_all[1:] != p_all[:-1]])
    last = np.concatenate([first[1:], [True]])
    node_b = np.nonzero(~last)[0]                        # every node but each piece's last ...
    node_b = np.append(node_b, s_all.size - 1)           # ... and the section's end
    node_a = node_b.copy()
    fb = first[node_b] & (node_b > 0)
    node_a[fb] = node_b[fb] - 1                          # a piece's first node arrives on the previous piece
    node_b[-1] = node_a[-1] = s_all.size - 1
    sdm = None if sd is None else np.minimum(sd[node_a], sd[node_b])
    return PathDerivs(s_all[node_b], L1[node_a], L2[node_a], L3[node_a], L1[node_b], L2[node_b], L3[node_b], sdm)


def _guess(pd: PathDerivs, V, A, J) -> tuple:
    """A start: half the velocity-limited speed, ramped from/to rest by the jerk limit, consistent T."""
    s = pd.s
    with np.errstate(divide="ignore"):
        vl = np.min(np.where(np.abs(pd.L1b) > 1e-12, V[None] / np.abs(pd.L1b), np.inf), axis=1)
        jl = np.min(np.where(np.abs(pd.L1b) > 1e-12, J[None] / np.abs(pd.L1b), np.inf), axis=1)
        al = np.min(np.where(np.abs(pd.L1b) > 1e-12, A[None] / np.abs(pd.L1b), np.inf), axis=1)
    vl = np.minimum(vl, 1e6)
    if pd.sd_max is not None:
        vl = np.minimum(vl, pd.sd_max)
    dist = np.minimum(s - s[0], s[-1] - s)
    jr = float(np.min(jl))
    ar = float(np.min(al))
    ramp = np.minimum((dist * jr ** 0.5) ** (2.0 / 3.0) * 0.5, np.sqrt(np.maximum(dist, 0) * ar))
    v = 0.3 * np.minimum(np.minimum.accumulate(vl[::-1])[::-1].clip(max=np.inf), vl)
    v = np.minimum(v, ramp)
    v[0] = v[-1] = 0.0
    h = np.diff(s)
    T = 2 * h / np.maximum(v[:-1] + v[1:], 1e-9)
    a = np.zeros_like(v)
    a[1:-1] = (v[2:] - v[:-2]) / np.maximum(T[1:] + T[:-1], 1e-12)
    jj = np.diff(a) / np.maximum(T, 1e-12)
    return v, a, jj, T


def solve(pd: PathDerivs, vmax, amax, jmax, cycle_s: float | None = 0.0005, guess=None,
          max_iter: int = 3000, tol: float = 1e-9, accel_jumps: bool = False,
          jerk_by_terms: bool = False) -> Optimum:
    """Minimum-time rest-to-rest traversal of the section ``pd`` under strut limits (each (m,)).

    ``accel_jumps``: the path acceleration may jump where two pieces meet (TOPP-RA's model, for checks with
    the jerk limit lifted); otherwise it is continuous (a finite jerk).
    ``jerk_by_terms``: each strut's three jerk terms are bounded by their magnitudes,
    ``|L'''| v^3 + 3 |L''| v |a| + |L'| |j| <= J`` (four smooth constraints, one per sign of ``a`` and ``j``),
    instead of by their signed sum: the optimum of any planner that keeps the terms within the limit one by
    one, as a second-order speed profile under a jerk filter does."""
    import casadi as ca
    t0 = time.perf_counter()
    V, A, J = (np.asarray(x, dtype=float).reshape(-1) for x in (vmax, amax, jmax))
    n = pd.s.shape[0]
    N = n - 1
    h = np.diff(pd.s)
    if np.any(h <= 0):
        raise ValueError("nodes must be strictly increasing")
    # scales: a speed, time, acceleration and jerk typical of the section
    vg, ag, jg, Tg = guess if guess is not None else _guess(pd, V, A, J)
    vs = max(float(np.max(vg)), 1e-6)
    ts = float(np.median(Tg))
    as_ = vs / max(ts, 1e-12) * 0.1 + 1e-12
    as_ = max(as_, float(np.max(np.abs(ag))) or 1.0)
    js = max(float(np.max(np.abs(jg))), as_ / ts)
    v = ca.SX.sym("v", n)
    a = ca.SX.sym("a", n)
    j = ca.SX.sym("j", N)
    T = ca.SX.sym("T", N)
    V_, A_, J_, T_ = v * vs, a * as_, j * js, T * ts
    # arriving path acceleration: A_ (departing) unless it may jump at a junction
    junc = np.nonzero(np.any(np.abs(pd.L2b - pd.L2a) > 1e-9, axis=1) | np.any(pd.L1b != pd.L1a, axis=1))[0]
    junc = junc[(junc > 0) & (junc < n - 1)] if accel_jumps else junc[:0]
    da = ca.SX.sym("da", int(junc.size))
    Aa = ca.SX(A_)
    for q, k in enumerate(junc.tolist()):
        Aa[k] = A_[k] + da[q] * as_
    v0, v1, a0, j0, T0 = V_[:-1], V_[1:], A_[:-1], J_, T_
    g = [(v0 * T0 + a0 * T0 ** 2 / 2 + j0 * T0 ** 3 / 6 - ca.DM(h)) / ca.DM(h),
         (v1 - (v0 + a0 * T0 + j0 * T0 ** 2 / 2)) / vs,
         (Aa[1:] - (a0 + j0 * T0)) / as_]
    lbg = [np.zeros(N)] * 3
    ubg = [np.zeros(N)] * 3
    m = pd.L1a.shape[1]
    for i in range(m):
        for L1, L2, AA in ((pd.L1a[:, i], pd.L2a[:, i], Aa), (pd.L1b[:, i], pd.L2b[:, i], A_)):
            g.append(ca.DM(L1) * V_ / V[i])
            g.append((ca.DM(L2) * V_ ** 2 + ca.DM(L1) * AA) / A[i])
            lbg += [-np.ones(n)] * 2
            ubg += [np.ones(n)] * 2
        # jerk of the interval before a node (arriving derivatives) and after it (departing)
        for L1, L2, L3, sl, AA in ((pd.L1a[1:, i], pd.L2a[1:, i], pd.L3a[1:, i], slice(1, n), Aa),
                                   (pd.L1b[:-1, i], pd.L2b[:-1, i], pd.L3b[:-1, i], slice(0, N), A_)):
            vv, aa, jv = V_[sl], AA[sl], J_
            if jerk_by_terms:
                for sa, sj in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                    g.append((ca.DM(np.abs(L3)) * vv ** 3 + 3 * ca.DM(np.abs(L2)) * vv * (sa * aa)
                              + ca.DM(np.abs(L1)) * (sj * jv)) / J[i])
                    lbg.append(np.full(N, -np.inf))
                    ubg.append(np.ones(N))
                continue
            g.append((ca.DM(L3) * vv ** 3 + 3 * ca.DM(L2) * vv * aa + ca.DM(L1) * jv) / J[i])
            lbg.append(-np.ones(N))
            ubg.append(np.ones(N))
        step = np.abs(pd.L2b[:, i] - pd.L2a[:, i])
        kk = np.nonzero(step > 1e-9)[0]
        if kk.size and cycle_s and not accel_jumps:
            g.append(ca.DM(step[kk]) * V_[kk.tolist()] ** 2 / (J[i] * cycle_s))
            lbg.append(np.zeros(kk.size))
            ubg.append(np.ones(kk.size))
    x = ca.vertcat(v, a, j, T, da)
    lbv = np.zeros(n)
    ubv = np.full(n, np.inf)
    if pd.sd_max is not None:
        ubv = np.minimum(ubv, pd.sd_max / vs)
    lbv[[0, -1]] = ubv[[0, -1]] = 0.0
    lba = np.full(n, -np.inf)
    uba = np.full(n, np.inf)
    lba[[0, -1]] = uba[[0, -1]] = 0.0
    nj = int(junc.size)
    lbx = np.concatenate([lbv, lba, np.full(N, -np.inf), np.full(N, 1e-9 / ts), np.full(nj, -np.inf)])
    ubx = np.concatenate([ubv, uba, np.full(N, np.inf), np.full(N, np.inf), np.full(nj, np.inf)])
    x0 = np.concatenate([vg / vs, ag / as_, jg / js, Tg / ts, np.zeros(nj)])
    nlp = {"x": x, "f": ca.sum1(T) / max(N, 1), "g": ca.vertcat(*g)}
    opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.max_iter": max_iter, "ipopt.tol": tol,
            "ipopt.acceptable_tol": 1e-7, "ipopt.mu_strategy": "adaptive", "ipopt.sb": "yes"}
    S = ca.nlpsol("jerkopt", "ipopt", nlp, opts)
    r = S(x0=x0, lbx=lbx, ubx=ubx, lbg=np.concatenate(lbg), ubg=np.concatenate(ubg))
    st = S.stats()
    xo = np.asarray(r["x"]).reshape(-1)
    vo, ao = xo[:n] * vs, xo[n:2 * n] * as_
    jo, To = xo[2 * n:2 * n + N] * js, xo[2 * n + N:2 * n + 2 * N] * ts
    return Optimum(float(np.sum(To)), pd.s.copy(), vo, ao, jo, To, str(st.get("return_status")),
                   int(st.get("iter_count", 0)), time.perf_counter() - t0)


def sample(opt: Optimum, dt: float) -> np.ndarray:
    """Path positions of the optimum's trajectory at times 0, dt, 2 dt, ... (the end held)."""
    tk = np.concatenate([[0.0], np.cumsum(opt.T)])
    t = np.arange(int(np.ceil(tk[-1] / dt)) + 1) * dt
    k = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, opt.T.shape[0] - 1)
    tau = np.clip(t - tk[k], 0.0, opt.T[k])
    s = opt.s[k] + opt.v[k] * tau + opt.a[k] * tau ** 2 / 2 + opt.j[k] * tau ** 3 / 6
    return np.clip(np.maximum.accumulate(s), opt.s[0], opt.s[-1])


def utilisation(path, hx, cfg, opts: list) -> dict:
    """Peak strut |v|, |a|, |jerk| over the limits of the optimum's trajectory (each section sampled at the
    cycle period, three rest samples either side, exact inverse kinematics, finite differences at the
    cycle period), as the bench measures TOPP-RA's and hexacnc's tables."""
    from ..planner import path as P
    dt = float(cfg.cycle.period_s)
    lim = [np.asarray(x, dtype=float) for x in (cfg.max_velocity_mm_s, cfg.max_acceleration_mm_s2,
                                                   cfg.max_jerk_mm_s3)]
    peak = np.zeros(3)
    for o in opts:
        s = sample(o, dt)
        s = np.clip(s, o.s[0] + 1e-9, o.s[-1] - 1e-9)
        L = P.strut_lengths(path.platform(path.piece_at(s), s), hx.plat, hx.base)
        L = np.vstack([np.repeat(L[:1], 3, axis=0), L, np.repeat(L[-1:], 3, axis=0)])
        for k in range(3):
            L = np.diff(L, axis=0) / dt
            peak[k] = max(peak[k], float(np.max(np.abs(L) / lim[k][None])))
    return {"velocity": float(peak[0]), "acceleration": float(peak[1]), "jerk": float(peak[2])}


def section_step(a: float, b: float, step_mm: float = GRID_STEP_MM) -> float:
    """The node step (mm) on the section [a, b]: ``step_mm``, finer on a short section (MIN_SECTION_NODES at
    least), coarser on a long one (MAX_NODES at most)."""
    return max(min(step_mm, (b - a) / MIN_SECTION_NODES), (b - a) / MAX_NODES)


def jerk_optimum(plan, cfg, sections, step_mm: float = GRID_STEP_MM, piece_nodes: int = PIECE_NODES,
                 jerk_scale: float = 1.0, accel_jumps: bool = False, shares=(1.0, 1.0, 1.0),
                 jerk_by_terms: bool = False) -> dict:
    """The jerk-limited optimum on the rest-to-rest ``sections`` [(a, b)] of the plan's executed path under
    the strut limits of ``cfg`` (jerk times ``jerk_scale``; velocity, acceleration and jerk times ``shares``):
    total time, per-section times and solver status, the trajectory's measured utilisation."""
    path, hx = plan.path, plan.hexapod
    vmax = np.asarray(cfg.max_velocity_mm_s, dtype=float) * float(shares[0])
    amax = np.asarray(cfg.max_acceleration_mm_s2, dtype=float) * float(shares[1])
    jmax = np.asarray(cfg.max_jerk_mm_s3, dtype=float) * jerk_scale * float(shares[2])
    t0 = time.perf_counter()
    opts = []
    for a, b in sections:
        pd = section_derivs(path, hx, a, b, section_step(a, b, step_mm), piece_nodes)
        opts.append(solve(pd, vmax, amax, jmax, cycle_s=float(cfg.cycle.period_s), accel_jumps=accel_jumps,
                          jerk_by_terms=jerk_by_terms))
    total = float(sum(o.duration_s for o in opts))
    return {"duration_s": total, "sections": opts, "solve_s": time.perf_counter() - t0,
            "ok": all(o.status in ("Solve_Succeeded", "Solved_To_Acceptable_Level") for o in opts),
            "nodes": int(sum(o.s.shape[0] for o in opts))}


#: the planner's own shares of the strut limits (v, a, j): the nominal plan uses at most these (plan.py, profile.py)
PLAN_SHARES = (0.995, 0.95, 0.95)


def jerk_optimum_report(plan, cfg, stops, at_shares: bool = False, by_terms: bool = False) -> dict:
    """The jerk-limited optimum (:mod:`hexacnc.bench.jerkopt`) on the plan's rest-to-rest sections; with
    ``at_shares`` also the optimum under the planner's own shares of the limits (``PLAN_SHARES``), which
    splits hexacnc's gap into the shares' part and the profile method's part; with ``by_terms`` also the
    optimum with each strut's jerk terms bounded one by one (``solve(jerk_by_terms=True)``): the best any
    planner can do that does not let the terms cancel, and the part of the gap that cancellation is worth; with
    both, also the optimum with the terms bounded one by one at the planner's shares (``by_terms_at_shares_cost``:
    the least ratio to the optimum that any planner keeping each term and the plan's headroom can reach)."""
    if not have_casadi():
        return {"skipped": INSTALL}
    r = jerk_optimum(plan, cfg, _sections(stops))
    opt = r["duration_s"]
    extra = {}

    def variant(name: str, cost_key: str, **kw) -> None:
        """One more optimum on the same sections: ``jerk_optimum_<name>_s`` / ``_ratio``, its cost against the
        optimum, ``<name>_solver_ok``."""
        rv = jerk_optimum(plan, cfg, _sections(stops), **kw)
        o = rv["duration_s"]
        extra.update({f"jerk_optimum_{name}_s": round(o, 6), f"jerk_optimum_{name}_ratio": round(plan.duration_s / o, 6),
                      cost_key: round(o / opt, 6), f"{name}_solver_ok": rv["ok"]})

    if at_shares:
        extra["shares"] = list(PLAN_SHARES)
        variant("at_shares", "shares_cost", shares=PLAN_SHARES)
    if by_terms:
        variant("by_terms", "by_terms_cost", jerk_by_terms=True)
    if at_shares and by_terms:
        # both at once: the floor of every planner that keeps each term within its limit and the plan's headroom
        variant("by_terms_at_shares", "by_terms_at_shares_cost", shares=PLAN_SHARES, jerk_by_terms=True)
    return {**extra, "jerk_optimum_s": round(opt, 6), "jerk_optimum_ratio": round(plan.duration_s / opt, 6),
            "within_8_percent": bool(plan.duration_s <= 1.08 * opt),
            "utilisation": {k: round(v, 6) for k, v in utilisation(plan.path, plan.hexapod, cfg,
                                                                     r["sections"]).items()},
            "solver_ok": r["ok"], "statuses": sorted({o.status for o in r["sections"]}),
            "nodes": r["nodes"], "solve_s": round(r["solve_s"], 2), "note": NOTE}
