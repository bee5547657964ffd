"""Measurement model for identification: geometry (42), frames (12), cause models.

Strut length from a drive reading ``q`` (mm)::

    L_i = o_i + q_i + sum_c B_c,i(X, row) . theta_c          (cause models, linear in theta_c)

The platform pose ``X`` (mm/rad, base frame) solves ``|t + R p_i - b_i| = L_i``
(batch forward kinematics).  The instrument sees ``y = T_reg o X o T_tgt``:
``T_reg`` (measurement frame <- base frame) and ``T_tgt`` (measured target in
the platform frame), each ``[tx, ty, tz (mm), a, b, c (rad)]``.  ``y`` is
``x, y, z`` (mm) and ``a, b, c`` (deg); any subset is compared.

Parameter vector ``theta = [geometry (42) | frames (0 or 12) | causes ...]``;
:class:`Layout` names every entry.  Residuals are whitened by the instrument
noise; priors toward nominal are extra equations ``(theta - theta0) / sigma``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errormodel import PARAM_NAMES, reading_parameter_jacobian
from ..errors import DataError
from ..kinematics import Hexapod
from ..pose import matrices_from_euler, rate_matrices
from .measurements import Measurements

#: catalog of candidate causes, in documentation order
CAUSES: tuple[str, ...] = ("elastic_sag", "thermal_expansion", "strut_scale", "strut_nonlinearity",
                           "backlash", "session_offset", "joint_offset")

#: per-strut variants of causes that can differ by strut (a softer strut, a strut that heats more);
#: each is chosen against its common form by cross-validation and the information criterion
VARIANTS: dict[str, str] = {"elastic_sag": "elastic_sag_per_strut",
                            "thermal_expansion": "thermal_expansion_per_strut"}
#: variant model name -> the catalog cause it is a form of
VARIANT_OF: dict[str, str] = {v: k for k, v in VARIANTS.items()}


def base_cause(name: str) -> str:
    """Catalog name of a cause model (``elastic_sag_per_strut`` -> ``elastic_sag``)."""
    return VARIANT_OF.get(name, name)


FRAME_NAMES: tuple[str, ...] = tuple(
    [f"frame_{k}" for k in ("tx_mm", "ty_mm", "tz_mm", "a_rad", "b_rad", "c_rad")]
    + [f"target_{k}" for k in ("tx_mm", "ty_mm", "tz_mm", "a_rad", "b_rad", "c_rad")])

T_REF_C = 20.0  #: reference temperature of the thermal cause model


# ---------------------------------------------------------------------------
# rotations, batch
# ---------------------------------------------------------------------------
def euler_from_matrices(R: np.ndarray) -> np.ndarray:
    """(N,3,3) -> (N,3) a, b, c radians (b in [-90, 90] deg)."""
    b = np.arcsin(np.clip(-R[:, 2, 0], -1.0, 1.0))
    a = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    c = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    return np.column_stack([a, b, c])


def measure(X: np.ndarray, frame: np.ndarray | None) -> np.ndarray:
    """Instrument coordinates (N,6) mm/deg of poses X (N,6) mm/rad through ``frame`` (12, or (N,12) per row)."""
    if frame is None:
        out = X.copy()
        out[:, 3:] = np.degrees(out[:, 3:])
        return out
    F = np.asarray(frame, dtype=float)
    RX = matrices_from_euler(X[:, 3:])
    if F.ndim == 1:
        Rr = matrices_from_euler(F[None, 3:6])[0]
        Rt = matrices_from_euler(F[None, 9:12])[0]
        pos = F[:3] + (X[:, :3] + RX @ F[6:9]) @ Rr.T
        Rm = np.einsum("ij,njk,kl->nil", Rr, RX, Rt)
    else:
        Rr = matrices_from_euler(F[:, 3:6])
        Rt = matrices_from_euler(F[:, 9:12])
        pos = F[:, :3] + np.einsum("nij,nj->ni", Rr, X[:, :3] + np.einsum("nij,nj->ni", RX, F[:, 6:9]))
        Rm = Rr @ RX @ Rt
    return np.column_stack([pos, np.degrees(euler_from_matrices(Rm))])


def unmeasure(y: np.ndarray, frame: np.ndarray | None) -> np.ndarray:
    """Inverse of :func:`measure` for full poses: base-frame poses (N,6) mm/rad."""
    Y = np.array(y, dtype=float)
    Rm = matrices_from_euler(np.radians(Y[:, 3:]))
    if frame is None:
        return np.column_stack([Y[:, :3], np.radians(Y[:, 3:])])
    Rr = matrices_from_euler(frame[None, 3:6])[0]
    Rt = matrices_from_euler(frame[None, 9:12])[0]
    RX = np.einsum("ji,njk,lk->nil", Rr, Rm, Rt)
    t = (Y[:, :3] - frame[:3]) @ Rr - RX @ frame[6:9]
    return np.column_stack([t, euler_from_matrices(RX)])


# ---------------------------------------------------------------------------
# batch forward kinematics
# ---------------------------------------------------------------------------
def strut_geometry(base: np.ndarray, plat: np.ndarray, X: np.ndarray):
    R = matrices_from_euler(X[:, 3:])
    rp = np.einsum("nij,kj->nki", R, plat)
    s = X[:, None, :3] + rp - base[None]
    L = np.sqrt(np.einsum("nki,nki->nk", s, s))
    return R, rp, s, L


def jacobian_batch(rp: np.ndarray, u: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(N,6,6) dL/dX (angles rad)."""
    J = np.concatenate([u, np.cross(rp, u)], axis=2)
    J[:, :, 3:] = J[:, :, 3:] @ rate_matrices(X[:, 3:])
    return J


#: passes of :meth:`Evaluator.poses` with pose-dependent causes; each ends early once the poses move < 1e-9
MAX_FIXED_POINT_PASSES = 60


def forward_batch(base: np.ndarray, plat: np.ndarray, L: np.ndarray, X0: np.ndarray,
                  tol_mm: float = 1e-10, max_iter: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N,6) mm/rad from lengths (N,6) by batched Newton; returns (X, converged mask)."""
    X = np.array(X0, dtype=float)
    conv = np.zeros(X.shape[0], dtype=bool)
    for _ in range(max_iter):
        _, rp, s, Ln = strut_geometry(base, plat, X)
        r = L - Ln
        err = np.max(np.abs(r), axis=1)
        conv = err <= tol_mm
        if conv.all():
            break
        u = s / Ln[..., None]
        J = jacobian_batch(rp, u, X)
        try:
            dX = np.linalg.solve(J, r[..., None])[..., 0]
        except np.linalg.LinAlgError:
            dX = np.array([np.linalg.lstsq(J[k], r[k], rcond=None)[0] for k in range(len(X))])
        step = np.abs(dX).max(axis=1)
        dX[step > 500.0] *= (500.0 / step[step > 500.0])[:, None]
        X += dX
    return X, conv & np.all(np.isfinite(X), axis=1)


# ---------------------------------------------------------------------------
# cause models
# ---------------------------------------------------------------------------
@dataclass
class CauseModel:
    """One candidate: ``n`` parameters, names, display units and a basis builder."""
    name: str
    names: list[str]
    units: str
    unit_scale: float          #: reported value = theta * unit_scale
    x_dependent: bool
    description: str
    build: object = field(repr=False, default=None)   # (ctx, X rad) -> (N,6,k)
    #: optional exact (nonlinear) form: (ctx, X, base, plat, theta_c) -> (length change (N,6), d/dtheta_c (N,6,k));
    #: ``build`` is its linearisation at theta_c = 0 (identifiability, planning, uncertainty)
    exact: object = field(repr=False, default=None)


class Context:
    """Everything about one measurement set and machine the model needs (fixed during a fit)."""

    def __init__(self, cfg, meas: Measurements, noise_mm: float, noise_deg: float,
                 fit_sessions: list[str] | None = None):
        self.cfg = cfg
        self.meas = meas
        self.n = meas.n
        self.q = meas.q
        self.mask = meas.mask
        self.y = np.where(self.mask, meas.y, 0.0)
        self.sigma = np.array([noise_mm] * 3 + [noise_deg] * 3)
        self.direction = meas.direction()
        self.T = meas.strut_temperatures()
        self.payload = meas.payload_kg if meas.payload_kg is not None else np.zeros(self.n)
        self.sessions = fit_sessions if fit_sessions is not None else meas.sessions()
        # strut stroke in readings, from the configured length limits and offsets
        lo = np.asarray(cfg.min_length_mm) - np.asarray(cfg.strut_offset_mm)
        hi = np.asarray(cfg.max_length_mm) - np.asarray(cfg.strut_offset_mm)
        self.q_center = 0.5 * (lo + hi)
        self.q_half = np.maximum(0.5 * (hi - lo), 1e-6)
        ax = np.asarray(cfg.base_axes, dtype=float)
        a = np.cross(ax, [0.0, 0.0, 1.0])
        bad = np.linalg.norm(a, axis=1) < 1e-3
        a[bad] = np.cross(ax[bad], [1.0, 0.0, 0.0])
        self.joint_axis1 = a / np.linalg.norm(a, axis=1)[:, None]
        axp = np.asarray(cfg.platform_axes, dtype=float)
        ap = np.cross(axp, [0.0, 0.0, 1.0])
        bad = np.linalg.norm(ap, axis=1) < 1e-3
        ap[bad] = np.cross(axp[bad], [1.0, 0.0, 0.0])
        self.joint_axis1_platform = ap / np.linalg.norm(ap, axis=1)[:, None]   #: platform frame
        #: strut_nonlinearity: polynomial degree and whether its gain (P1) term is included
        self.nl_degree = 3
        self.nl_linear = True
        Tf = meas.T_frame
        self.frame_thermal = Tf is not None and bool(np.all(np.isfinite(Tf))) and float(np.ptp(Tf)) >= 0.2
        self.stiffness = np.asarray(cfg.stiffness_N_per_mm, dtype=float)

    # -- applicability ------------------------------------------------------
    def applicable(self, cause: str) -> str | None:
        """None if the cause can be fitted to this data, else the reason it cannot."""
        cause = base_cause(cause)
        if cause == "thermal_expansion":
            if self.T is None:
                return "no temperature columns (T_strut1..6 or T_frame)"
            if not np.all(np.isfinite(self.T)) or float(np.ptp(self.T)) < 0.2:
                return "temperatures vary by less than 0.2 K"
        if cause == "session_offset" and len(self.sessions) < 2:
            return "one session only (no session column or one label)"
        if cause == "elastic_sag" and self.cfg.mass_kg <= 0 and not np.any(self.payload > 0):
            return "no carrier mass and no payload"
        return None


def _sag_basis(ctx: Context, X: np.ndarray, hx_base: np.ndarray, hx_plat: np.ndarray) -> np.ndarray:
    cfg = ctx.cfg
    g = np.asarray(cfg.gravity_mm_s2, dtype=float) * 1e-3
    R, rp, s, L = strut_geometry(hx_base, hx_plat, X)
    u = s / L[..., None]
    Jt = np.concatenate([u, np.cross(rp, u)], axis=2)            # (N,6,6) twist Jacobian
    m = cfg.mass_kg + ctx.payload                                 # (N,) payload at the COG (first order)
    F = m[:, None] * g[None]
    cog = R @ np.asarray(cfg.center_of_gravity_mm, dtype=float)
    tip = R @ np.asarray(cfg.tool.tip_platform_mm, dtype=float)
    M = np.cross(cog, cfg.mass_kg * g[None]) + np.cross(tip, ctx.payload[:, None] * g[None])
    w = np.concatenate([F, M], axis=1)
    f = np.linalg.solve(np.transpose(Jt, (0, 2, 1)), w[..., None])[..., 0]   # tension positive, N
    return (f * 1e-3)[..., None]                                  # mm per (mm/kN)


def cause_model(name: str, ctx: Context) -> CauseModel:
    if name == "elastic_sag":
        return CauseModel(name, ["compliance_mm_per_kN"], "mm/kN", 1.0, True,
                          "strut compliance under the carrier's weight and payload: "
                          "L += compliance * f (f: static strut force, tension positive)",
                          lambda c, X, b, p: _sag_basis(c, X, b, p))
    if name == "elastic_sag_per_strut":
        return CauseModel(name, [f"compliance{i + 1}_mm_per_kN" for i in range(6)], "mm/kN", 1.0, True,
                          "compliance of each strut under the carrier's weight and payload: "
                          "L_i += compliance_i * f_i (a softer strut, a worn joint)",
                          lambda c, X, b, p: _diag(_sag_basis(c, X, b, p)[..., 0]))
    if name == "thermal_expansion_per_strut":
        def thp(c, X, b, p):
            cols = [_diag((c.q + np.asarray(c.cfg.strut_offset_mm)) * (c.T - T_REF_C) * 1e-6)]
            if c.frame_thermal:
                _, _, s_, L = strut_geometry(b, p, X)
                ub = np.einsum("nki,ki->nk", s_ / L[..., None], b)
                cols.append((ub * (c.meas.T_frame[:, None] - T_REF_C) * 1e-6)[..., None])
            return np.concatenate(cols, axis=2)
        names = [f"expansion{i + 1}_ppm_per_K" for i in range(6)] + (
            ["frame_expansion_ppm_per_K"] if ctx.frame_thermal else [])
        return CauseModel(name, names, "ppm/K", 1.0, ctx.frame_thermal,
                          f"growth of each strut L_i += alpha_i * L_i * (T_strut_i - {T_REF_C:g} degC)", thp)
    if name == "thermal_expansion":
        def th(c, X, b, p):
            cols = [((c.q + np.asarray(c.cfg.strut_offset_mm)) * (c.T - T_REF_C) * 1e-6)[..., None]]
            if c.frame_thermal:   # base joints move radially with the frame: b_i *= 1 + beta (T_frame - T_ref)
                _, _, s_, L = strut_geometry(b, p, X)
                u = s_ / L[..., None]
                ub = np.einsum("nki,ki->nk", u, b)
                cols.append((ub * (c.meas.T_frame[:, None] - T_REF_C) * 1e-6)[..., None])
            return np.concatenate(cols, axis=2)
        names = ["expansion_ppm_per_K"] + (["frame_expansion_ppm_per_K"] if ctx.frame_thermal else [])
        return CauseModel(name, names, "ppm/K", 1.0, ctx.frame_thermal,
                          f"strut growth L += alpha * L * (T_strut - {T_REF_C:g} degC)"
                          + ("; base frame growth b_i *= 1 + beta * (T_frame - 20 degC)" if ctx.frame_thermal else ""),
                          th)
    if name == "strut_scale":
        return CauseModel(name, [f"scale{i + 1}_ppm" for i in range(6)], "ppm", 1.0, False,
                          "gain error of each strut reading: L += s_i * q_i",
                          lambda c, X, b, p: _diag(c.q * 1e-6))
    if name == "strut_nonlinearity":
        deg = int(ctx.nl_degree)
        first = 1 if ctx.nl_linear else 2
        orders = list(range(first, deg + 1))

        def nl(c, X, b, p, orders=orders):
            t = (c.q - c.q_center) / c.q_half
            P = np.polynomial.legendre.legvander(t.ravel(), max(orders)).reshape(t.shape + (max(orders) + 1,))
            return np.concatenate([_diag(P[..., k]) for k in orders], axis=2)
        return CauseModel(name, [f"p{k}_strut{i + 1}_mm" for k in orders for i in range(6)],
                          "mm", 1.0, False,
                          "smooth reading-to-length map of each strut: L += sum_k c_k,i P_k(t), Legendre "
                          f"polynomials of degree {first}..{deg} in t = reading normalised over the configured "
                          "stroke (P1 is a gain error: P1 coefficient / half stroke = scale)", nl)
    if name == "backlash":
        return CauseModel(name, [f"half_backlash{i + 1}_mm" for i in range(6)], "mm", 1.0, False,
                          "offset that flips with the approach direction of each strut (row order): "
                          "L += h_i * dir_i", lambda c, X, b, p: _diag(c.direction))
    if name == "session_offset":
        def so(c, X, b, p):
            sess = c.meas.session
            out = np.zeros((c.n, 6, 6 * (len(c.sessions) - 1)))
            for k, lab in enumerate(c.sessions[1:]):
                rows = sess == lab
                for i in range(6):
                    out[rows, i, 6 * k + i] = 1.0
            return out
        return CauseModel(name, [f"session_{lab}_offset{i + 1}_mm" for lab in ctx.sessions[1:] for i in range(6)],
                          "mm", 1.0, False,
                          "strut offsets that move between sessions (re-homing); the first session is the reference",
                          so)
    if name == "joint_offset":
        def jo(c, X, b, p):
            return _joint_offset(c, X, b, p, None)[1]
        return CauseModel(name, [f"base_joint_offset{i + 1}_mm" for i in range(6)]
                          + [f"platform_joint_offset{i + 1}_mm" for i in range(6)], "mm", 1.0, True,
                          "universal joints whose two axes do not meet: the strut pivot sits d_i off the "
                          "joint's first axis a_i (base and platform side), L -= d_i * sqrt(1 - (u_i . a_i)^2) "
                          "to first order (fitted exactly: the drive spans the two pivots)",
                          jo, exact=_joint_offset)
    raise DataError(f"unknown cause {name!r}; known: {', '.join(CAUSES + tuple(VARIANTS.values()))}")


def _joint_offset(c: Context, X, b, p, theta) -> tuple[np.ndarray, np.ndarray]:
    """Exact joint offsets: the pivots sit ``theta`` (base 6, platform 6) along the unit normals n of the
    strut to each joint's first axis; length change ``|s| - |s + th_b n_b + th_p n_p|`` and its
    derivative (theta = 0: ``-sqrt(1 - (u . a)^2)`` per side)."""
    R, _, s, L = strut_geometry(b, p, X)
    nb = s - np.einsum("nki,ki->nk", s, c.joint_axis1)[..., None] * c.joint_axis1[None]
    ap = np.einsum("nij,kj->nki", R, c.joint_axis1_platform)
    npl = s - np.einsum("nki,nki->nk", s, ap)[..., None] * ap
    nb /= np.maximum(np.linalg.norm(nb, axis=2), 1e-12)[..., None]
    npl /= np.maximum(np.linalg.norm(npl, axis=2), 1e-12)[..., None]
    th = np.zeros(12) if theta is None else np.asarray(theta, dtype=float)
    e = s + th[None, :6, None] * nb + th[None, 6:, None] * npl
    Le = np.linalg.norm(e, axis=2)
    return L - Le, np.concatenate([_diag(-np.einsum("nki,nki->nk", e, nb) / Le),
                                   _diag(-np.einsum("nki,nki->nk", e, npl) / Le)], axis=2)


def _diag(v: np.ndarray) -> np.ndarray:
    """(N,6) -> (N,6,6) with v[:, i] in column i of strut i."""
    out = np.zeros(v.shape + (6,))
    idx = np.arange(6)
    out[:, idx, idx] = v
    return out


# ---------------------------------------------------------------------------
# layout
# ---------------------------------------------------------------------------
@dataclass
class Layout:
    """Names, nominal values and prior sigmas of every parameter of one model."""
    names: list[str]
    theta0: np.ndarray
    prior_sigma: np.ndarray          #: inf: no prior
    frame: slice | None
    causes: dict[str, slice]
    cause_models: dict[str, CauseModel]

    @property
    def n(self) -> int:
        return len(self.names)


def build_layout(cfg, ctx: Context, causes=(), frame: np.ndarray | None = None, prior_joint_mm: float = 5.0,
                 prior_offset_mm: float = 50.0) -> Layout:
    hx = Hexapod(cfg)
    names = list(PARAM_NAMES)
    theta0 = [hx.parameters()]
    sig = [np.r_[np.full(36, prior_joint_mm), np.full(6, prior_offset_mm)]]
    fr = None
    if frame is not None:
        fr = slice(len(names), len(names) + 12)
        names += list(FRAME_NAMES)
        theta0.append(np.asarray(frame, dtype=float))
        sig.append(np.r_[np.full(3, 1e4), np.full(3, 10.0), np.full(3, 1e4), np.full(3, 10.0)])
    cs: dict[str, slice] = {}
    cms: dict[str, CauseModel] = {}
    for c in causes:
        cm = cause_model(c, ctx)
        cs[c] = slice(len(names), len(names) + len(cm.names))
        cms[c] = cm
        names += cm.names
        theta0.append(np.zeros(len(cm.names)))
        sig.append(np.full(len(cm.names), 1e6))
    return Layout(names, np.concatenate(theta0), np.concatenate(sig), fr, cs, cms)


# ---------------------------------------------------------------------------
# evaluation
# ---------------------------------------------------------------------------
class Evaluator:
    """Residuals and Jacobian of one (layout, measurement set); caches the FK poses."""

    def __init__(self, cfg, layout: Layout, ctx: Context, X_init: np.ndarray | None = None):
        self.cfg = cfg
        self.lay = layout
        self.ctx = ctx
        home = np.array(cfg.home_pose, dtype=float)
        home[3:] = np.radians(home[3:])
        self.X = np.tile(home, (ctx.n, 1)) if X_init is None else np.array(X_init, dtype=float)
        self.converged = np.ones(ctx.n, dtype=bool)
        self._key = None

    def split(self, theta):
        th = np.asarray(theta, dtype=float)
        base = th[:18].reshape(6, 3)
        plat = th[18:36].reshape(6, 3)
        off = th[36:42]
        frame = th[self.lay.frame] if self.lay.frame is not None else None
        return base, plat, off, frame

    def lengths_from_readings(self, theta, X) -> tuple[np.ndarray, dict]:
        """Strut lengths (N,6) of the readings at poses X and each cause's derivative d L / d theta_c."""
        base, plat, off, _ = self.split(theta)
        L = off[None] + self.ctx.q
        B = {}
        for c, sl in self.lay.causes.items():
            cm = self.lay.cause_models[c]
            if cm.exact is not None:
                dl, B[c] = cm.exact(self.ctx, X, base, plat, theta[sl])
                L = L + dl
            else:
                B[c] = cm.build(self.ctx, X, base, plat)
                L = L + np.einsum("nik,k->ni", B[c], theta[sl])
        return L, B

    def poses(self, theta) -> np.ndarray:
        base, plat, _, _ = self.split(theta)
        xdep = any(cm.x_dependent for cm in self.lay.cause_models.values())
        X = self.X
        # pose-dependent causes: to the fixed point, not a set count (it contracts linearly, by ~0.25 per pass
        # with joint offsets of 50 mm: 20 passes to 1e-9; 12 passes left such poses 1e-5 mm off their lengths)
        for _ in range(MAX_FIXED_POINT_PASSES if xdep else 1):
            L, _ = self.lengths_from_readings(theta, X)
            X_prev, (X, conv) = X, forward_batch(base, plat, L, X)
            if float(np.max(np.abs(X - X_prev), initial=0.0)) < 1e-9:
                break
        bad = ~conv
        if bad.any():   # restart failed rows from home
            home = np.array(self.cfg.home_pose, dtype=float)
            home[3:] = np.radians(home[3:])
            L, _ = self.lengths_from_readings(theta, X)
            X2, conv2 = forward_batch(base, plat, L[bad], np.tile(home, (int(bad.sum()), 1)))
            X[bad] = X2
            conv[bad] = conv2
        self.converged = conv
        return X

    def evaluate(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residual vector (measured coordinates, then priors) and its Jacobian."""
        theta = np.asarray(theta, dtype=float)
        X = self.poses(theta)
        self.X = X
        base, plat, off, frame = self.split(theta)
        ypred = measure(X, frame)
        r = ypred - self.ctx.y
        r[:, 3:] = (r[:, 3:] + 180.0) % 360.0 - 180.0
        r = r / self.ctx.sigma
        r[~self.ctx.mask] = 0.0
        r[~self.converged] = 1e3   # unreachable under these parameters
        # Jacobian: dX/dtheta = -J^-1 dg/dtheta,  g = L(X) - L_readings
        hx = Hexapod.from_parameters(self.cfg, theta[:42])
        Xdeg = X.copy()
        Xdeg[:, 3:] = np.degrees(Xdeg[:, 3:])
        G = np.zeros((self.ctx.n, 6, self.lay.n))
        G[:, :, :42] = reading_parameter_jacobian(hx, Xdeg)
        _, B = self.lengths_from_readings(theta, X)
        for c, sl in self.lay.causes.items():
            G[:, :, sl] = -B[c]
        _, rp, s, L = strut_geometry(base, plat, X)
        J = jacobian_batch(rp, s / L[..., None], X)
        dX = -np.linalg.solve(J, G)                        # (N,6,P)
        # dy/dX and dy/dframe: analytic without a frame, else central differences in one batched call
        n = self.ctx.n
        if frame is None:
            Jy = dX.copy()
            Jy[:, 3:] = np.degrees(Jy[:, 3:])
        else:
            hX = np.array([1e-6] * 3 + [1e-8] * 3)
            Xs = np.repeat(X[None], 12, axis=0)
            for j in range(6):
                Xs[2 * j, :, j] += hX[j]
                Xs[2 * j + 1, :, j] -= hX[j]
            hF = np.array(([1e-6] * 3 + [1e-8] * 3) * 2)
            Fs = np.repeat(frame[None], 24, axis=0)
            for j in range(12):
                Fs[2 * j, j] += hF[j]
                Fs[2 * j + 1, j] -= hF[j]
            Xall = np.concatenate([Xs.reshape(-1, 6), np.tile(X, (24, 1))])
            Fall = np.concatenate([np.tile(frame, (12 * n, 1)), np.repeat(Fs, n, axis=0)])
            Y = measure(Xall, Fall)
            YX = Y[:12 * n].reshape(6, 2, n, 6)
            dY = YX[:, 0] - YX[:, 1]
            dY[..., 3:] = (dY[..., 3:] + 180.0) % 360.0 - 180.0
            dydX = np.transpose(dY / (2 * hX)[:, None, None], (1, 2, 0))      # (N,6,6)
            Jy = np.einsum("nij,njp->nip", dydX, dX)
            YF = Y[12 * n:].reshape(12, 2, n, 6)
            dF = YF[:, 0] - YF[:, 1]
            dF[..., 3:] = (dF[..., 3:] + 180.0) % 360.0 - 180.0
            Jy[:, :, self.lay.frame] = np.transpose(dF / (2 * hF)[:, None, None], (1, 2, 0))
        Jy = Jy / self.ctx.sigma[None, :, None]
        Jy[~self.ctx.mask] = 0.0
        Jy[~self.converged] = 0.0
        m = self.ctx.mask.ravel()
        rv = r.ravel()[m]
        Jv = Jy.reshape(-1, self.lay.n)[m]
        pri = np.isfinite(self.lay.prior_sigma)
        rp_ = (theta[pri] - self.lay.theta0[pri]) / self.lay.prior_sigma[pri]
        Jp = np.zeros((int(pri.sum()), self.lay.n))
        Jp[np.arange(int(pri.sum())), np.where(pri)[0]] = 1.0 / self.lay.prior_sigma[pri]
        return np.concatenate([rv, rp_]), np.vstack([Jv, Jp])

    def n_data(self) -> int:
        return int(self.ctx.mask.sum())

    # -- reporting ------------------------------------------------------------
    def residuals(self, theta) -> dict:
        """Unwhitened residuals: coordinates (N,6) mm/deg (NaN unmeasured) and struts (N,6) (NaN w/o full pose)."""
        theta = np.asarray(theta, dtype=float)
        X = self.poses(theta)
        self.X = X
        base, plat, off, frame = self.split(theta)
        r = measure(X, frame) - self.ctx.meas.y
        r[:, 3:] = (r[:, 3:] + 180.0) % 360.0 - 180.0
        full = self.ctx.meas.full_pose_rows()
        rs = np.full((self.ctx.n, 6), np.nan)
        if full.any():
            Xb = unmeasure(self.ctx.meas.y[full], frame)
            _, _, _, Lm = strut_geometry(base, plat, Xb)
            Lq, _ = self.lengths_from_readings(theta, Xb if len(Xb) == self.ctx.n else _fill(X, full, Xb))
            rs[full] = Lm - Lq[full]
        return {"coords": r, "struts": rs, "poses": X}


def _fill(X, full, Xb):
    out = X.copy()
    out[full] = Xb
    return out


def rms_summary(res: dict) -> dict:
    """R = {position_mm, orientation_deg, strut_mm}: RMS per row over measured coordinates; null where absent."""
    r = res["coords"]
    out = {}
    for key, sl in (("position_mm", slice(0, 3)), ("orientation_deg", slice(3, 6))):
        part = r[:, sl]
        m = np.isfinite(part)
        rows = m.any(axis=1)
        out[key] = float(np.sqrt(np.nansum(part[rows] ** 2) / rows.sum())) if rows.any() else None
    s = res["struts"]
    fin = np.isfinite(s)
    out["strut_mm"] = float(np.sqrt(np.mean(s[fin] ** 2))) if fin.any() else None
    return out


def _project_rotation(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    return U @ np.diag([1.0, 1.0, d]) @ Vt


def initial_frame(cfg, meas: Measurements) -> np.ndarray:
    """Rough registration (12) from full-pose rows: Kabsch of nominal FK positions onto measured ones."""
    hx = Hexapod(cfg)
    full = meas.full_pose_rows()
    if full.sum() < 3:
        raise DataError(f"{meas.path}: registering the measurement frame needs at least 3 full-pose rows "
                        f"(x,y,z and orientation), got {int(full.sum())}")
    home = np.array(cfg.home_pose, dtype=float)
    home[3:] = np.radians(home[3:])
    L = meas.q[full] + hx.offset
    X, _ = forward_batch(hx.base, hx.plat, L, np.tile(home, (int(full.sum()), 1)))
    y = meas.y[full]
    Rm = matrices_from_euler(np.radians(y[:, 3:]))
    RX = matrices_from_euler(X[:, 3:])
    P, Q = X[:, :3], y[:, :3]
    spread = np.linalg.svd(P - P.mean(0), compute_uv=False)
    if spread[1] > 1.0:   # positions span at least a plane: Kabsch
        H = (P - P.mean(0)).T @ (Q - Q.mean(0))
        Rr = _project_rotation(H.T)
    else:                 # orientation average (target assumed aligned)
        Rr = _project_rotation(np.einsum("nij,nkj->ik", Rm, RX))
    tr = Q.mean(0) - Rr @ P.mean(0)
    Rt = _project_rotation(np.einsum("nji,jk,nkl->il", RX, Rr.T, Rm))
    tt = np.mean(np.einsum("nji,nj->ni", RX, (Q - tr) @ Rr - P), axis=0)
    ar = euler_from_matrices(Rr[None])[0]
    at = euler_from_matrices(Rt[None])[0]
    return np.r_[tr, ar, tt, at]
