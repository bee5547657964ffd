"""Thermal drift end to end: a warming machine, the observer, the cycle transform.

The simulated machine ("truth") differs from the observer's model on purpose:

* each strut is a finer 1-D heat model (``truth_segments``, default 40 against
  ``[thermal] segments``);
* its friction heat is not uniform: it falls linearly from the drive (base) end
  to the platform end, ``heat_profile_ratio`` (3:1) - the model assumes uniform;
* its heat input is ``truth_heat_ratio`` (1.15) times what the model assumes.

Inputs: strut speeds from a program (:mod:`hexacnc.sim.program`: a synthetic
milling program through the G-code interpreter and the look-ahead planner when
they are available, else an exact-stop trapezoid profile) repeated under a varying feed
override (phases), an ambient temperature that creeps and oscillates (HVAC),
and a frame that follows the ambient with a long time constant.  The spindle
housing warms while the spindle runs; the spindle shaft (what grows) follows the
housing with a lag.

Sensors, all with white Gaussian noise: per strut the ``[thermal] probes``
segments (``probe_noise_K``), one ambient and one frame sensor (same noise), one
spindle-housing probe (``spindle_probe_noise_K``).  The observer
(:class:`hexacnc.thermal.ThermalObserver`) runs at ``1/dt_s`` (10 Hz; the daemon runs it
at its probe rate, :mod:`hexacnc.daemon.thermalsup`) and its offsets go into :class:`hexacnc.transform.CycleTransform`
exactly as the daemon sets them; the spindle growth from the probe goes to
``set_spindle_growth_mm``.  Drift is the tool-tip error at the measuring pose
(home): strut commands from the transform plus the true thermal growth, through
forward kinematics, against the commanded tool tip.

Calibration: the true heat coefficient is chosen (by linearity of the heat
equation, then a 1-D root search) so that the uncompensated peak z drift is
``target_drift_um`` (45 um, the seed's scenario).
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from ..kinematics import Hexapod
from ..pose import matrix_from_euler, pose_to_rad
from ..thermal import ThermalObserver, discretise, spindle_growth_mm, strut_heat_model
from ..transform import CycleTransform
from .program import program_trajectory, synthetic_program

#: seed-like 2.5 h schedule: (minutes, feed override, spindle on)
DEFAULT_PHASES = ((20, 1.0, True), (15, 0.6, True), (20, 1.3, True), (10, 0.0, False),
                  (25, 1.0, True), (20, 0.8, True), (15, 1.2, True), (5, 0.0, False), (20, 1.0, True))


@dataclass
class ThermalScenario:
    duration_s: float = 9000.0
    dt_s: float = 0.1                       #: observer / daemon thermal rate
    phases: tuple = DEFAULT_PHASES          #: repeated to cover duration_s
    program_lines: int = 300
    trajectory_source: str = "auto"         #: "auto" (planner if available), "planner", "exact-stop"
    truth_segments: int = 40
    truth_heat_ratio: float = 1.15          #: true heat / modelled heat
    heat_profile_ratio: float = 3.0         #: true source density base end / platform end
    target_drift_um: float = 45.0           #: uncompensated peak |z| drift to calibrate to
    heat_per_speed_W_s_mm: float | None = None   #: true coefficient; None: calibrate
    ambient_creep_K: float = 0.4            #: ambient rise over the run
    ambient_swing_K: float = 0.15           #: HVAC oscillation amplitude
    ambient_period_s: float = 1800.0
    frame_tau_s: float = 7200.0
    spindle_rise_K: float = 8.0
    spindle_tau_s: float = 900.0
    spindle_shaft_lag_s: float = 300.0
    spindle_probe_noise_K: float = 0.05
    sample_every_s: float = 10.0            #: drift evaluation / output series
    seed: int = 1
    T0_C: float = 20.0


def _phase_arrays(sc: ThermalScenario, n: int):
    t = np.arange(n) * sc.dt_s
    ov = np.zeros(n)
    sp = np.zeros(n, dtype=bool)
    t0 = 0.0
    k = 0
    while t0 < sc.duration_s:
        mins, f, on = sc.phases[k % len(sc.phases)]
        sel = (t >= t0) & (t < t0 + mins * 60.0)
        ov[sel] = f
        sp[sel] = on
        t0 += mins * 60.0
        k += 1
    return ov, sp


def strut_speed_profile(cfg, sc: ThermalScenario, n: int):
    """Mean |strut speed| (n,6) per step from the repeated program under the override phases."""
    tr, desc = program_trajectory(cfg, synthetic_program(cfg, sc.program_lines, seed=sc.seed), 0.01,
                                  sc.trajectory_source)
    travel = np.concatenate([np.zeros((1, 6)), np.cumsum(np.abs(np.diff(tr.lengths_mm, axis=0)), axis=0)])
    Tc = tr.t_s[-1]
    Dtot = travel[-1]
    ov, spindle_on = _phase_arrays(sc, n)
    tau = np.concatenate([[0.0], np.cumsum(ov * sc.dt_s)])          # program time at step edges
    cyc = np.floor(tau / Tc)
    r = tau - cyc * Tc
    D = cyc[:, None] * Dtot[None, :] + np.stack([np.interp(r, tr.t_s, travel[:, i]) for i in range(6)], 1)
    speed = np.diff(D, axis=0) / sc.dt_s
    return speed, ov, spindle_on, tr, desc


def truth_probe_segments(cfg, length_mm: float, nseg: int) -> list[int]:
    """Segments of an ``nseg`` truth grid holding the ``[thermal] probes`` (observer segment centres)."""
    m_obs = strut_heat_model(cfg.thermal, length_mm)
    centres = m_obs.segment_centres_mm() / m_obs.length_mm
    return [min(nseg - 1, int(c * nseg)) for c in centres[list(cfg.thermal.probes)]]


def _simulate_linear(models, dt, inputs, T0, pidx, T_ref):
    """Run 6 strut models on inputs (n,6,3).

    Returns growth (n,6) mm relative to ``T_ref``, mean temperature (n,6) and the
    temperatures at segments ``pidx`` (n,6,p): only what the scenario needs, so
    memory stays O(n) per strut.
    """
    disc = [discretise(m.A, m.B, dt) for m in models]
    Ad = np.stack([d[0] for d in disc])
    Bd = np.stack([d[1] for d in disc])
    C = np.stack([m.C for m in models])
    n = inputs.shape[0]
    nseg = models[0].n
    T = np.full((6, nseg), T0, dtype=float)
    growth = np.empty((n, 6))
    mean = np.empty((n, 6))
    probe = np.empty((n, 6, len(pidx)))
    Cs = C.sum(axis=1)
    for k in range(n):
        T = np.einsum("ijk,ik->ij", Ad, T) + np.einsum("ijk,ik->ij", Bd, inputs[k])
        growth[k] = np.einsum("ij,ij->i", T, C) - T_ref * Cs
        mean[k] = T.mean(axis=1)
        probe[k] = T[:, pidx]
    return growth, mean, probe


@dataclasses.dataclass
class _Environment:
    """Air, frame, spindle housing and shaft temperatures (n,) over the run (deg C)."""
    ambient: np.ndarray
    frame: np.ndarray
    housing: np.ndarray
    shaft: np.ndarray


def _environment(sc: ThermalScenario, t: np.ndarray, spindle_on: np.ndarray) -> _Environment:
    n = t.shape[0]
    Ta = sc.T0_C + sc.ambient_creep_K * t / sc.duration_s + sc.ambient_swing_K * np.sin(
        2 * math.pi * t / sc.ambient_period_s)
    a_f = math.exp(-sc.dt_s / sc.frame_tau_s)
    Tf = np.empty(n)
    x = sc.T0_C
    for k in range(n):
        x = a_f * x + (1 - a_f) * Ta[k]
        Tf[k] = x
    # spindle housing and shaft (first order each)
    a_s = math.exp(-sc.dt_s / sc.spindle_tau_s)
    a_l = math.exp(-sc.dt_s / sc.spindle_shaft_lag_s)
    Tsp = np.empty(n)
    Tsh = np.empty(n)
    hsg, shf = sc.T0_C, sc.T0_C
    for k in range(n):
        tgt = Ta[k] + (sc.spindle_rise_K if spindle_on[k] else 0.0)
        hsg = a_s * hsg + (1 - a_s) * tgt
        shf = a_l * shf + (1 - a_l) * hsg
        Tsp[k] = hsg
        Tsh[k] = shf
    return _Environment(Ta, Tf, Tsp, Tsh)


def _heat_to_target(sc: ThermalScenario, zpeak) -> float:
    """The true heat per strut speed (W s/mm): the scenario's, or the one giving ``target_drift_um``."""
    if sc.heat_per_speed_W_s_mm is not None:
        return float(sc.heat_per_speed_W_s_mm)
    target = sc.target_drift_um * 1e-3
    if zpeak(0.0) >= target:
        return 0.0
    hi = 1.0
    while zpeak(hi) < target and hi < 1e4:
        hi *= 2
    return brentq(lambda h: zpeak(h) - target, 0.0, hi, xtol=1e-6)


def run(cfg, sc: ThermalScenario | None = None, progress=None) -> dict:
    """Run the scenario; returns the JSON-ready figures (see :func:`summary_keys`)."""
    sc = sc or ThermalScenario()
    wall0 = time.perf_counter()
    rng = np.random.default_rng(sc.seed)
    n = int(round(sc.duration_s / sc.dt_s))
    t = (np.arange(n) + 1) * sc.dt_s
    speed, override, spindle_on, tr, desc = strut_speed_profile(cfg, sc, n)

    hx = Hexapod(cfg)
    lengths = hx.lengths(cfg.home_pose)
    nseg = sc.truth_segments
    prof = np.linspace(sc.heat_profile_ratio, 1.0, nseg)      # base end (segment 0) -> platform end
    unit_cfg = dataclasses.replace(cfg.thermal, heat_per_speed_W_s_mm=1.0)
    truth = [strut_heat_model(unit_cfg, float(L), segments=nseg, source_profile=prof) for L in lengths]
    env = _environment(sc, t, spindle_on)

    # truth by superposition: unit heat part + environment part
    u_heat = np.zeros((n, 6, 3))
    u_heat[:, :, 0] = np.abs(speed)
    u_env = np.zeros((n, 6, 3))
    u_env[:, :, 1] = env.ambient[:, None]
    u_env[:, :, 2] = env.frame[:, None]
    # probes: the observer's probed segment centres located on the truth grid
    m_obs = strut_heat_model(cfg.thermal, float(lengths[0]))
    centres = m_obs.segment_centres_mm() / m_obs.length_mm
    pidx = truth_probe_segments(cfg, float(lengths[0]), nseg)
    Tref = cfg.thermal.reference_temperature_C
    g_heat, mean_heat, probe_heat = _simulate_linear(truth, sc.dt_s, u_heat, 0.0, pidx, 0.0)
    g_env, mean_env, probe_env = _simulate_linear(truth, sc.dt_s, u_env, sc.T0_C, pidx, Tref)

    # tool-tip map at the measuring pose (home), linear, for the calibration
    X = pose_to_rad(cfg.home_pose)
    R = matrix_from_euler(*X[3:])
    axis = np.asarray(cfg.tool.axis_platform, dtype=float)
    Jtip = hx.jacobian_twist_rad(X, np.asarray(cfg.tool.tip_platform_mm, dtype=float))
    tip_of_dL = np.linalg.inv(Jtip)[:3]                     # (3,6) tool-tip shift per strut growth
    g_sp_true = np.array([spindle_growth_mm(v, cfg) for v in env.shaft])
    sp_shift = np.outer(g_sp_true, R @ axis)                # (n,3) tool tip moves along the tool axis

    def zpeak(h):
        dz = (g_heat * h + g_env) @ tip_of_dL[2] + sp_shift[:, 2]
        return float(np.max(np.abs(dz)))

    h_true = _heat_to_target(sc, zpeak)
    h_model = h_true / sc.truth_heat_ratio
    growth_true = g_heat * h_true + g_env                   # (n,6) mm
    mean_true = mean_heat * h_true + mean_env               # (n,6) mean strut temperature
    probe_true = probe_heat * h_true + probe_env            # (n,6,p)

    mcfg = cfg.replace(thermal=dataclasses.replace(cfg.thermal, heat_per_speed_W_s_mm=h_model))
    obs = ThermalObserver(mcfg, sc.dt_s)
    noise = cfg.thermal.probe_noise_K
    probes = probe_true + rng.normal(0.0, noise, (n, 6, len(pidx)))
    Ta_meas = env.ambient + rng.normal(0.0, noise, n)
    Tf_meas = env.frame + rng.normal(0.0, noise, n)
    Tsp_meas = env.housing + rng.normal(0.0, sc.spindle_probe_noise_K, n)
    obs.reset(np.full(6, sc.T0_C))          # the daemon starts the estimate at the probe mean
    obs.reset(np.full((6, obs.n), float(np.mean(probes[0]))))

    S, est = _observe(cfg, sc, hx, obs, X, (speed, Ta_meas, Tf_meas, probes, Tsp_meas),
                      growth_true, mean_true, env.frame, g_sp_true, t, override, progress)
    probes_desc = {
        "per_strut": len(obs.probes), "segments": list(obs.probes),
        "positions_fraction_of_length_from_base": [round(float(centres[p]), 4) for p in obs.probes],
        "noise_K": noise, "ambient_and_frame_sensor_noise_K": noise,
        "spindle_probe": 1, "spindle_probe_noise_K": sc.spindle_probe_noise_K, "total_sensors": 6 * len(obs.probes) + 3,
    }
    out = {
        "scenario": "from cold, varying feed override, spindle phases",
        "duration_h": sc.duration_s / 3600.0,
        "observer_rate_hz": 1.0 / sc.dt_s,
        "speed_source": desc + " per pass, repeated under feed override phases",
        "mean_strut_speed_mm_s": float(np.mean(np.abs(speed))),
        "heat_per_speed_W_s_mm": {"true": h_true, "model": h_model},
        "model_mismatch": {"truth_segments": nseg, "model_segments": obs.n, "truth_heat_ratio": sc.truth_heat_ratio,
                           "truth_heat_profile_base_to_platform": sc.heat_profile_ratio},
        "probes": probes_desc,
    }
    out.update(_drift_figures(sc, S, est, growth_true, g_sp_true))
    out["wall_time_s"] = time.perf_counter() - wall0
    out["series"] = {
        "columns": ["t_s", "dx_uncomp_um", "dy_uncomp_um", "dz_uncomp_um", "dx_comp_um", "dy_comp_um",
                    "dz_comp_um", "strut_frame_dT_K", "mean_growth_true_um", "mean_growth_est_um",
                    "spindle_growth_um", "override"],
        "rows": [[round(float(v), 5) for v in r] for r in S],
    }
    return out


def _observe(cfg, sc, hx, obs, X, meas, growth_true, mean_true, Tf, g_sp_true, t, override, progress):
    """Run the observer over the readings; every ``sample_every_s`` the tool-tip drift at the
    measuring pose with and without compensation. Returns the series (m, 12) and the estimate (n, 6)."""
    speed, Ta_meas, Tf_meas, probes, Tsp_meas = meas
    n = t.shape[0]
    tip = np.asarray(cfg.tool.tip_platform_mm, dtype=float)
    axis = np.asarray(cfg.tool.axis_platform, dtype=float)
    home_tip = cfg.home_pose[:3] + matrix_from_euler(*X[3:]) @ tip
    every = max(1, int(round(sc.sample_every_s / sc.dt_s)))
    ct_c = CycleTransform(cfg)
    ct_u = CycleTransform(cfg)
    rows = []
    est = np.empty((n, 6))
    for k in range(n):
        est[k] = obs.update(speed[k], Ta_meas[k], Tf_meas[k], probes[k])
        if (k + 1) % every == 0 or k == n - 1:
            g_sp_est = spindle_growth_mm(Tsp_meas[k], cfg)
            out = []
            for ct, comp in ((ct_u, False), (ct_c, True)):
                ct.set_thermal_offsets_mm(est[k] if comp else np.zeros(6))
                ct.set_spindle_growth_mm(g_sp_est if comp else 0.0)
                code = _command_at_rest(ct, X)
                if code != 0:
                    raise RuntimeError(f"measuring pose rejected by the transform: {ct.describe(code)}")
                L_act = np.array(ct.cmd_mm) + np.array(ct.sag_mm) + growth_true[k]
                fk = hx.forward(L_act, cfg.home_pose)
                Xa = pose_to_rad(fk.pose)
                Ra = matrix_from_euler(*Xa[3:])
                tip_act = Xa[:3] + Ra @ (tip + g_sp_true[k] * axis)
                out.append((tip_act - home_tip) * 1e3)
            dT = float(np.mean(mean_true[k]) - Tf[k])
            rows.append([t[k], *out[0], *out[1], dT, float(np.mean(growth_true[k]) * 1e3),
                         float(np.mean(est[k]) * 1e3), g_sp_true[k] * 1e3, override[k]])
            if progress:
                progress(k + 1, n)
    return np.array(rows), est


def _drift_figures(sc, S, est, growth_true, g_sp_true) -> dict:
    z_u, z_c = S[:, 3], S[:, 6]
    d3_u = np.linalg.norm(S[:, 1:4], axis=1)
    d3_c = np.linalg.norm(S[:, 4:7], axis=1)
    peak_u, peak_c = float(np.max(np.abs(z_u))), float(np.max(np.abs(z_c)))
    err_g = (est - growth_true) * 1e3
    return {
        "peak_drift_z_um": {"uncompensated": peak_u, "compensated": peak_c},
        "peak_drift_3d_um": {"uncompensated": float(d3_u.max()), "compensated": float(d3_c.max())},
        "reduction_pct": 100.0 * (1.0 - peak_c / peak_u) if peak_u > 0 else 0.0,
        "final_drift_z_um": {"uncompensated": float(z_u[-1]), "compensated": float(z_c[-1])},
        "strut_frame_dT_K": {"peak": float(S[:, 7].max()), "final": float(S[:, 7][-1])},
        "strut_growth_estimate_error_um": {"rms": float(np.sqrt(np.mean(err_g ** 2))),
                                           "max_after_10min": float(np.max(np.abs(err_g[int(600 / sc.dt_s):])))},
        "spindle_growth_peak_um": float(np.max(np.abs(g_sp_true)) * 1e3),
    }


def _command_at_rest(ct: CycleTransform, X) -> int:
    """Command a pose the machine rests at (re-seed the velocity guard: offsets jump between samples)."""
    from ..transform import LIMIT_ACCELERATION, LIMIT_VELOCITY
    code = ct.command(*X)
    if code in (LIMIT_VELOCITY, LIMIT_ACCELERATION):
        ct.reset([ct.length_mm[i] - ct.sag_mm[i] - ct.thermal_mm[i] for i in range(6)])
        code = ct.command(*X)
    return code


def plot(result: dict, path: str) -> None:
    """Figure-6-like plot: z drift with and without compensation, strut-frame dT."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    S = np.array(result["series"]["rows"])
    tm = S[:, 0] / 60.0
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7.0, 5.2), sharex=True,
                                   gridspec_kw={"height_ratios": [2.2, 1]})
    ax1.plot(tm, S[:, 3], label="uncompensated", color="tab:red")
    ax1.plot(tm, S[:, 6], label="compensated (observer + spindle probe)", color="tab:blue")
    ax1.axhline(0, color="0.6", lw=0.6)
    ax1.set_ylabel("tool z drift (um)")
    r = result
    ax1.set_title(f"Thermal drift, {r['duration_h']:.1f} h: peak {r['peak_drift_z_um']['uncompensated']:.1f} -> "
                  f"{r['peak_drift_z_um']['compensated']:.1f} um ({r['reduction_pct']:.0f} % less)", fontsize=10)
    ax1.legend(fontsize=8)
    ax1.grid(alpha=0.3)
    ax2.plot(tm, S[:, 7], color="tab:orange", label="mean strut - frame")
    ax2b = ax2.twinx()
    ax2b.step(tm, S[:, 11], color="0.5", lw=0.7, where="post")
    ax2b.set_ylabel("feed override", color="0.5", fontsize=8)
    ax2.set_ylabel("dT (K)")
    ax2.set_xlabel("time (min)")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def save_figure(fig, path: str) -> None:
    import os
    tmp = f"{path}.tmp.png"
    fig.savefig(tmp, dpi=80)
    os.replace(tmp, path)
