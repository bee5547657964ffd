"""Predicted tool-tip uncertainty over the workspace after calibration.

The fitted parameters' covariance ``C`` (from the noise estimate and the data
Jacobian, :meth:`~hexacnc.calib.identify.FitResult.covariance`) is carried to the
tool tip through the pose the calibrated model reaches: at a pose ``X`` the
strut-length error of a parameter error ``dtheta`` is ``G dtheta`` (geometry:
``d reading / d theta``; causes: minus their strut-length bases), the pose error
``dX = -J^-1 G dtheta`` and the tool-tip position error ``dp = [I, -[R p_tip]x E] dX``.
``Cov(p) = A C A^T`` with ``A = dp/dtheta``; the instrument frame's parameters are
left out (they belong to the instrument, not the machine).  Grid: the workspace
box (shrunk 10 % about home) in x and y at three heights, home orientation,
reachable poses only.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..errormodel import reading_parameter_jacobian
from ..kinematics import Hexapod
from .identify import FitResult
from .measurements import Measurements
from .model import Context, jacobian_batch, rate_matrices, strut_geometry

CSV_COLUMNS = ("x_mm", "y_mm", "z_mm", "a_deg", "b_deg", "c_deg", "sigma_x_mm", "sigma_y_mm", "sigma_z_mm",
               "sigma_position_mm")


def grid_poses(cfg, n_xy: int = 9, n_z: int = 3, shrink: float = 0.9) -> np.ndarray:
    """Reachable poses (N,6) mm/deg on an x-y grid at ``n_z`` heights, home orientation."""
    lo = np.asarray(cfg.workspace_min, dtype=float)
    hi = np.asarray(cfg.workspace_max, dtype=float)
    home = np.asarray(cfg.home_pose, dtype=float)
    lo = home + shrink * (lo - home)
    hi = home + shrink * (hi - home)
    xs, ys, zs = (np.linspace(lo[k], hi[k], n) for k, n in ((0, n_xy), (1, n_xy), (2, n_z)))
    Z, Y, Xg = np.meshgrid(zs, ys, xs, indexing="ij")
    P = np.tile(home, (Xg.size, 1))
    P[:, 0], P[:, 1], P[:, 2] = Xg.ravel(), Y.ravel(), Z.ravel()
    ok = ~Hexapod(cfg).batch_violations(P)
    return P[ok]


def _grid_context(res: FitResult, P: np.ndarray, hx: Hexapod) -> Context:
    """A context for the cause bases at the grid poses: readings from the fitted geometry, no payload,
    the fit data's mean temperatures, the first session."""
    ctx0 = res.evaluator.ctx
    q = hx.inverse_batch(P) - hx.offset[None]
    m = Measurements("<grid>", q, np.full_like(q, np.nan))
    n = len(P)
    if ctx0.meas.session is not None and len(ctx0.sessions):
        m.session = np.array([ctx0.sessions[0]] * n, dtype=object)
    if ctx0.meas.T_strut is not None:
        m.T_strut = np.tile(np.nanmean(ctx0.meas.T_strut, axis=0), (n, 1))
    if ctx0.meas.T_frame is not None:
        m.T_frame = np.full(n, float(np.nanmean(ctx0.meas.T_frame)))
    m.payload_kg = np.zeros(n)
    ctx = Context(ctx0.cfg, m, float(ctx0.sigma[0]), float(ctx0.sigma[3]), fit_sessions=ctx0.sessions)
    ctx.nl_degree, ctx.nl_linear = ctx0.nl_degree, ctx0.nl_linear
    return ctx


def tool_tip_covariance(cfg, res: FitResult, poses_deg: np.ndarray) -> np.ndarray:
    """(N,3,3) covariance (mm^2) of the tool-tip position at ``poses_deg`` after calibration."""
    lay = res.layout
    hx = Hexapod.from_parameters(cfg, res.theta[:42])
    P = np.asarray(poses_deg, dtype=float)
    X = P.copy()
    X[:, 3:] = np.radians(X[:, 3:])
    G = np.zeros((len(P), 6, lay.n))
    G[:, :, :42] = reading_parameter_jacobian(hx, P)
    if lay.causes:
        ctx = _grid_context(res, P, hx)
        for c, sl in lay.causes.items():
            G[:, :, sl] = -lay.cause_models[c].build(ctx, X, hx.base, hx.plat)
    R, rp, s, L = strut_geometry(hx.base, hx.plat, X)
    J = jacobian_batch(rp, s / L[..., None], X)
    dX = -np.linalg.solve(J, G)                                   # (N,6,P)
    tip = np.einsum("nij,j->ni", R, np.asarray(cfg.tool.tip_platform_mm, dtype=float))
    E = rate_matrices(X[:, 3:])
    skew = np.zeros((len(P), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -tip[:, 2], tip[:, 1], -tip[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = tip[:, 2], -tip[:, 1], tip[:, 0]
    A = dX[:, :3] - np.einsum("nij,njk,nkp->nip", skew, E, dX[:, 3:])   # dp/dtheta (N,3,P)
    idx = np.where(res.free)[0]
    keep = np.ones(len(idx), dtype=bool)
    if lay.frame is not None:
        keep = ~np.isin(idx, np.arange(lay.frame.start, lay.frame.stop))
    C = res.covariance()[np.ix_(keep, keep)]
    Af = A[:, :, idx[keep]]
    return np.einsum("nip,pq,njq->nij", Af, C, Af)


def tool_tip_map(cfg, res: FitResult, n_xy: int = 9, n_z: int = 3) -> dict:
    """Grid, per-axis and total (sqrt of the trace) 1-sigma tool-tip position uncertainty (mm)."""
    P = grid_poses(cfg, n_xy, n_z)
    C = tool_tip_covariance(cfg, res, P)
    sd = np.sqrt(np.maximum(np.einsum("nii->ni", C), 0.0))
    tot = np.sqrt(np.sum(sd ** 2, axis=1))
    rows = np.column_stack([P, sd, tot])
    return {"columns": list(CSV_COLUMNS), "rows": rows.tolist(), "points": int(len(P)),
            "sigma_position_mm": {"median": float(np.median(tot)), "p95": float(np.percentile(tot, 95)),
                                  "max": float(np.max(tot))},
            "definition": "1-sigma tool-tip position uncertainty (sqrt of the covariance trace) from the fitted "
                          "parameters' covariance, home orientation, x-y grid at three heights; instrument "
                          "frame parameters excluded"}


def write_map_csv(path: str | Path, m: dict) -> None:
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(m["columns"])
        for r in m["rows"]:
            w.writerow([f"{v:.6g}" for v in r])


def plot_map(path: str | Path, m: dict) -> None:
    from .plots import _plt
    plt = _plt()
    rows = np.asarray(m["rows"])
    zs = np.unique(np.round(rows[:, 2], 6))
    fig, axes = plt.subplots(1, len(zs), figsize=(4.8 * len(zs), 4.0), squeeze=False)
    fig.subplots_adjust(wspace=0.4)
    vmax = float(rows[:, 9].max())
    for ax, z in zip(axes[0], zs):
        sel = np.isclose(rows[:, 2], z)
        sc = ax.scatter(rows[sel, 0], rows[sel, 1], c=rows[sel, 9] * 1000.0, vmin=0, vmax=vmax * 1000.0,
                        cmap="viridis", s=60)
        ax.set_title(f"z = {z:.0f} mm")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_aspect("equal", adjustable="datalim")
    fig.colorbar(sc, ax=axes[0].tolist(), label="tool-tip 1-sigma (um)")
    fig.suptitle("Predicted tool-tip uncertainty after calibration")
    fig.savefig(path, dpi=90)
    plt.close(fig)
