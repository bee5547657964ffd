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
        """(P_free, P_free) parameter covariance from the noise model and priors."""
        if self._cov is None:
            idx = np.where(self.free)[0]
            sig = self.layout.prior_sigma[idx]
            A = self.jac.T @ self.jac + np.diag(1.0 / sig ** 2)
            D = 1.0 / np.sqrt(np.diag(A))
            As = A * D[:, None] * D[None, :]
            self._cov = np.linalg.pinv(As, rcond=1e-14) * D[:, None] * D[None, :]
        return self._cov


def fit(cfg, ctx: Context, layout: Layout, theta_init: np.ndarray | None = None, free: np.ndarray | None = None,
        max_iter: int = 60, X_init: np.ndarray | None = None, tol: float = 1e-10) -> FitResult:
    """Levenberg-Marquardt with column scaling; returns a :class:`FitResult`."""
    theta = np.array(layout.theta0 if theta_init is None else theta_init, dtype=float)
    free = np.ones(layout.n, dtype=bool) if free is None else np.asarray(free, dtype=bool)
    ev = Evaluator(cfg, layout, ctx, X_init)
    nd = ev.n_data()
    if nd == 0:
        raise DataError(f"{ctx.meas.path}: no measured coordinates")
    r, J = ev.evaluate(theta)
    cost = float(r @ r)
    lam = 1e-4
    it = 0
    converged = False
    idx = np.where(free)[0]
    while it < max_iter:
        it += 1
        Jf = J[:, idx]
        D = np.sqrt(np.einsum("ij,ij->j", Jf, Jf))
        D[D == 0] = 1.0
        Js = Jf / D
        A = Js.T @ Js
        g = Js.T @ r
        improved = False
        for _ in range(12):
            try:
                step = -np.linalg.solve(A + lam * np.eye(len(idx)), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            th_new = theta.copy()
            th_new[idx] += step / D
            X_saved = ev.X.copy()
            r_new, J_new = ev.evaluate(th_new)
            c_new = float(r_new @ r_new)
            if c_new <= cost:
                rel = (cost - c_new) / max(cost, 1e-300)
                theta, r, J, cost = th_new, r_new, J_new, c_new
                lam = max(lam / 5.0, 1e-9)
                improved = True
                if rel < tol or float(np.max(np.abs(step))) < 1e-9:
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
    Jd = J[:ndata_rows][:, idx]
    rd = r[:ndata_rows]
    sig = layout.prior_sigma[idx]
    s = np.linalg.svd(Jd * sig[None, :], compute_uv=False)
    p_eff = float(np.sum(s ** 2 / (1.0 + s ** 2)))
    return FitResult(layout, theta, free, float(rd @ rd), nd, p_eff, it, converged, ev, Jd)


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
