"""Planner speed-ups that must not change the plan: condition-number bound, vectorised grid,
incremental verification passes (seeded paths)."""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.kinematics import Hexapod
from hexacnc.planner import path as P
from hexacnc.planner import limits as LI
from hexacnc.planner import plan as PL
from hexacnc.planner import verify as VF


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def test_condition_bound_is_an_upper_bound_and_exact_where_inconclusive():
    rng = np.random.default_rng(7)
    J = rng.normal(size=(4000, 6, 6))
    J[:50, 5] = J[:50, 4] + 1e-7 * rng.normal(size=(50, 6))      # near-singular
    J[50:60, 5] = J[50:60, 4]                                     # singular
    sv = np.linalg.svd(J, compute_uv=False)
    with np.errstate(divide="ignore"):
        exact = sv[:, 0] / sv[:, -1]
    for limit in (10.0, 1e3, 1e6):
        c = LI.condition_numbers(J, limit)
        passed = c <= limit
        # the verdict is the exact one, and every returned value bounds the true condition number
        assert np.array_equal(passed, exact <= limit)
        assert np.all(c[passed] >= exact[passed] * (1 - 1e-9))
        # inconclusive bound: the eigenvalue value (accurate while cond^2 is well above 1e-16)
        over = ~passed & (exact < 1e6)
        if limit < 1e5:
            assert over.sum() > 10
        assert np.allclose(c[over], exact[over], rtol=1e-6)
    assert not np.any(LI.condition_numbers(J[50:60], 1e3) <= 1e3)


def test_grid_offsets_match_per_piece_reference(cfg):
    from hexacnc.gcode.blocks import Block
    rng = np.random.default_rng(3)
    home = np.array(cfg.home_pose, dtype=float)
    tip = home.copy()
    tip[:3] += np.asarray(cfg.tool.tip_platform_mm)
    pts = [tip + np.r_[rng.uniform(-5, 5, 3) * (10 ** rng.uniform(-2, 1, 3)), rng.uniform(-1, 1, 3)]
           for _ in range(60)]
    blocks = [Block("line", i + 1, pts[i], pts[i + 1], feed_mm_s=30.0, blend_tolerance_mm=0.05)
              for i in range(len(pts) - 1)]
    path, _ = P.build_path(blocks, cfg)
    hx = Hexapod(cfg)
    h, nint, _, _ = P.sample_spacing(path, hx.plat, float(np.min(hx.min_length)), 0.001)
    ref = []
    for m in range(path.n):
        L_m = float(path.slen[m])
        u = np.arange(int(nint[m]) + 1) * float(h[m])
        u[-1] = L_m
        ext = PL.GRADE_MM[(PL.GRADE_MM < 0.5 * L_m) & (PL.GRADE_MM < h[m])]
        if ext.size:
            u = np.unique(np.concatenate([u, ext, L_m - ext]))
        ref.append(u)
    pidx, u, counts = P.grid_offsets(path, h, nint, PL.GRADE_MM)
    assert np.array_equal(u, np.concatenate(ref))
    assert np.array_equal(counts, [r.shape[0] for r in ref])
    assert np.array_equal(pidx, np.repeat(np.arange(path.n), counts))


def _topp_problem(seed: int, n: int = 3000):
    from hexacnc.planner.topp import accel_coefficients
    rng = np.random.default_rng(seed)
    s = np.cumsum(rng.uniform(0.002, 0.05, n))
    Lp = np.sin(s[:, None] * rng.uniform(0.5, 3, 6) + rng.uniform(0, 6, 6)) * rng.uniform(0.2, 1, 6)
    Lpp = np.cos(s[:, None] * rng.uniform(0.5, 3, 6)) * rng.uniform(0.0, 30, 6)
    Lp[rng.integers(0, n, 20), 2] = 0.0                      # struts standing still along the path
    h = np.diff(s)
    h[rng.integers(0, n - 1, 15)] = 0.0                      # duplicated junction points
    c, e, d, xmvc = accel_coefficients(Lp, Lpp, np.full(6, 5000.0))
    xlim = np.minimum(xmvc, rng.uniform(100, 2e4, n))
    xlim[rng.integers(0, n, 8)] = 0.0                        # stops
    xlim[0] = xlim[-1] = 0.0
    return h, c, e, d, xlim, rng


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_wavefront_topp_is_the_sequential_pass_bit_for_bit(seed):
    from hexacnc.planner.topp import forward_backward
    from hexacnc.planner.toppvec import WavefrontTopp
    h, c, e, d, xlim, rng = _topp_problem(seed)
    w = WavefrontTopp(h, c, e, d)
    x = w.solve(xlim)
    assert np.array_equal(x, forward_backward(h, xlim, c, e, d))
    assert x.max() > 0
    xl = xlim.copy()
    for _ in range(4):
        ranges = []
        for _ in range(int(rng.integers(1, 12))):
            a = int(rng.integers(0, xl.shape[0] - 40))
            b = a + int(rng.integers(0, 40))
            xl[a:b + 1] *= rng.uniform(0.2, 1.0)
            ranges.append((a, b))
        xw = w.solve_ranges(xl, ranges)
        assert np.array_equal(xw, forward_backward(h, xl, c, e, d))


def _program(cfg, seed: int):
    from hexacnc.gcode.blocks import Block
    rng = np.random.default_rng(seed)
    tip = np.array(cfg.home_pose, dtype=float)
    tip[:3] += np.asarray(cfg.tool.tip_platform_mm)
    out = []
    ln = 1
    for i in range(80):
        nxt = tip.copy()
        r = rng.uniform()
        if r < 0.1:
            pass                                                  # zero-length move (dropped)
        elif r < 0.2:
            nxt[3:] += rng.uniform(-2, 2, 3)                      # rotary only
        else:
            nxt[:3] += rng.uniform(-3, 3, 3)
        kw = dict(feed_mm_s=float(rng.uniform(5, 50)), blend_tolerance_mm=0.05,
                  exact_stop=bool(rng.uniform() < 0.05), tool_length_mm=float(rng.choice([0.0, 0.0, 10.0])))
        if rng.uniform() < 0.2:
            kw["inverse_time_s"] = float(rng.uniform(0.1, 2))
        if rng.uniform() < 0.15:
            out.append(Block("rapid", ln, tip, nxt))
        elif rng.uniform() < 0.15 and np.linalg.norm(nxt[:2] - tip[:2]) > 0.5:
            ctr = 0.5 * (tip[:3] + nxt[:3])
            ctr[2] = tip[2]
            out.append(Block("arc", ln, tip, nxt, center=ctr, normal=np.array([0.0, 0.0, 1.0]),
                             clockwise=bool(rng.uniform() < 0.5), **kw))
        else:
            out.append(Block("line", ln, tip, nxt, **kw))
        ln += 1
        if rng.uniform() < 0.08:
            out.append(Block(str(rng.choice(["dwell", "coolant", "spindle"])), ln, seconds=0.1))
            ln += 1
        tip = nxt
    return out


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_vectorised_raw_moves_equal_the_block_loop(cfg, seed):
    blocks = _program(cfg, seed)
    ref, ev_ref = P.raw_moves(blocks, cfg)
    ra, ev = P.raw_arrays(blocks, cfg)
    want = P.RawArrays.from_raws(ref)
    for f in ("kind", "line", "slen", "coef", "tool_mm", "feed", "rapid", "exact_stop", "tolerance"):
        assert np.array_equal(getattr(ra, f), getattr(want, f)), f
    assert [(i, b.line) for i, b in ev] == [(i, b.line) for i, b in ev_ref]
    assert ra.kind.shape[0] < sum(b.kind in ("line", "arc", "rapid") for b in blocks)   # zero-length dropped


@pytest.mark.parametrize("field,value", [("feed_mm_s", -1.0), ("end", [0.0, 1.0]), ("inverse_time_s", 0.0),
                                         ("end", [float("nan")] * 6), ("kind", "spline")])
def test_vectorised_raw_moves_raise_the_first_error_with_its_line(cfg, field, value):
    from hexacnc.errors import PlanError
    blocks = _program(cfg, 5)
    moves = [b for b in blocks if b.kind == "line" and np.linalg.norm(b.end - b.start) > 0
             and b.inverse_time_s is None]
    setattr(moves[7], field, value)
    with pytest.raises(PlanError) as ref:
        P.raw_moves(blocks, cfg)
    with pytest.raises(PlanError) as got:
        P.build_path(blocks, cfg)
    assert (got.value.line, got.value.limit, str(got.value)) == (ref.value.line, ref.value.limit, str(ref.value))
    assert got.value.line == moves[7].line


def _dynamic_program(cfg, seed: int, n: int = 120):
    """Short blended moves at a high feed (dynamics-bound, several verification passes)."""
    from hexacnc.gcode.blocks import Block
    rng = np.random.default_rng(seed)
    tip = np.array(cfg.home_pose, dtype=float)
    tip[:3] += np.asarray(cfg.tool.tip_platform_mm)
    out = []
    for i in range(n):
        nxt = tip.copy()
        nxt[:3] += rng.uniform(-1.5, 1.5, 3)
        nxt[3:] += rng.uniform(-0.3, 0.3, 3)
        out.append(Block("line", i + 1, tip, nxt, feed_mm_s=250.0, blend_tolerance_mm=0.05))
        tip = nxt
    return out


@pytest.mark.parametrize("seed", [11, 12])
def test_incremental_passes_give_the_plan_of_full_passes(cfg, seed, monkeypatch):
    """The verification loop re-solves the TOPP only where limits changed and evaluates the model
    only where a bound exceeds a violation threshold; re-solving everything and evaluating every
    moving sample in every pass must give the same plan."""
    blocks = _dynamic_program(cfg, seed)
    fast = PL.plan_program(blocks, cfg)
    assert fast.iterations >= 3                       # several passes, so incremental ones happened
    from hexacnc.planner.toppvec import WavefrontTopp
    monkeypatch.setattr(WavefrontTopp, "solve_ranges", lambda self, xlim, ranges, **kw: self.solve(xlim))
    monkeypatch.setattr(PL, "MODEL_SCREEN", (0.0, 0.0, 0.0))
    full = PL.plan_program(blocks, cfg)
    assert full.iterations == fast.iterations
    assert full.duration_s == pytest.approx(fast.duration_s, rel=1e-9)
    assert full.utilisation == fast.utilisation
    assert np.array_equal(full.s_tab, fast.s_tab)
    assert max(fast.utilisation.values()) <= 1.0


@pytest.mark.parametrize("seed", [0, 4])
def test_lean_accel_coefficients_equal_topp_ones(seed):
    from hexacnc.planner import topp, toppvec
    rng = np.random.default_rng(seed)
    Lp = rng.normal(size=(500, 6))
    Lpp = rng.normal(size=(500, 6)) * 40
    Lp[rng.integers(0, 500, 30), rng.integers(0, 6, 30)] = 0.0
    Lpp[rng.integers(0, 500, 10), rng.integers(0, 6, 10)] = 0.0
    amax = rng.uniform(1e3, 1e4, 6)
    for a, b in zip(toppvec.accel_coefficients(Lp, Lpp, amax), topp.accel_coefficients(Lp, Lpp, amax)):
        assert np.array_equal(a, b)


def test_interval_screen_finds_exactly_the_samples_above_threshold():
    rng = np.random.default_rng(9)
    sg = np.cumsum(rng.uniform(0.0, 0.2, 400))
    sg[rng.integers(1, 399, 30)] = sg[rng.integers(1, 399, 30)]
    sg = np.sort(sg)
    sg[0] = 0.0
    sg[50] = sg[51]                                                  # duplicated junction point
    s_f = np.sort(np.concatenate([rng.uniform(0, sg[-1], 3000), np.full(40, sg[120]), [sg[-1]] * 5]))
    s_f[0] = 0.0
    sd, sdd, sddd = (rng.normal(size=s_f.shape[0]) * k for k in (50.0, 3e3, 1e5))
    Lp, Lpp, Lppp = (rng.normal(size=(sg.shape[0], 6)) * k for k in (1.0, 0.1, 0.01))
    b = VF._Bounds(Lp, Lpp, Lppp, np.full(6, 300.0), np.full(6, 1e4), np.full(6, 1e6))
    g = np.clip(np.searchsorted(sg, s_f, side="right") - 1, 0, sg.shape[0] - 2)
    uv, ua, uj, _, _, _ = b.at(g, sd, sdd, sddd, extras=False)
    for thr in ((0.1, 0.2, 0.3), (0.5, 0.5, 0.5), (0.0, 0.0, 0.0)):
        want = np.nonzero((uv > thr[0]) | (ua > thr[1]) | (uj > thr[2]))[0]
        idx, gi, bv, ba, bj = VF._screen_intervals(sg, s_f, sd, sdd, sddd, b, thr)
        assert np.array_equal(idx, want) and np.array_equal(gi, g[want])
        assert np.array_equal(bv, uv[want]) and np.array_equal(ba, ua[want]) and np.array_equal(bj, uj[want])
        assert 0 < want.size


def test_exact_measurement_does_not_depend_on_its_chunking(cfg, monkeypatch):
    blocks = _dynamic_program(cfg, 13, n=60)
    ref = PL.plan_program(blocks, cfg)
    monkeypatch.setattr(VF, "EXACT_CHUNK", 97)
    small = PL.plan_program(blocks, cfg)
    assert small.utilisation == ref.utilisation
    assert ref.gov.keys() == small.gov.keys()
    assert all(np.array_equal(np.asarray(ref.gov[k]), np.asarray(small.gov[k])) for k in ref.gov)
    assert np.array_equal(small.s_tab, ref.s_tab)
