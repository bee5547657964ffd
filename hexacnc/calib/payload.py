"""Payload mass and centre of gravity from drive torques at rest poses.

At rest the drives hold the static strut forces (:mod:`hexacnc.sag`): with the
twist Jacobian ``J_t`` at the pose, ``J_t^T f = w`` where ``w`` is the gravity
wrench of the carrier (known: ``[carrier]``) plus the payload's.  The payload's
wrench is linear in its mass ``m`` and first moment ``h = m c`` (``c`` its centre
of gravity, platform frame)::

    w_p = [m g ; (R c) x m g] = [g m ; -[g]x R h]

so each rest pose gives six equations ``f - J_t^-T w_carrier = J_t^-T w_p(m, h)``
in four unknowns (plus, optionally, one torque offset per drive).  Forces come
from the drive torque (0x6077, per mille of rated torque) times
``force_N_per_permille`` (screw lead, gear, rated torque).

Noise model (simulation and the least-squares weights, documented in
docs/calibration.md): reading = f / k + offset_i + friction + noise, with
``noise`` Gaussian (``noise_permille``, current ripple and quantisation),
``friction`` the screw's static friction left at rest, uniform in
``+-friction_N`` (the side depends on the last approach), and a constant
offset per drive (``offset_permille`` spread).  Friction is the dominant
error; averaging over many rest poses reduces it like noise.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import DataError
from ..kinematics import Hexapod
from ..pose import matrix_from_euler
from .model import strut_geometry
from .synth import sample_poses


@dataclass
class DriveTorqueModel:
    force_N_per_permille: float = 10.0    #: strut force per per-mille of rated torque (N)
    noise_permille: float = 1.0           #: Gaussian reading noise (1 sigma)
    friction_N: float = 20.0              #: static friction left at rest: uniform in +- this (N)
    offset_permille: float = 0.5          #: spread of the constant per-drive torque offset (1 sigma)
    rest_samples: int = 1                 #: readings averaged per rest pose (the noise, not the friction, averages)

    def rest_sigma_N(self) -> float:
        """1-sigma error of one strut force at one rest pose: averaged noise and the static friction."""
        return math.sqrt((self.noise_permille * self.force_N_per_permille) ** 2 / max(1, self.rest_samples)
                         + self.friction_N ** 2 / 3.0)


@dataclass
class PayloadResult:
    mass_kg: float
    mass_std_kg: float
    cog_platform_mm: np.ndarray
    cog_std_mm: np.ndarray
    rest_poses: int
    residual_rms_N: float
    offsets_permille: np.ndarray | None = None
    extra: dict = field(default_factory=dict)


def rest_forces(hx: Hexapod, poses_deg: np.ndarray, payload_kg: float = 0.0, payload_cog_mm=None) -> np.ndarray:
    """(N,6) static strut forces (N, tension positive) at poses (batched :func:`hexacnc.sag.strut_forces_N`;
    the payload at ``payload_cog_mm``, platform frame, default the tool tip)."""
    cfg = hx.cfg
    P = np.asarray(poses_deg, dtype=float).reshape(-1, 6)
    X = P.copy()
    X[:, 3:] = np.radians(X[:, 3:])
    R, rp, s, L = strut_geometry(hx.base, hx.plat, X)
    u = s / L[..., None]
    Jt = np.concatenate([u, np.cross(rp, u)], axis=2)
    g = np.asarray(cfg.gravity_mm_s2, dtype=float) * 1e-3
    F = np.tile((cfg.mass_kg + payload_kg) * g, (len(P), 1))
    M = np.cross(R @ np.asarray(cfg.center_of_gravity_mm, dtype=float), cfg.mass_kg * g)
    if payload_kg:
        pp = np.asarray(cfg.tool.tip_platform_mm if payload_cog_mm is None else payload_cog_mm, dtype=float)
        M = M + np.cross(R @ pp, payload_kg * g)
    w = np.concatenate([F, M], axis=1)
    return np.linalg.solve(np.transpose(Jt, (0, 2, 1)), w[..., None])[..., 0]


def simulate_torques(hx: Hexapod, poses_deg, payload_kg: float, payload_cog_mm, model: DriveTorqueModel,
                     rng: np.random.Generator, offsets_permille: np.ndarray | None = None) -> np.ndarray:
    """(N,6) torque readings (per mille of rated torque) at rest poses under the noise model; the drives'
    constant offsets are drawn unless given (give the same ones for recordings of the same drives)."""
    f = rest_forces(hx, poses_deg, payload_kg, payload_cog_mm)
    off = rng.normal(0.0, model.offset_permille, 6) if offsets_permille is None else offsets_permille
    fric = rng.uniform(-model.friction_N, model.friction_N, f.shape)
    noise = rng.normal(0.0, model.noise_permille / math.sqrt(max(1, model.rest_samples)), f.shape)
    return (f + fric) / model.force_N_per_permille + off[None] + noise


def _design(hx: Hexapod, poses_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pose: forces of the carrier alone (N,6) and d(force)/d(m, h_x, h_y, h_z) (N,6,4) (batched)."""
    P = np.asarray(poses_deg, dtype=float).reshape(-1, 6)
    g = np.asarray(hx.cfg.gravity_mm_s2, dtype=float) * 1e-3
    gx = np.array([[0.0, -g[2], g[1]], [g[2], 0.0, -g[0]], [-g[1], g[0], 0.0]])
    X = np.column_stack([P[:, :3], np.radians(P[:, 3:])])
    R, rp, s, L = strut_geometry(hx.base, hx.plat, X)
    u = s / L[..., None]
    JtT = np.transpose(np.concatenate([u, np.cross(rp, u)], axis=2), (0, 2, 1))
    W = np.zeros((len(P), 6, 4))
    W[:, :3, 0] = g
    W[:, 3:, 1:] = -np.einsum("ij,njk->nik", gx, R)
    return rest_forces(hx, P), np.linalg.solve(JtT, W)


def identify_payload(hx: Hexapod, poses_deg, torques_permille, model: DriveTorqueModel,
                     fit_offsets: bool = True, tare: tuple | None = None) -> PayloadResult:
    """Payload mass and COG (platform frame) from torques at rest poses (least squares).

    ``tare``: (poses, torques) at rest without the payload (the carrier alone): the drives' torque
    offsets are then fitted on both sets together, which separates them from the payload (a payload's
    force pattern changes little with the pose, so offsets alone would absorb much of it).
    """
    P = np.asarray(poses_deg, dtype=float)
    T = np.asarray(torques_permille, dtype=float)
    n_pay = len(P)
    if tare is not None:
        P = np.vstack([P, np.asarray(tare[0], dtype=float)])
        T = np.vstack([T, np.asarray(tare[1], dtype=float)])
    if P.ndim != 2 or P.shape[1] != 6 or T.shape != P.shape:
        raise DataError(f"payload identification: poses {P.shape} and torques {T.shape} must both be (N, 6)")
    ok = np.all(np.isfinite(T), axis=1) & np.all(np.isfinite(P), axis=1)
    n_min = 4 if fit_offsets else 2
    if ok[:n_pay].sum() < n_min:
        raise DataError(f"payload identification needs at least {n_min} rest poses with torques, "
                        f"got {int(ok[:n_pay].sum())}")
    f0, D = _design(hx, P)
    D[n_pay:] = 0.0                    # the tare rows carry no payload
    P, T, f0, D = P[ok], T[ok], f0[ok], D[ok]
    y = (T * model.force_N_per_permille - f0).reshape(-1)
    A = D.reshape(-1, 4)
    if fit_offsets:
        A = np.hstack([A, np.tile(np.eye(6) * model.force_N_per_permille, (len(P), 1))])
    sig = model.rest_sigma_N()
    sol, *_ = np.linalg.lstsq(A, y, rcond=None)
    r = y - A @ sol
    dof = max(1, len(y) - A.shape[1])
    s_est = max(sig, float(np.sqrt(r @ r / dof)))
    C = np.linalg.pinv(A.T @ A) * s_est ** 2
    sd = np.sqrt(np.maximum(np.diag(C), 0.0))
    m, cog, cog_sd = _mass_cog(sol, C)
    return PayloadResult(m, float(sd[0]), cog, cog_sd, int(ok[:n_pay].sum()), float(np.sqrt(np.mean(r ** 2))),
                         sol[4:] if fit_offsets else None)


def _mass_cog(sol, C):
    """Mass ``sol[0]`` (kg), COG ``h / m`` from the first moments ``h = sol[1:4]`` (kg mm), and the COG's
    standard deviations by first-order propagation of the (m, h) block of the covariance ``C``."""
    m, h = float(sol[0]), sol[1:4]
    cog = h / m if abs(m) > 1e-9 else np.full(3, np.nan)
    Jc = np.zeros((3, 4))
    if abs(m) > 1e-9:
        Jc[:, 0] = -h / m ** 2
        Jc[:, 1:] = np.eye(3) / m
    return m, cog, np.sqrt(np.maximum(np.diag(Jc @ C[:4, :4] @ Jc.T), 0.0))


def identify_payload_in_motion(hx: Hexapod, poses_deg, torques_permille, velocity_mm_s, acceleration_mm_s2,
                               model: DriveTorqueModel, min_speed_mm_s: float = 1.0) -> PayloadResult:
    """Payload mass and COG from torques sampled *while moving* (the drives' torque TPDO3,
    ``[bus] torque_pdo_every``): per sample and strut ``k T = f_carrier(pose) + D(pose) (m, h) + c_i sign(v_i)
    + b_i v_i + j_i a_i`` with each strut's Coulomb ``c_i``, viscous ``b_i`` and lumped inertia ``j_i`` as
    nuisance parameters (22 unknowns); samples of a strut slower than ``min_speed_mm_s`` are left out (its
    static friction is unknown).  ``velocity_mm_s`` / ``acceleration_mm_s2``: (N,6) strut rates (from the
    commanded lengths).  No torque offsets: give rest poses with a tare to :func:`identify_payload` for those."""
    P = np.asarray(poses_deg, dtype=float).reshape(-1, 6)
    T = np.asarray(torques_permille, dtype=float).reshape(-1, 6)
    V = np.asarray(velocity_mm_s, dtype=float).reshape(-1, 6)
    Acc = np.asarray(acceleration_mm_s2, dtype=float).reshape(-1, 6)
    if not (len(P) == len(T) == len(V) == len(Acc)):
        raise DataError(f"payload in motion: poses {P.shape}, torques {T.shape}, velocities {V.shape} and "
                        f"accelerations {Acc.shape} must have the same rows")
    use = np.isfinite(T) & (np.abs(V) >= min_speed_mm_s) & np.isfinite(Acc) & np.all(np.isfinite(P), axis=1)[:, None]
    rows = np.where(use.any(axis=1))[0]
    if use.sum() < 60:
        raise DataError(f"payload identification in motion needs at least 60 strut samples while moving with "
                        f"torques, got {int(use.sum())}")
    f0, D = _design(hx, P[rows])
    u = use[rows]
    k = model.force_N_per_permille
    n_eq = int(u.sum())
    A = np.zeros((n_eq, 22))
    y = np.zeros(n_eq)
    r_idx, s_idx = np.nonzero(u)
    A[:, :4] = D[r_idx, s_idx]
    A[np.arange(n_eq), 4 + s_idx] = np.sign(V[rows][r_idx, s_idx])
    A[np.arange(n_eq), 10 + s_idx] = V[rows][r_idx, s_idx]
    A[np.arange(n_eq), 16 + s_idx] = Acc[rows][r_idx, s_idx] * 1e-3
    y[:] = T[rows][r_idx, s_idx] * k - f0[r_idx, s_idx]
    sol, *_ = np.linalg.lstsq(A, y, rcond=None)
    r = y - A @ sol
    s_est = float(np.sqrt(r @ r / max(1, n_eq - 22)))
    C = np.linalg.pinv(A.T @ A) * s_est ** 2
    sd = np.sqrt(np.maximum(np.diag(C), 0.0))
    m, cog, cog_sd = _mass_cog(sol, C)
    return PayloadResult(m, float(sd[0]), cog, cog_sd, 0, float(np.sqrt(np.mean(r ** 2))), None,
                         {"samples": int(len(rows)), "strut_samples": n_eq, "coulomb_N": sol[4:10].tolist(),
                          "viscous_N_s_per_mm": sol[10:16].tolist(), "inertia_kg": sol[16:22].tolist()})


def plan_rest_poses(cfg, n: int, seed: int = 0, candidates: int = 2000, offsets: bool = True) -> np.ndarray:
    """n rest poses (mm/deg) for :func:`identify_payload`, greedily chosen from random reachable candidates
    to minimise the variance of the payload mass (its COG and, with ``offsets``, the drives' torque
    offsets as nuisance parameters; the offsets' own information comes from a tare set, which does not
    depend on its poses).  The mass shows in the total strut force: poses where the struts lean more carry
    more force per kilogram, and a spread of orientations separates the mass from the offsets and the COG.
    """
    if n < 4:
        raise DataError(f"payload rest poses: at least 4 needed, asked for {n}")
    hx = Hexapod(cfg)
    C = sample_poses(cfg, np.random.default_rng(seed), max(candidates, 2 * n))
    _, D = _design(hx, C)                                    # (K,6,4) force per (m, h)
    k = 10 if offsets else 4
    blocks = np.zeros((len(C), 6, k))
    blocks[:, :, :4] = D
    if offsets:
        blocks[:, :, 4:] = np.eye(6)[None]
    info = np.einsum("kia,kib->kab", blocks, blocks)         # per candidate: its information (k,k)
    A = 1e-6 * np.eye(k)
    if offsets:
        A[4:, 4:] += np.eye(6) * 60.0                        # a tare set of the order of 60 rest poses
    chosen = np.zeros(len(C), dtype=bool)
    for _ in range(n):
        var = np.linalg.inv(A[None] + info)[:, 0, 0]
        var[chosen] = np.inf
        j = int(np.argmin(var))
        chosen[j] = True
        A = A + info[j]
    return C[chosen]


def carrier_update(cfg, res: PayloadResult, current_payload_kg: float = 0.0) -> dict:
    """Proposed ``[carrier]`` (carrier + payload as one body) and the payload's effect on sag."""
    m_c = float(cfg.mass_kg)
    c_c = np.asarray(cfg.center_of_gravity_mm, dtype=float)
    m_t = m_c + res.mass_kg
    cog_t = (m_c * c_c + res.mass_kg * res.cog_platform_mm) / m_t if m_t > 0 else c_c
    hx = Hexapod(cfg)
    home = np.asarray(cfg.home_pose, dtype=float)
    d = (sag_tip_deviation(hx, home, res.mass_kg, res.cog_platform_mm)
         - sag_tip_deviation(hx, home, current_payload_kg, None))
    return {"carrier": {"mass_kg": round(m_t, 3), "center_of_gravity_mm": [round(float(v), 2) for v in cog_t]},
            "payload": {"mass_kg": res.mass_kg, "center_of_gravity_mm": res.cog_platform_mm.tolist()},
            "toml": (f"[carrier]\nmass_kg = {m_t:.3f}\ncenter_of_gravity_mm = "
                     f"[{', '.join(f'{v:.2f}' for v in cog_t)}]\n"),
            "sag_change_at_home": {"pose_deviation": [float(v) for v in d],
                                   "position_um": float(np.linalg.norm(d[:3]) * 1000.0),
                                   "note": "tool-tip deviation (x, y, z mm, then the platform rotation a, b, c "
                                           "deg) under the identified payload minus under the one the current "
                                           "model assumes, uncompensated, at the home pose (first order)"}}


def sag_tip_deviation(hx: Hexapod, pose_deg, payload_kg: float, payload_cog_mm) -> np.ndarray:
    """First-order tool-tip deviation (x, y, z mm; rotation deg) of the uncompensated machine under its
    weight and a payload: strut elongations ``f / k`` through the inverse twist Jacobian."""
    P = np.asarray(pose_deg, dtype=float)
    e = rest_forces(hx, P[None], payload_kg, payload_cog_mm)[0] / np.asarray(hx.cfg.stiffness_N_per_mm, dtype=float)
    X = np.r_[P[:3], np.radians(P[3:])]
    tw = np.linalg.solve(hx.jacobian_twist_rad(X), e)          # (v mm, omega rad) at the platform origin
    tip = matrix_from_euler(X[3], X[4], X[5]) @ np.asarray(hx.cfg.tool.tip_platform_mm, dtype=float)
    return np.r_[tw[:3] + np.cross(tw[3:], tip), np.degrees(tw[3:])]
