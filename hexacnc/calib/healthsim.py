"""Seeded synthetic recordings of a running machine with hidden model drift (tests and benchmarks).

Moves between random poses (smooth rest-to-rest, then a rest), sampled at
``rate_hz``.  The drives see the static strut forces of the carrier and the
*true* payload (:func:`hexacnc.sag.strut_forces_N`), Coulomb and viscous
friction (at rest: a static friction held for the whole rest), the torque noise model of :class:`~hexacnc.calib.payload.DriveTorqueModel`;
the following error carries the friction through the servo stiffness and the
unmodelled compliance of each strut (``f_i * extra_compliance_i``).  Strut
temperatures ramp by ``temperature_rise_K``; the cycle applies the thermal
offsets only when ``thermal_compensated``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..kinematics import Hexapod
from .payload import DriveTorqueModel, rest_forces
from .recording import Recording, empty_like_signals
from .synth import sample_poses


@dataclass
class Drift:
    payload_kg: float = 0.0                     #: true payload (the model assumes ``assumed_payload_kg``)
    payload_cog_mm: tuple = (0.0, 0.0, -150.0)  #: platform frame
    assumed_payload_kg: float = 0.0
    friction_N: tuple = (60.0,) * 6             #: Coulomb friction per strut while moving
    extra_compliance_mm_per_kN: tuple = (0.0,) * 6
    temperature_rise_K: float = 0.0
    thermal_compensated: bool = True
    torque: DriveTorqueModel = field(default_factory=DriveTorqueModel)
    torque_offsets_permille: tuple = (0.4, -0.3, 0.6, -0.5, 0.2, -0.1)   #: the drives' constant offsets
    servo_N_per_mm: float = 2.0e5               #: position loop stiffness seen by the friction
    follow_noise_mm: float = 0.0005
    viscous_N_s_per_mm: float = 0.5


def _profile(n_moves: int, move_s: float, rest_s: float, rate_hz: float, rng, cfg, rest_poses=None):
    if rest_poses is None:
        P = sample_poses(cfg, rng, n_moves + 1, shrink=0.8)
    else:
        P = np.vstack([np.asarray(cfg.home_pose, dtype=float)[None], np.asarray(rest_poses, dtype=float)])
        n_moves = len(P) - 1
    segs = []
    for k in range(n_moves):
        tm = np.arange(0.0, move_s, 1.0 / rate_hz) / move_s
        s = tm ** 3 * (10 - 15 * tm + 6 * tm ** 2)
        segs.append(P[k] + s[:, None] * (P[k + 1] - P[k]))
        segs.append(np.repeat(P[k + 1][None], int(rest_s * rate_hz), axis=0))
    return np.vstack(segs)


def simulate(cfg, seed: int, drift: Drift, n_moves: int = 40, move_s: float = 0.8, rest_s: float = 0.6,
             rate_hz: float = 100.0, rest_poses=None) -> Recording:
    """``rest_poses`` (mm/deg): the poses to stop at, in order, from home (default: ``n_moves`` random ones)."""
    rng = np.random.default_rng(seed)
    hx = Hexapod(cfg)
    poses = _profile(n_moves, move_s, rest_s, rate_hz, rng, cfg, rest_poses)
    n = len(poses)
    L = hx.inverse_batch(poses)
    v = np.gradient(L, 1.0 / rate_hz, axis=0)
    f = rest_forces(hx, poses, drift.payload_kg, np.asarray(drift.payload_cog_mm))
    tm = drift.torque
    moving = np.abs(v) > 1e-3
    fr = np.asarray(drift.friction_N, dtype=float)[None]
    # static friction at rest: one value per strut and rest, held until the strut moves again
    rest_no = np.cumsum(np.vstack([np.zeros((1, 6), dtype=bool), moving[:-1] & ~moving[1:]]), axis=0)
    stat = np.take_along_axis(rng.uniform(-tm.friction_N, tm.friction_N, (int(rest_no.max()) + 1, 6)), rest_no, 0)
    fric = np.where(moving, fr * np.sign(v) + drift.viscous_N_s_per_mm * v, stat)
    off = np.asarray(drift.torque_offsets_permille, dtype=float)
    torque = (f + fric) / tm.force_N_per_permille + off[None] + rng.normal(0.0, tm.noise_permille, (n, 6))
    comp = np.asarray(drift.extra_compliance_mm_per_kN, dtype=float)[None] * 1e-3
    follow = fric / drift.servo_N_per_mm + f * comp + rng.normal(0.0, drift.follow_noise_mm, (n, 6))
    t = np.arange(n) / rate_hz
    T = 20.0 + drift.temperature_rise_K * (t / t[-1])[:, None] * rng.uniform(0.8, 1.2, 6)[None]
    alpha = cfg.thermal.expansion_per_K
    growth = alpha * L * (T - 20.0)
    d = empty_like_signals(n)
    d["t_s"] = t
    d["t_loop_s"] = t
    d["drives_enabled"] = np.ones(n)
    d["struts_cmd_mm"] = L
    d["struts_act_mm"] = L - follow
    d["following_error_mm"] = follow
    d["torque_permille"] = torque
    d["temperature_C"] = T
    d["thermal_offsets_mm"] = growth if drift.thermal_compensated else np.zeros_like(growth)
    d["pose_cmd"] = poses
    d["pose_act"] = poses
    d["fk_residual_mm"] = np.zeros(n)
    d["payload_kg"] = np.full(n, drift.assumed_payload_kg)
    meta = {"source": "hexacnc.calib.healthsim", "seed": seed, "rate_hz": rate_hz,
            "torque_force_N_per_permille": tm.force_N_per_permille}
    return Recording(d, meta)
