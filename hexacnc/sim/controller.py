"""Controller structures (the seed's figure 7): per-strut cascade against a coupled state controller.

Both run on the same plant (:class:`hexacnc.sim.dynamics.CoupledModel`, drive
cascades inside the drives, continuous) at the worst workspace position.  The
main control runs every ``Ts`` (``[cycle] period_s``) and reaches the drives
with the bus dead time ``[dynamics] bus_dead_time_s`` (1.5 ms = 3 cycles at
0.5 ms): the whole loop delay is put on the command path, which for a linear
loop is equivalent to splitting it between feedback and command.

* **conventional**: the main control sends the strut setpoints only; the
  cascades (tuned the conventional way at the worst position,
  :func:`~hexacnc.sim.dynamics.tune_conventional`) do the rest.
* **coupled**: in addition the main control closes a state feedback through
  the Jacobian-coupled model: a Kalman filter (drive feedback: position,
  velocity, force of each drive; the delayed commands are known) estimates the
  36 plant states, an LQR gain designed on the delay-augmented discrete model
  adds a velocity reference to each drive.  The LQR weights the tool-tip error
  and carrier rotation; the control-effort weight is chosen from a short sweep
  as the one with the shortest settling time (overshoot <= 10 %, peak drive
  force at most 3 times the conventional structure's).

A 50 um tool step along z: settling time (band +-2 % = 1 um) and overshoot for both.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.linalg import solve_discrete_are

from ..pose import pose_to_rad
from .dynamics import IF, IQ, IQD, IVFF, IY, NX, CoupledModel, Gains, _discretise


def _tip_twist_jacobian(model: CoupledModel, pose_deg):
    X = pose_to_rad(pose_deg)
    return model.hx.jacobian_twist_rad(X, model.tip)


class StepExperiment:
    """Both controller structures on the plant linearised at ``pose_deg``."""

    def __init__(self, model: CoupledModel, gains: Gains, pose_deg, Ts: float | None = None,
                 dead_time_s: float | None = None, substeps: int = 5):
        cfg = model.cfg
        self.model = model
        self.g = gains
        self.pose = np.asarray(pose_deg, dtype=float)
        self.Ts = float(cfg.cycle.period_s if Ts is None else Ts)
        td = cfg.dynamics.bus_dead_time_s if dead_time_s is None else dead_time_s
        self.d = int(round(td / self.Ts))
        self.sub = substeps
        J, R = model.jacobian(self.pose)
        gff = Gains(gains.kp_1_s, gains.kv_N_s_mm, gains.tn_s, gains.velocity_bandwidth_hz, True)
        A, B = model.matrices(J, R, gff)
        self.A, self.B = A, B
        self.T = model.tip_map(R)
        self.J = J
        h = self.Ts / substeps
        self.Ah, self.Bh = _discretise(A, B, h)
        self.Ad, self.Bd = _discretise(A, B, self.Ts)
        self.tip_rows = np.zeros((6, NX))
        self.tip_rows[:3, IY] = self.T
        self.tip_rows[3:, IY.start + 3:IY.stop] = np.eye(3)

    # -- step target --------------------------------------------------------------
    def step_lengths(self, dz_mm: float) -> np.ndarray:
        Jt = _tip_twist_jacobian(self.model, self.pose)
        return Jt @ np.array([0.0, 0.0, dz_mm, 0.0, 0.0, 0.0])

    def steady_state(self, dL: np.ndarray) -> np.ndarray:
        xs = np.zeros(NX)
        xs[IQ] = dL
        xs[IY] = np.linalg.solve(self.J, dL)
        return xs

    # -- LQG design on the delay-augmented discrete model -------------------------------------------
    def design(self, rho: float) -> dict:
        d, n = self.d, NX
        Bu = self.Bd[:, IVFF]
        na = n + 6 * d
        Aa = np.zeros((na, na))
        Ba = np.zeros((na, 6))
        Aa[:n, :n] = self.Ad
        if d == 0:
            Ba[:n] = Bu
        else:
            Aa[:n, n:n + 6] = Bu                       # oldest buffered command acts now
            for j in range(d - 1):
                Aa[n + 6 * j:n + 6 * j + 6, n + 6 * (j + 1):n + 6 * (j + 2)] = np.eye(6)
            Ba[n + 6 * (d - 1):] = np.eye(6)
        # weights: tool tip (1 um), rotation (1 urad), drive-side positions vs carrier (soft)
        Cq = np.zeros((12, na))
        Cq[:6, :n] = self.tip_rows * np.array([1e3, 1e3, 1e3, 1e6 * 0.2, 1e6 * 0.2, 1e6 * 0.2])[:, None]
        Cq[6:, IQD] = np.eye(6) * 1e-1
        Q = Cq.T @ Cq + 1e-9 * np.eye(na)
        R = rho * np.eye(6)
        P = solve_discrete_are(Aa, Ba, Q, R)
        K = np.linalg.solve(R + Ba.T @ P @ Ba, Ba.T @ P @ Aa)
        Cm, L = self._kalman(Aa)
        cl = np.linalg.eigvals(Aa - Ba @ K)
        return {"K": K, "L": L, "Aa": Aa, "Ba": Ba, "Cm": Cm, "rho": rho,
                "max_pole_radius": float(np.max(np.abs(cl)))}

    def _kalman(self, Aa: np.ndarray):
        """Steady-state Kalman gain on the drive feedback (position, velocity, force of each drive)."""
        if getattr(self, "_kal", None) is not None:
            return self._kal
        n, na = NX, Aa.shape[0]
        Cm = np.zeros((18, na))
        Cm[:6, IQ] = np.eye(6)
        Cm[6:12, IQD] = np.eye(6)
        Cm[12:, IF] = np.eye(6)
        Rm = np.diag([1e-4 ** 2] * 6 + [1e-2 ** 2] * 6 + [1.0] * 6)
        Gw = np.zeros((na, 12))
        Gw[:n, :6] = self.Bd[:, 12:18]     # force disturbances on the drive side
        Gw[:n, 6:] = self.Bd[:, 18:24]     # wrench on the carrier
        Qw = Gw @ np.diag([10.0 ** 2] * 6 + [10.0 ** 2] * 3 + [1e3 ** 2] * 3) @ Gw.T + 1e-12 * np.eye(na)
        Pk = solve_discrete_are(Aa.T, Cm.T, Qw, Rm)
        L = Pk @ Cm.T @ np.linalg.inv(Cm @ Pk @ Cm.T + Rm)
        self._kal = (Cm, L)
        return self._kal

    # -- simulation ----------------------------------------------------------------------------------
    def simulate(self, dz_mm: float = 0.05, duration_s: float = 0.5, design: dict | None = None,
                 plant: "StepExperiment | None" = None) -> dict:
        """Step of the tool tip by ``dz_mm``; ``design`` None: conventional cascade only.

        ``plant``: another experiment (same pose and cycle, different machine parameters) whose
        model is simulated while the controller keeps this one's (model-error check).
        """
        pl = self if plant is None else plant
        dL = self.step_lengths(dz_mm)
        xs = self.steady_state(dL)
        n, d = NX, self.d
        steps = int(round(duration_s / self.Ts))
        x = np.zeros(n)
        rbuf = [np.zeros(6)] * d            # setpoints in flight on the bus
        ubuf = [np.zeros(6)] * d
        xa_hat = None
        if design is not None:
            xa_hat = np.zeros(n + 6 * d)
        t_out, z_out = [0.0], [0.0]
        fmax = 0.0
        for k in range(steps):
            r_main = dL                      # main control: step setpoint at t = 0
            u_main = np.zeros(6)
            if design is not None:
                # estimate of the deviation from the target state, plus the known commands in flight
                e = xa_hat.copy()
                e[:n] -= xs
                u_main = -design["K"] @ e
            rbuf.append(r_main)
            ubuf.append(u_main)
            r_drv = rbuf.pop(0)
            u_drv = ubuf.pop(0)
            u_in = np.zeros(24)
            u_in[0:6] = r_drv
            u_in[6:12] = u_drv
            for _ in range(self.sub):
                x = pl.Ah @ x + pl.Bh @ u_in
                t_out.append(t_out[-1] + self.Ts / self.sub)
                z_out.append(float(pl.T[2] @ x[IY]))
                fmax = max(fmax, float(np.max(np.abs(x[IF]))))
            if design is not None:
                # predict with the known inputs, correct with the drive feedback
                Aa, Ba = design["Aa"], design["Ba"]
                pred = Aa @ xa_hat + Ba @ u_main
                pred[:n] += self.Bd[:, 0:6] @ r_drv
                y = design["Cm"][:, :n] @ x
                xa_hat = pred + design["L"] @ (y - design["Cm"] @ pred)
        t = np.array(t_out)
        z = np.array(z_out) * 1e3                      # um
        return {"t_s": t, "z_um": z, **step_metrics(t, z, dz_mm * 1e3), "peak_drive_force_N": fmax}


def step_metrics(t: np.ndarray, y: np.ndarray, target: float, band: float = 0.02) -> dict:
    """Settling time (last exit from +-band*target), overshoot %, rise time 10-90 %."""
    err = np.abs(y - target)
    outside = np.nonzero(err > band * abs(target))[0]
    if len(outside) == 0:
        ts = 0.0
    elif outside[-1] == len(y) - 1:
        ts = math.inf
    else:
        ts = float(t[outside[-1] + 1])
    over = max(0.0, (float(np.max(y)) - target) / target * 100.0) if target > 0 else 0.0
    i10 = np.nonzero(y >= 0.1 * target)[0]
    i90 = np.nonzero(y >= 0.9 * target)[0]
    rise = float(t[i90[0]] - t[i10[0]]) if len(i10) and len(i90) else math.inf
    return {"settling_time_s": ts, "overshoot_pct": over, "rise_time_s": rise,
            "final_um": float(y[-1])}


def compare(model: CoupledModel, gains: Gains, pose_deg, dz_mm: float = 0.05, duration_s: float = 0.4,
            rhos=(0.01, 0.1, 1.0, 3.0, 10.0, 30.0, 100.0, 1e3, 1e4), force_budget: float = 3.0) -> dict:
    """Figure 7: conventional cascade vs coupled state controller at ``pose_deg``.

    The coupled design is the sweep's fastest settling with overshoot <= 10 % and
    a peak drive force at most ``force_budget`` times the conventional one's.
    """
    ex = StepExperiment(model, gains, pose_deg)
    conv = ex.simulate(dz_mm, duration_s)
    best = None
    sweep = []
    for rho in rhos:
        des = ex.design(rho)
        if des["max_pole_radius"] >= 1.0:
            continue
        res = ex.simulate(dz_mm, duration_s, des)
        sweep.append({"rho": rho, "settling_time_s": res["settling_time_s"], "overshoot_pct": res["overshoot_pct"],
                      "peak_drive_force_N": res["peak_drive_force_N"]})
        if res["overshoot_pct"] <= 10.0 and res["peak_drive_force_N"] <= force_budget * conv["peak_drive_force_N"] and (best is None or res["settling_time_s"] < best[1]["settling_time_s"]):
            best = (des, res)
    if best is None:
        raise RuntimeError("no stable coupled design in the sweep")
    des, coup = best
    keys = ("settling_time_s", "overshoot_pct", "rise_time_s", "final_um", "peak_drive_force_N")
    # model error: the machine is heavier (+25 % carrier mass and inertia) and its struts softer (-20 %)
    # than the model both controllers were tuned / designed on
    cfg = model.cfg
    off = cfg.replace(mass_kg=cfg.mass_kg * 1.25, inertia_kg_mm2=np.asarray(cfg.inertia_kg_mm2) * 1.25,
                      stiffness_N_per_mm=np.asarray(cfg.stiffness_N_per_mm) * 0.8)
    ex_off = StepExperiment(CoupledModel(off, model.hx), gains, pose_deg)
    rob = {"plant_change": "carrier mass and inertia +25 %, strut stiffness -20 %",
           "conventional": {k: v for k, v in ex.simulate(dz_mm, duration_s, None, ex_off).items() if k in keys},
           "coupled": {k: v for k, v in ex.simulate(dz_mm, duration_s, des, ex_off).items() if k in keys}}
    return {
        "pose": list(map(float, pose_deg)), "step_um": dz_mm * 1e3, "cycle_s": ex.Ts,
        "dead_time_s": ex.d * ex.Ts, "gains": gains.as_dict(),
        "conventional": {k: conv[k] for k in keys},
        "coupled": {**{k: coup[k] for k in keys}, "rho": des["rho"]},
        "force_budget": force_budget,
        "model_error_check": rob,
        "speedup": (conv["settling_time_s"] / coup["settling_time_s"]) if coup["settling_time_s"] > 0 else math.inf,
        "sweep": sweep,
        "_series": {"t_s": conv["t_s"], "conventional_um": conv["z_um"], "coupled_um": coup["z_um"]},
    }
