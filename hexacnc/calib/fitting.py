"""Fitting primitives of the diagnosis: options, one model's fit, blocked cross-validation, BIC.

A *model* is the 42 geometric parameters (plus the measurement-frame registration
where the instrument is not in the base frame) plus a list of cause models
(:data:`~hexacnc.calib.model.CAUSES` and the per-strut variants of
:data:`~hexacnc.calib.model.VARIANTS`), fitted jointly.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import DataError
from .identify import FitResult, fit
from .measurements import Measurements
from .model import CAUSES, Context, Evaluator, build_layout


#: used for weighting only when the noise is not given
DEFAULT_NOISE_MM = 0.01


@dataclass
class Options:
    noise_mm: float | None = None
    noise_deg: float | None = None
    causes: tuple[str, ...] = CAUSES
    frame: str = "auto"                  #: auto | base | register
    folds: int = 5
    min_cv_gain: float = 0.03            #: relative CV RMS reduction a cause must bring
    min_delta_bic: float = 10.0
    max_causes: int = 4
    rereference_rows: int | None = None  #: None: auto (only for holdout sessions not seen in the fit)
    rereference: str = "offsets"         #: offsets | offsets+frame
    prior_joint_mm: float = 5.0
    prior_offset_mm: float = 50.0
    variants: bool = True                #: try the per-strut forms (model.VARIANTS) against the common ones
    retest: bool = True                  #: re-test each named cause in the presence of the others
    min_swap_delta_bic: float = 10.0     #: a cause is told apart from another when swapping costs this much BIC
    min_separable_fraction: float = 1e-4 #: below: the signature lies inside the geometric parameters' span


@dataclass
class Model:
    causes: list[str]
    fit: FitResult
    cv_rms: float = math.nan             #: whitened CV residual RMS
    bic: float = math.nan
    nl_degree: int = 3                   #: strut_nonlinearity degree used by this model
    nl_linear: bool = True               #: strut_nonlinearity includes its gain (P1) term


def noise_defaults(cfg, noise_mm, noise_deg) -> tuple[float, float, bool]:
    """Weights (mm, deg) and whether the noise is known."""
    known = noise_mm is not None or noise_deg is not None
    char = max(1.0, float(np.mean(np.linalg.norm(np.asarray(cfg.platform_joints_mm)[:, :2], axis=1))))
    if noise_mm is None and noise_deg is None:
        noise_mm = DEFAULT_NOISE_MM
    if noise_mm is None:
        noise_mm = math.radians(noise_deg) * char
    if noise_deg is None:
        noise_deg = math.degrees(noise_mm / char)
    if noise_mm <= 0 or noise_deg <= 0:
        raise DataError(f"instrument noise must be positive, got {noise_mm} mm, {noise_deg} deg")
    return float(noise_mm), float(noise_deg), known


def use_frame(meas: Measurements, how: str) -> bool:
    if how == "register":
        return True
    if how == "base":
        return False
    if how != "auto":
        raise DataError(f"frame must be auto, base or register, got {how!r}")
    return int(meas.full_pose_rows().sum()) >= 3


def fit_model(cfg, ctx: Context, causes, frame0: np.ndarray | None, opts: Options,
              warm: FitResult | None = None) -> FitResult:
    """Fit geometry (+frame) + causes; warm-started from a smaller model where given."""
    lay = build_layout(cfg, ctx, causes, frame0, opts.prior_joint_mm, opts.prior_offset_mm)
    theta = lay.theta0.copy()
    X0 = None
    if warm is not None:
        for j, nm in enumerate(warm.layout.names):
            if nm in lay.names:
                theta[lay.names.index(nm)] = warm.theta[j]
        X0 = warm.evaluator.X
    elif frame0 is not None:   # frames first: the nominal geometry seen through an unknown frame
        free = np.zeros(lay.n, dtype=bool)
        free[lay.frame] = True
        r0 = fit(cfg, ctx, lay, free=free, max_iter=30)
        theta, X0 = r0.theta, r0.evaluator.X
    res = fit(cfg, ctx, lay, theta_init=theta, X_init=X0)
    bad = ~res.evaluator.converged
    if bad.any():
        lines = ctx.meas.lines[bad] if ctx.meas.lines is not None else np.where(bad)[0] + 1
        raise DataError(f"{ctx.meas.path}: the readings of {int(bad.sum())} row(s) (line(s) "
                        f"{', '.join(str(int(x)) for x in lines[:10])}{' ...' if bad.sum() > 10 else ''}) give no "
                        f"pose of this machine even after fitting; are the readings in mm and does the config "
                        f"({cfg.path}) describe this machine?")
    return res


def check_readings(cfg, meas: Measurements, margin: float = 0.05) -> None:
    """Readings must put every strut inside its configured stroke (with a margin): else the units
    or the machine description are wrong, and a fit would only hide it."""
    L = meas.q + np.asarray(cfg.strut_offset_mm)[None]
    lo = np.asarray(cfg.min_length_mm)
    hi = np.asarray(cfg.max_length_mm)
    tol = margin * (hi - lo)
    bad = (L < lo - tol) | (L > hi + tol)
    if bad.any():
        k, i = (int(v) for v in np.argwhere(bad)[0])
        line = int(meas.lines[k]) if meas.lines is not None else k + 1
        raise DataError(f"{meas.path}: line {line}, q{i + 1} = {meas.q[k, i]:g} mm puts strut {i + 1} at "
                        f"{L[k, i]:.1f} mm, outside its stroke [{lo[i]:g}, {hi[i]:g}] mm of {cfg.path} "
                        f"({int(bad.any(axis=1).sum())} row(s) affected): wrong units (see --map scale) or "
                        f"the wrong machine description")


NL_DEGREES = (3, 5, 7)


def set_nl(ctx: Context, model: "Model") -> None:
    """Context options of strut_nonlinearity for the layouts built from now on."""
    ctx.nl_degree = getattr(model, "nl_degree", ctx.nl_degree)
    ctx.nl_linear = "strut_scale" not in model.causes and getattr(model, "nl_linear", True)


def fit_candidate(cfg, ctx: Context, chosen: list[str], c: str, frame0, opts: "Options", warm: FitResult,
                   known: bool, current_degree: int) -> "Model":
    """Fit chosen + [c]; strut_nonlinearity picks its polynomial degree by BIC.

    ``ctx``'s strut_nonlinearity options are restored before returning; the fitted
    layout keeps the ones it was built with.
    """
    keep_deg, keep_lin = ctx.nl_degree, ctx.nl_linear
    try:
        ctx.nl_linear = "strut_scale" not in chosen   # with a gain term unless strut_scale came first
        ctx.nl_degree = current_degree
        if c != "strut_nonlinearity":
            r = fit_model(cfg, ctx, chosen + [c], frame0, opts, warm=warm)
            r.noise_known = known
            m = Model(chosen + [c], r, bic=bic(r, known))
            m.nl_degree = current_degree
            return m
        best = None
        for deg in NL_DEGREES:
            ctx.nl_degree = deg
            r = fit_model(cfg, ctx, chosen + [c], frame0, opts, warm=warm)
            r.noise_known = known
            m = Model(chosen + [c], r, bic=bic(r, known))
            m.nl_degree = deg
            if best is None or m.bic < best.bic - 1e-9:
                best = m
        return best
    finally:
        ctx.nl_degree, ctx.nl_linear = keep_deg, keep_lin


def folds(n: int, k: int) -> list[np.ndarray]:
    k = max(2, min(k, n // 4))
    edges = np.linspace(0, n, k + 1).astype(int)
    return [np.arange(edges[i], edges[i + 1]) for i in range(k)]


def cv_score(cfg, meas: Measurements, ctx: Context, model_fit: FitResult, causes, frame0, opts: Options) -> float:
    """Blocked K-fold CV: whitened RMS of the residuals of each block predicted from the others."""
    num, den = 0.0, 0
    for test in folds(meas.n, opts.folds):
        train = np.setdiff1d(np.arange(meas.n), test)
        ctx_tr = Context(cfg, meas.subset(train), ctx.sigma[0], ctx.sigma[3], fit_sessions=ctx.sessions)
        ctx_te = Context(cfg, meas.subset(test), ctx.sigma[0], ctx.sigma[3], fit_sessions=ctx.sessions)
        lay = model_fit.layout
        # warm start from the full-data fit
        r = fit(cfg, ctx_tr, lay, theta_init=model_fit.theta, X_init=model_fit.evaluator.X[train], max_iter=20,
                rel_tol=1e-6)
        ev = Evaluator(cfg, lay, ctx_te, model_fit.evaluator.X[test])
        rv, _ = ev.evaluate(r.theta)
        nd = int(ctx_te.mask.sum())
        num += float(rv[:nd] @ rv[:nd])
        den += nd
    return math.sqrt(num / max(den, 1))


def bic(res: FitResult, noise_known: bool) -> float:
    n = res.n_data
    if noise_known:
        return res.cost + res.p_eff * math.log(n)
    return n * math.log(max(res.cost, 1e-300) / n) + res.p_eff * math.log(n)
