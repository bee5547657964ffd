"""Nonlinear rigid-body time simulation of the machine (check of the linearised model).

Independent of :class:`hexacnc.sim.dynamics.CoupledModel`'s matrices: the carrier
is a rigid body (COG position, rotation matrix, velocity, angular velocity with
the gyroscopic term), strut lengths and directions come from the exact geometry
every evaluation (the Jacobian is never formed), the drives run the same cascade
(holding their position), integration by classic RK4.  Used for the ring-down
test: start in one eigenvector of the linear model, fit a damped sinusoid to
the response, compare frequency and damping with the eigenvalue.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import curve_fit

from ..pose import matrix_from_axis_angle, pose_to_rad, matrix_from_euler
from .dynamics import IF, IQ, IQD, IV, IY, IZ, CoupledModel, Gains


class NonlinearMachine:
    """State: drives ``q, qd, z, F`` (6 each), carrier ``p_cog`` (3), ``R`` (3x3), ``v`` (3), ``w`` (3)."""

    def __init__(self, model: CoupledModel, gains: Gains, pose_deg):
        self.m = model
        self.g = gains
        hx = model.hx
        X = pose_to_rad(pose_deg)
        self.R0 = matrix_from_euler(*X[3:])
        self.p0 = X[:3] + self.R0 @ model.cog
        self.arm_plat = hx.plat - model.cog          # joints relative to the COG, platform frame
        self.base = hx.base
        self.L0 = hx.lengths(pose_deg)               # unstressed lengths: q = L0 at rest
        self.k = model.k
        self.c = model.c
        self.I = model.I_plat
        self.mc = model.mc

    def deriv(self, s: dict) -> dict:
        m, g = self.m, self.g
        R = s["R"]
        arm = self.arm_plat @ R.T
        d = s["p"] + arm - self.base
        L = np.linalg.norm(d, axis=1)
        u = d / L[:, None]
        vj = s["v"] + np.cross(s["w"], arm)
        Ld = np.einsum("ij,ij->i", u, vj)
        f = self.k * (s["q"] - L) + self.c * (s["qd"] - Ld)
        verr = g.kp_1_s * (self.L0 - s["q"]) - s["qd"]
        Fcmd = g.kv_N_s_mm * verr + g.kv_N_s_mm / g.tn_s * s["z"]
        force = f @ u
        moment = np.einsum("ij,i->j", np.cross(arm, u), f)
        Iw = R @ self.I @ R.T
        wd = np.linalg.solve(Iw, moment - np.cross(s["w"], Iw @ s["w"]))
        W = np.array([[0.0, -s["w"][2], s["w"][1]], [s["w"][2], 0.0, -s["w"][0]], [-s["w"][1], s["w"][0], 0.0]])
        return {"q": s["qd"], "qd": (s["F"] - f) / m.md, "z": verr, "F": (Fcmd - s["F"]) / m.tau,
                "p": s["v"], "R": W @ R, "v": force / self.mc, "w": wd}

    def from_linear(self, x: np.ndarray) -> dict:
        """Nonlinear state from a linear deviation state (36,) about the pose."""
        Y = x[IY]
        ang = float(np.linalg.norm(Y[3:]))
        Rd = matrix_from_axis_angle(Y[3:] / ang, ang) if ang > 0 else np.eye(3)
        return {"q": self.L0 + x[IQ], "qd": x[IQD].copy(), "z": x[IZ].copy(), "F": x[IF].copy(),
                "p": self.p0 + Y[:3], "R": Rd @ self.R0, "v": x[IV][:3].copy(), "w": x[IV][3:].copy()}

    def simulate(self, s: dict, duration_s: float, h: float = 2e-5, every: int = 5):
        """RK4; returns times and tool-tip displacement (N,3) in mm."""
        n = int(round(duration_s / h))
        tip_arm = self.m.tip - self.m.cog
        tip0 = self.p0 + self.R0 @ tip_arm
        ts, tips = [], []
        for k in range(n + 1):
            if k % every == 0:
                ts.append(k * h)
                tips.append(s["p"] + s["R"] @ tip_arm - tip0)
            if k == n:
                break
            k1 = self.deriv(s)
            k2 = self.deriv(_axpy(s, k1, h / 2))
            k3 = self.deriv(_axpy(s, k2, h / 2))
            k4 = self.deriv(_axpy(s, k3, h))
            s = {key: s[key] + h / 6 * (k1[key] + 2 * k2[key] + 2 * k3[key] + k4[key]) for key in s}
            U, _, Vt = np.linalg.svd(s["R"])
            s["R"] = U @ Vt
        return np.array(ts), np.array(tips)


def _axpy(s, d, h):
    return {k: s[k] + h * d[k] for k in s}


def _damped(t, a, sigma, w, phi, off):
    return a * np.exp(-sigma * t) * np.cos(w * t + phi) + off


def fit_ringdown(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Frequency (Hz) and damping ratio of a damped sinusoid fitted to ``y(t)``.

    The start value comes from the FFT peak and the log decrement of the
    envelope, not from the model.
    """
    y = np.asarray(y, dtype=float)
    dt = t[1] - t[0]
    nfft = 1 << int(math.ceil(math.log2(len(y) * 8)))
    spec = np.abs(np.fft.rfft((y - y.mean()) * np.hanning(len(y)), nfft))
    fr = np.fft.rfftfreq(nfft, dt)
    f0 = fr[1 + int(np.argmax(spec[1:]))]
    env0 = np.max(np.abs(y[: len(y) // 4]))
    env1 = np.max(np.abs(y[3 * len(y) // 4:])) + 1e-30
    sigma0 = max(0.0, math.log(env0 / env1) / (t[-1] * 0.75))
    p0 = [y[0] if y[0] != 0 else env0, sigma0, 2 * math.pi * f0, 0.0, 0.0]
    popt, _ = curve_fit(_damped, t, y, p0=p0, maxfev=20000)
    a, sigma, w, phi, off = popt
    w = abs(w)
    wn = math.hypot(w, sigma)
    return wn / (2 * math.pi), sigma / wn


def ringdown(model: CoupledModel, gains: Gains, pose_deg, mode_index: int = 0, amplitude_mm: float = 1e-3,
             periods: float = 6.0, h: float = 2e-5) -> dict:
    """Excite oscillatory mode ``mode_index`` (sorted by frequency) of the linear model at ``pose_deg``,
    run the nonlinear simulation, fit the ring-down; both results side by side."""
    A, _ = model.at(pose_deg, gains)
    lam, V = np.linalg.eig(A)
    sel = np.nonzero(lam.imag > 1e-6)[0]
    sel = sel[np.argsort(np.abs(lam[sel]))]
    j = sel[mode_index]
    v = V[:, j]
    # pick the phase that puts the mode into the carrier displacement
    v = v * np.exp(-1j * np.angle(v[IY][np.argmax(np.abs(v[IY]))]))
    x0 = np.real(v)
    x0 *= amplitude_mm / np.max(np.abs(x0[IY][:3]) + 1e-30)
    f_lin = abs(lam[j]) / (2 * math.pi)
    z_lin = -lam[j].real / abs(lam[j])
    nm = NonlinearMachine(model, gains, pose_deg)
    dur = periods / f_lin
    t, tip = nm.simulate(nm.from_linear(x0), dur, h=h)
    comp = int(np.argmax(np.std(tip, axis=0)))
    f_fit, z_fit = fit_ringdown(t, tip[:, comp])
    return {"pose": list(map(float, pose_deg)), "mode_index": mode_index,
            "linear_hz": float(f_lin), "linear_damping": float(z_lin),
            "ringdown_hz": float(f_fit), "ringdown_damping": float(z_fit),
            "t_s": t, "tip_mm": tip[:, comp]}
