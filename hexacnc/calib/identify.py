"""Identification: weighted Levenberg-Marquardt over a :class:`~hexacnc.calib.model.Layout`.

Residuals are whitened by the instrument noise; priors toward nominal are
extra equations.  After convergence: covariance, standard deviations,
strongest correlations and the directions the data cannot identify (SVD of the
data Jacobian in prior-normalised coordinates: a direction with singular value
below 1 is held more by the prior than by the measurements).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import DataError
from .model import Context, Evaluator, Layout, rms_summary


@dataclass
class FitResult:
    layout: Layout
    theta: np.ndarray
    free: np.ndarray
    cost: float                    #: whitened data residual sum of squares (chi^2 with true noise)
    n_data: int
    p_eff: float                   #: effective number of parameters (priors shrink some)
    iterations: int
    converged: bool
    evaluator: Evaluator = field(repr=False)
    jac: np.ndarray = field(repr=False, default=None)      #: whitened data Jacobian at theta (free columns)
    basis: np.ndarray = field(repr=False, default=None)    #: (P, k) theta = theta_init + basis @ z
    jac_z: np.ndarray = field(repr=False, default=None)    #: whitened data Jacobian w.r.t. z
    noise_known: bool = True   #: False: covariance scaled by chi^2/dof (noise estimated from the residual)
    _cov: np.ndarray | None = field(repr=False, default=None)

    @property
    def dof(self) -> float:
        return max(1.0, self.n_data - self.p_eff)

    @property
    def chi2_red(self) -> float:
        return self.cost / self.dof

    def residuals(self) -> dict:
        return self.evaluator.residuals(self.theta)

    def rms(self) -> dict:
        return rms_summary(self.residuals())

    def covariance(self) -> np.ndarray:
        """(P_free, P_free) parameter covariance from the noise model and priors (free = ``self.free``)."""
        if self._cov is None:
            T = self.basis
            sig = self.layout.prior_sigma
            A = self.jac_z.T @ self.jac_z + T.T @ (T / sig[:, None] ** 2)
            D = 1.0 / np.sqrt(np.diag(A))
            Cz = np.linalg.pinv(A * D[:, None] * D[None, :], rcond=1e-14) * D[:, None] * D[None, :]
            Tf = T[self.free]
            self._cov = Tf @ Cz @ Tf.T
            if not self.noise_known:
                self._cov = self._cov * max(1.0, self.chi2_red)
        return self._cov


def gauge_basis(layout: Layout, fix_gauge: bool) -> np.ndarray:
    """(P, k) basis of the parameter changes a fit may make.

    With a registered measurement frame, a rigid motion of all base joints is the
    same as moving the frame, and a rigid motion of all platform joints the same
    as moving the tracked target: ``fix_gauge`` removes these 12 directions
    (the joints' centroid and mean orientation stay nominal), which keeps the
    problem well conditioned.
    """
    P = layout.n
    if not (fix_gauge and layout.frame is not None):
        return np.eye(P)
    blocks = []
    th0 = layout.theta0
    for start in (0, 18):
        pts = th0[start:start + 18].reshape(6, 3)
        C = np.zeros((6, 18))
        for i in range(6):
            C[0:3, 3 * i:3 * i + 3] = np.eye(3)
            x, y, z = pts[i]
            C[3:6, 3 * i:3 * i + 3] = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
        _, sv, Vt = np.linalg.svd(C)
        blocks.append(Vt[int(np.sum(sv > 1e-9 * sv[0])):].T)        # (18, 12)
    T = np.zeros((P, P - 12))
    T[0:18, 0:12] = blocks[0]
    T[18:36, 12:24] = blocks[1]
    T[36:, 24:] = np.eye(P - 36)
    return T


def fit(cfg, ctx: Context, layout: Layout, theta_init: np.ndarray | None = None, free: np.ndarray | None = None,
        max_iter: int = 60, X_init: np.ndarray | None = None, tol: float = 1e-3,
        fix_gauge: bool = True, rel_tol: float = 1e-9) -> FitResult:
    """Levenberg-Marquardt with column scaling; returns a :class:`FitResult`.

    ``tol``, ``rel_tol``: stop when the whitened cost (chi^2) drops by less than
    ``max(tol, rel_tol * cost)``.
    ``free``: mask of parameters to fit (default all); with a registered frame
    and all geometry free, the 12 gauge directions are removed (:func:`gauge_basis`).
    """
    theta = np.array(layout.theta0 if theta_init is None else theta_init, dtype=float)
    if free is None:
        free = np.ones(layout.n, dtype=bool)
        T = gauge_basis(layout, fix_gauge)
    else:
        free = np.asarray(free, dtype=bool)
        T = np.eye(layout.n)[:, free]
    ev = Evaluator(cfg, layout, ctx, X_init)
    nd = ev.n_data()
    if nd == 0:
        raise DataError(f"{ctx.meas.path}: no measured coordinates")
    r, J = ev.evaluate(theta)
    cost = float(r @ r)
    lam = 1e-4
    it = 0
    converged = False
    k = T.shape[1]
    while it < max_iter:
        it += 1
        Jf = J @ T
        D = np.sqrt(np.einsum("ij,ij->j", Jf, Jf))
        D[D == 0] = 1.0
        Js = Jf / D
        A = Js.T @ Js
        g = Js.T @ r
        improved = False
        for _ in range(12):
            try:
                step = -np.linalg.solve(A + lam * np.eye(k), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            th_new = theta + T @ (step / D)
            X_saved = ev.X.copy()
            r_new, J_new = ev.evaluate(th_new)
            c_new = float(r_new @ r_new)
            if c_new <= cost:
                drop = cost - c_new
                theta, r, J, cost = th_new, r_new, J_new, c_new
                lam = max(lam / 5.0, 1e-9)
                improved = True
                # converged: chi^2 moves by less than tol (statistically nothing) or a tiny step
                if drop < max(tol, rel_tol * cost) or float(np.max(np.abs(step))) < 1e-9:
                    converged = True
                break
            ev.X = X_saved
            lam *= 8.0
        if not improved:
            converged = True   # no descent direction left at this precision
            break
        if converged:
            break
    ev.evaluate(theta)
    nprior = int(np.isfinite(layout.prior_sigma).sum())
    ndata_rows = r.shape[0] - nprior
    Jd = J[:ndata_rows]
    rd = r[:ndata_rows]
    Jz = Jd @ T
    sig = layout.prior_sigma
    Ap = T.T @ (T / sig[:, None] ** 2)
    H = Jz.T @ Jz
    try:
        p_eff = float(np.trace(np.linalg.solve(H + Ap, H)))
    except np.linalg.LinAlgError:
        p_eff = float(np.linalg.matrix_rank(Jz))
    return FitResult(layout, theta, free, float(rd @ rd), nd, p_eff, it, converged, ev, Jd[:, free], T, Jz)


# ---------------------------------------------------------------------------
# reports on a fit
# ---------------------------------------------------------------------------
def parameter_table(res: FitResult, nominal: np.ndarray | None = None) -> list[dict]:
    """Per free parameter: name, value, change from nominal, standard deviation."""
    C = res.covariance()
    sd = np.sqrt(np.maximum(np.diag(C), 0.0))
    idx = np.where(res.free)[0]
    out = []
    th0 = res.layout.theta0 if nominal is None else nominal
    for k, j in enumerate(idx):
        out.append({"name": res.layout.names[j], "value": float(res.theta[j]),
                    "change": float(res.theta[j] - th0[j]), "std": float(sd[k])})
    return out


def strongest_correlations(res: FitResult, count: int = 10) -> list[dict]:
    C = res.covariance()
    sd = np.sqrt(np.maximum(np.diag(C), 1e-300))
    rho = C / sd[:, None] / sd[None, :]
    idx = np.where(res.free)[0]
    iu = np.triu_indices(len(idx), 1)
    vals = np.abs(rho[iu])
    order = np.argsort(-vals)[:count]
    return [{"a": res.layout.names[idx[iu[0][k]]], "b": res.layout.names[idx[iu[1][k]]],
             "correlation": float(rho[iu[0][k], iu[1][k]])} for k in order]


def unidentifiable_directions(res: FitResult, max_dirs: int = 20, top: int = 6) -> list[dict]:
    """Directions of parameter space the data cannot identify (held by the prior), with names.

    In prior-normalised coordinates ``z = (theta - theta0) / sigma_prior`` the
    data Jacobian's singular values ``s``: ``s < 1`` means the measurements
    constrain that combination less than the prior does.  Each direction is
    given by its largest components (parameter name and weight).
    """
    idx = np.where(res.free)[0]
    sig = res.layout.prior_sigma[idx]
    _, s, Vt = np.linalg.svd(res.jac * sig[None, :], full_matrices=False)
    out = []
    smax = float(s[0]) if len(s) else 0.0
    # pad: with fewer data rows than parameters the missing singular values are zero
    n_missing = len(idx) - len(s)
    if n_missing > 0:
        _, _, Vfull = np.linalg.svd(res.jac * sig[None, :], full_matrices=True)
        s = np.r_[s, np.zeros(n_missing)]
        Vt = Vfull
    for k in np.argsort(s):
        if s[k] >= 1.0 or len(out) >= max_dirs:
            break
        v = Vt[k] * sig
        v = v / np.linalg.norm(v)
        comp = np.argsort(-np.abs(v))[:top]
        out.append({"singular_value": float(s[k]),
                    "relative": float(s[k] / smax) if smax > 0 else 0.0,
                    "data_std_in_prior_units": (float(1.0 / s[k]) if s[k] > 0 else math.inf),
                    "combination": [{"name": res.layout.names[idx[c]], "weight": round(float(v[c]), 4)}
                                    for c in comp if abs(v[c]) > 0.05]})
    return out
