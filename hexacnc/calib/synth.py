"""Seeded generator of measurement sets with a hidden effect (for tests and benchmarks).

A "true" machine is the configured one with random manufacturing errors
(joint positions, strut offsets).  Poses are drawn inside the workspace within
limits; the instrument sees them through an optional registration frame with
Gaussian noise.  One effect from the catalog (or none) acts on the struts with
a random magnitude; the physics is simulated directly (exact joint geometry
for ``joint_offset``, a polynomial spool/lead map for ``strut_nonlinearity``),
not through the identification model's linearised bases.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..kinematics import Hexapod
from .measurements import Measurements, write_measurements
from .model import CAUSES, VARIANTS, Context, base_cause, cause_model, measure, strut_geometry

#: effects the generator can hide: the catalog plus the per-strut variants
EFFECTS: tuple[str, ...] = CAUSES + tuple(VARIANTS.values())

MEASURE_SETS = {"xyzabc": "xyzabc", "xyz": "xyz", "z": "z", "ab": "ab", "xyzab": "xyzab"}


@dataclass
class SynthSet:
    fit: Measurements
    holdout: Measurements
    effect: str                      #: "none", a cause name, or several joined by "+"
    effect_params: dict = field(default_factory=dict)
    magnitude_mm: float = 0.0        #: RMS of the effect on the struts (per-strut mean removed)
    theta_true: np.ndarray | None = None
    frame_true: np.ndarray | None = None
    noise_mm: float = 0.0
    noise_deg: float = 0.0
    effects: list = field(default_factory=list)          #: the hidden effects (empty: none)
    effects_params: dict = field(default_factory=dict)   #: per effect: its parameters
    magnitudes_mm: dict = field(default_factory=dict)    #: per effect: its RMS on the struts


def sample_poses(cfg, rng: np.random.Generator, n: int, shrink: float = 0.9) -> np.ndarray:
    """n reachable poses (mm/deg), uniform in the workspace box (shrunk about home), within limits."""
    hx = Hexapod(cfg)
    lo = np.asarray(cfg.workspace_min, dtype=float)
    hi = np.asarray(cfg.workspace_max, dtype=float)
    home = np.asarray(cfg.home_pose, dtype=float)
    lo = home + shrink * (lo - home)
    hi = home + shrink * (hi - home)
    out = []
    while sum(len(o) for o in out) < n:
        P = lo + (hi - lo) * rng.random((4 * n, 6))
        ok = ~hx.batch_violations(P)
        out.append(P[ok])
    return np.vstack(out)[:n]


def _effect_lengths(effect: str, params: np.ndarray, ctx: Context, X: np.ndarray, base, plat) -> np.ndarray:
    """Physical strut-length change (N,6) mm of a hidden effect at true poses X (rad)."""
    if effect == "joint_offset":   # exact: each pivot sits d off its joint's first axis, towards the strut
        R, _, s, L = strut_geometry(base, plat, X)
        a = ctx.joint_axis1[None]
        ap = np.einsum("nij,kj->nki", R, ctx.joint_axis1_platform)
        nb = s - np.einsum("nki,nki->nk", s, np.broadcast_to(a, s.shape))[..., None] * a
        nb /= np.linalg.norm(nb, axis=2)[..., None]
        npl = s - np.einsum("nki,nki->nk", s, ap)[..., None] * ap
        npl /= np.linalg.norm(npl, axis=2)[..., None]
        eff = s - params[None, :6, None] * nb - params[None, 6:, None] * npl
        return L - np.linalg.norm(eff, axis=2)   # the drive spans the pivots, not the joint centres
    if effect == "strut_nonlinearity":   # spool-like quadratic plus cubic lead error, in reading units
        # (the best straight line over the stroke removed: a pure gain error is strut_scale)
        t = (ctx.q - ctx.q_center) / ctx.q_half
        return params[None, :6] * (t * t - 1.0 / 3.0) + params[None, 6:] * (t ** 3 - 0.6 * t)
    cm = cause_model(effect, ctx)
    B = cm.build(ctx, X, base, plat)
    return np.einsum("nik,k->ni", B, params)


def _random_params(effect: str, rng, ctx: Context) -> np.ndarray:
    if effect in ("elastic_sag", "thermal_expansion"):
        return np.array([1.0])
    if effect in VARIANTS.values():   # per strut: a spread around the common value, one strut far off
        p = rng.uniform(0.7, 1.3, 6)
        p[rng.integers(6)] *= rng.choice([0.2, 2.5])
        return p
    if effect == "session_offset":
        return rng.normal(size=6 * (len(ctx.sessions) - 1))
    if effect == "backlash":   # physical sign: the strut lags its motor by the half gap (L += h * dir, h < 0)
        return -np.abs(rng.normal(size=6))
    if effect in ("strut_nonlinearity", "joint_offset"):
        return rng.normal(size=12)
    return rng.normal(size=6)


def _readings(effects, params, ctx_fn, X, base, plat, off, session, n_iter: int = 6):
    """Readings q such that o + q + sum(effects(q, X)) = |s| (fixed point; effects are small).

    Backlash is solved row by row in the order the rows were measured: the
    direction of each strut is the direction its reading (the motor) moved,
    which is what :meth:`Measurements.direction` recovers from the readings.
    """
    _, _, _, L = strut_geometry(base, plat, X)
    smooth = [(e, p) for e, p in zip(effects, params) if e != "backlash"]
    half = next((p for e, p in zip(effects, params) if e == "backlash"), None)
    q = L - off
    for _ in range(n_iter):
        ctx = ctx_fn(q)
        dl = sum((_effect_lengths(e, p, ctx, X, base, plat) for e, p in smooth), np.zeros_like(q))
        q = L - off - dl
        if half is not None:
            q = backlash_readings(q, half, session)
    return q


def backlash_readings(p: np.ndarray, half: np.ndarray, session) -> np.ndarray:
    """Motor readings q (N,6) that put the struts at the lengths whose backlash-free readings are ``p``.

    ``L = o + q + h * dir`` with ``h <= 0`` (the output lags the motor by the
    half gap); ``dir`` is the sign of the reading's last move, +1 on the first row
    of a session (approached from the retracted home side).  On a reversal the
    motor travels the gap before the strut follows, so the direction of the
    reading is always consistent with the data (each row: the one solution).
    """
    if np.any(half > 0):
        raise ValueError("backlash: the half gap h must be <= 0 in L = o + q + h * dir (the output lags the motor)")
    q = np.empty_like(p)
    prev = np.ones(p.shape[1])
    for k in range(p.shape[0]):
        if k == 0 or (session is not None and session[k] != session[k - 1]):
            prev = np.ones(p.shape[1])
            q[k] = p[k] - half * prev
            continue
        keep = p[k] - half * prev                   # no reversal: the gap stays taken up
        same = (keep - q[k - 1]) * prev >= -1e-9
        d = np.where(same, prev, -prev)
        q[k] = p[k] - half * d
        prev = d
    return q


def generate(cfg, seed: int, effect: str = "none", n_fit: int = 120, n_holdout: int = 60,
             measure_set: str = "xyzabc", noise_mm: float = 0.005, noise_deg: float = 0.0005,
             magnitude_range: tuple[float, float] = (10.0, 40.0), joint_sigma_mm: float = 0.5,
             offset_sigma_mm: float = 1.0, registration: bool = False, sessions: int = 3,
             holdout_new_session_mm: float = 0.0, effects: tuple[str, ...] | None = None) -> SynthSet:
    """One seeded fit + holdout pair.  ``magnitude_range`` is in units of ``noise_mm``.

    ``effect``: one hidden effect (or ``none``); ``effects``: several at once (overrides
    ``effect``; each gets its own random magnitude in ``magnitude_range``); names from
    :data:`EFFECTS` (the catalog plus the per-strut variants).
    ``holdout_new_session_mm`` > 0: the held-out rows come from a new session (label
    ``new``) whose strut offsets moved by that RMS amount (re-homing).
    """
    effs = [e for e in (effects if effects is not None else (effect,)) if e != "none"]
    for e in effs:
        if e not in EFFECTS:
            raise ValueError(f"unknown effect {e!r}")
    if len({base_cause(e) for e in effs}) != len(effs):
        raise ValueError(f"effects {effs}: one form per cause (common or per strut)")
    kinds = {base_cause(e) for e in effs}
    rng = np.random.default_rng(seed)
    hx = Hexapod(cfg)
    theta = hx.parameters().copy()
    theta[:36] += rng.normal(0.0, joint_sigma_mm, 36)
    theta[36:] += rng.normal(0.0, offset_sigma_mm, 6)
    base, plat, off = theta[:18].reshape(6, 3), theta[18:36].reshape(6, 3), theta[36:]
    frame = None
    if registration:
        frame = np.r_[rng.normal(0, 200, 3), rng.normal(0, 0.2, 3), rng.normal(0, 50, 3), rng.normal(0, 0.05, 3)]
    n = n_fit + n_holdout
    P = sample_poses(cfg, rng, n)
    X = P.copy()
    X[:, 3:] = np.radians(X[:, 3:])
    sess = None
    if "session_offset" in kinds or sessions > 1:
        labels = [f"s{k + 1}" for k in range(max(2 if "session_offset" in kinds else 1, sessions))]
        sess = np.array([labels[min(len(labels) - 1, k * len(labels) // n_fit)] for k in range(n_fit)]
                        + [labels[k % len(labels)] for k in range(n_holdout)], dtype=object)
    T = None
    if "thermal_expansion" in kinds:
        drift = np.cumsum(rng.normal(0, 0.4, n)) + rng.uniform(19, 24)
        T = drift[:, None] + rng.normal(0, 0.5, (n, 6)) + rng.normal(0, 1.0, 6)[None]
    payload = None
    if "elastic_sag" in kinds:
        payload = np.where(rng.random(n) < 0.5, 0.0, rng.uniform(0.0, 2.0 * max(cfg.mass_kg, 10.0), n))
    # fit and holdout rows are one stream (backlash direction follows the row order of each file)
    parts = []
    for rows in (slice(0, n_fit), slice(n_fit, n)):
        m = Measurements("<synthetic>", np.zeros((rows.stop - rows.start, 6)), np.zeros((rows.stop - rows.start, 6)))
        m.session = None if sess is None else sess[rows]
        m.T_strut = None if T is None else T[rows]
        m.payload_kg = None if payload is None else payload[rows]
        parts.append(m)
    ctx_fit0 = Context(cfg, parts[0], noise_mm, noise_deg)
    _, _, _, L = strut_geometry(base, plat, X[:n_fit])
    parts[0].q = L - off
    c0 = Context(cfg, parts[0], noise_mm, noise_deg)
    params, mags = [], {}
    for e in effs:
        p_ = _random_params(e, rng, ctx_fit0)
        # scale to a random magnitude: RMS of the effect on the struts, per-strut mean removed
        target = rng.uniform(*magnitude_range) * noise_mm
        dl = _effect_lengths(e, p_, c0, X[:n_fit], base, plat)
        dl = dl - dl.mean(axis=0)
        params.append(p_ * target / max(float(np.sqrt(np.mean(dl ** 2))), 1e-12))
        mags[e] = float(target)
    for m, rows in zip(parts, (slice(0, n_fit), slice(n_fit, n))):
        Xr = X[rows]

        def ctx_fn(q, m=m):
            m.q = q
            return Context(cfg, m, noise_mm, noise_deg, fit_sessions=ctx_fit0.sessions)
        if rows.start == n_fit and holdout_new_session_mm > 0:
            m.session = np.array(["new"] * len(Xr), dtype=object)
        m.q = _readings(effs, params, ctx_fn, Xr, base, plat, off, m.session)
        if rows.start == n_fit and holdout_new_session_mm > 0:   # re-homed: every reading moves by a constant
            m.q = m.q - rng.normal(0.0, holdout_new_session_mm, 6)[None]
        y = measure(Xr, frame)
        y[:, :3] += rng.normal(0, noise_mm, (len(Xr), 3))
        y[:, 3:] += rng.normal(0, noise_deg, (len(Xr), 3))
        keep = np.array([c in MEASURE_SETS.get(measure_set, measure_set) for c in "xyzabc"])
        if not keep.any():
            raise ValueError(f"measure set {measure_set!r} names no coordinate of xyzabc")
        y[:, ~keep] = np.nan
        m.y = y
        m.lines = np.arange(2, len(Xr) + 2)
    eps = {e: _effect_param_names(e, p_, ctx_fit0) for e, p_ in zip(effs, params)}
    label = "+".join(effs) if effs else "none"
    first = eps[effs[0]] if len(effs) == 1 else {}
    return SynthSet(parts[0], parts[1], label, first, float(sum(mags.values())), theta, frame, noise_mm, noise_deg,
                    effects=effs, effects_params=eps, magnitudes_mm=mags)


def _effect_param_names(effect: str, params: np.ndarray, ctx: Context) -> dict:
    if effect == "strut_nonlinearity":
        ep = {f"quad{i + 1}_mm": float(params[i]) for i in range(6)}
        ep.update({f"cubic{i + 1}_mm": float(params[6 + i]) for i in range(6)})
        return ep
    return {nm: float(v) for nm, v in zip(cause_model(effect, ctx).names, params)}


def write_set(s: SynthSet, fit_path, holdout_path) -> None:
    write_measurements(fit_path, s.fit)
    write_measurements(holdout_path, s.holdout)
