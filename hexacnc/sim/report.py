"""Runs behind ``hexacnc simulate``: figures as JSON-ready dicts and PNG plots (matplotlib Agg).

Each ``run_*`` returns a dict without numpy arrays; ``plot_*`` write PNGs
atomically (temp file + ``os.replace``).
"""
from __future__ import annotations

import json
import math
import os
import time

import numpy as np

from . import thermal as sim_thermal
from .controller import compare
from .dynamics import CoupledModel, drive_transfer_functions, eigen_grid, simulate_path, tune_conventional, \
    workspace_grid
from .nonlinear import ringdown
from .program import program_trajectory, synthetic_program, to_gcode_tooltip


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_png(fig, path: str) -> None:
    tmp = f"{path}.tmp.png"
    fig.savefig(tmp, dpi=80)
    os.replace(tmp, path)


def write_json(obj, path: str) -> None:
    tmp = f"{path}.tmp"
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(obj, fh, indent=1, allow_nan=True)
        fh.write("\n")
    os.replace(tmp, path)


def _thin(a: np.ndarray, n: int = 2000) -> np.ndarray:
    step = max(1, int(math.ceil(len(a) / n)))
    return a[::step]


def _thin_max(a: np.ndarray, n: int = 2000) -> np.ndarray:
    """Largest value per bucket, so that a thinned plot keeps the peaks."""
    step = max(1, int(math.ceil(len(a) / n)))
    m = len(a) // step * step
    head = a[:m].reshape(-1, step).max(axis=1)
    return np.concatenate([head, [a[m:].max()]]) if m < len(a) else head


def _thin_maxabs(a: np.ndarray, n: int = 2000) -> np.ndarray:
    """(N,k): per bucket and column the signed value of largest magnitude."""
    step = max(1, int(math.ceil(len(a) / n)))
    out = []
    for i in range(0, len(a), step):
        blk = a[i:i + step]
        out.append(blk[np.argmax(np.abs(blk), axis=0), np.arange(a.shape[1])])
    return np.array(out)


# ---------------------------------------------------------------------------
def run_thermal(cfg, **scenario) -> dict:
    return sim_thermal.run(cfg, sim_thermal.ThermalScenario(**scenario))


def plot_thermal(res: dict, path: str) -> None:
    sim_thermal.plot(res, path)


# ---------------------------------------------------------------------------
def worst_and_gains(cfg, n_grid: int = 5):
    model = CoupledModel(cfg)
    grid = workspace_grid(cfg, n_xyz=n_grid)
    eg = eigen_grid(model, grid)
    worst = np.asarray(eg["worst_pose"])
    gains, crit = tune_conventional(model, worst)
    return model, grid, worst, gains, crit


def run_dynamics(cfg, lines: int = 1000, n_grid: int = 5, seed: int = 1, ringdown_check: bool = True,
                 source: str = "auto") -> dict:
    t0 = time.perf_counter()
    model, grid, worst, gains, crit = worst_and_gains(cfg, n_grid)
    eg = eigen_grid(model, grid, gains)
    moves = synthetic_program(cfg, lines, seed=seed)
    tp = time.perf_counter()
    tr, desc = program_trajectory(cfg, moves, cfg.cycle.period_s, source)
    t_plan = time.perf_counter() - tp
    path = simulate_path(model, gains, tr.poses, tr.dt_s, tr.line)
    ser = path.pop("_series")
    out = {
        "model": {"reflected_mass_kg": cfg.dynamics.reflected_mass_kg, "drive_lag_s": cfg.dynamics.drive_lag_s,
                  "stiffness_N_per_mm": np.asarray(cfg.stiffness_N_per_mm).tolist(),
                  "strut_damping_N_s_mm": model.c.tolist(), "carrier_mass_kg": cfg.mass_kg},
        "gains": gains.as_dict(), "critical_velocity_bandwidth_hz_at_worst": crit,
        "eigen": {k: v for k, v in eg.items() if k not in ("poses",)},
        "grid_points": len(grid),
        "program": {"source": desc, "lines": lines, "duration_s": tr.duration_s, "trajectory_wall_s": t_plan},
        "path": path,
    }
    tf = drive_transfer_functions(model, gains, np.logspace(0, 3, 200))
    out["Gs_bandwidth_hz"] = tf["Gs_bandwidth_hz"]
    out["Gz_static_um_per_kN"] = float(1e6 / model.k[0])
    if ringdown_check:
        rd = ringdown(model, gains, worst, 0, h=5e-5, periods=5)
        out["ringdown_check"] = {k: rd[k] for k in ("pose", "linear_hz", "linear_damping", "ringdown_hz",
                                                    "ringdown_damping")}
    out["wall_time_s"] = time.perf_counter() - t0
    out["_series"] = {"t_s": _thin(ser["t_s"]).tolist(),
                      "tip_err_um": _thin_max(np.linalg.norm(ser["tip_um"], axis=1)).tolist(),
                      "ferr_um": _thin_maxabs(ser["ferr_um"]).tolist(), "grid": grid.tolist()}
    out["_gcode"] = to_gcode_tooltip(cfg, moves)
    return out


def plot_dynamics(res: dict, path_eigen: str, path_path: str) -> None:
    plt = _plt()
    G = np.asarray(res["_series"]["grid"])
    f = np.asarray(res["eigen"]["lowest_locked_hz"])
    flat = (G[:, 3] == 0) & (G[:, 4] == 0)
    fig, axs = plt.subplots(1, 2, figsize=(9, 3.8))
    zs = np.unique(G[flat, 2])
    for z in zs:
        sel = flat & (G[:, 2] == z)
        axs[0].plot(G[sel, 0] + 0.02 * G[sel, 1], f[sel], "o", ms=3, label=f"z={z:.0f}")
    axs[0].set_xlabel("x (mm), untilted, grouped by y")
    axs[0].set_ylabel("lowest eigenfrequency (Hz)")
    axs[0].legend(fontsize=7)
    axs[0].set_title("drives locked: lowest carrier mode", fontsize=9)
    axs[0].grid(alpha=0.3)
    tilt = np.hypot(G[:, 3], G[:, 4])
    sc = axs[1].scatter(G[:, 2], f, c=tilt, s=8, cmap="viridis")
    w = res["eigen"]["worst_pose"]
    axs[1].plot([w[2]], [res["eigen"]["worst_lowest_hz"]], "rx", ms=10, label=f"worst {np.round(w, 1).tolist()}")
    axs[1].set_xlabel("z (mm)")
    axs[1].legend(fontsize=7)
    fig.colorbar(sc, ax=axs[1], label="tilt (deg)")
    axs[1].grid(alpha=0.3)
    fig.tight_layout()
    save_png(fig, path_eigen)
    plt.close(fig)

    s = res["_series"]
    t = np.asarray(s["t_s"])
    fig, axs = plt.subplots(2, 1, figsize=(8, 4.6), sharex=True)
    axs[0].plot(t, s["tip_err_um"], lw=0.6)
    axs[0].set_ylabel("tool-tip error (um)")
    axs[0].set_title(f"{res['program']['lines']}-line program, {res['program']['duration_s']:.0f} s: "
                     f"max {res['path']['path_error_um']['max']:.1f} um", fontsize=9)
    fe = np.asarray(s["ferr_um"])
    for i in range(6):
        axs[1].plot(t, fe[:, i], lw=0.5, label=f"strut {i + 1}")
    axs[1].set_ylabel("following error (um)")
    axs[1].set_xlabel("time (s)")
    axs[1].legend(fontsize=6, ncol=6)
    for a in axs:
        a.grid(alpha=0.3)
    fig.tight_layout()
    save_png(fig, path_path)
    plt.close(fig)


# ---------------------------------------------------------------------------
def run_controller(cfg, step_um: float = 50.0, n_grid: int = 5, duration_s: float = 0.3) -> dict:
    t0 = time.perf_counter()
    model, grid, worst, gains, crit = worst_and_gains(cfg, n_grid)
    res = compare(model, gains, worst, dz_mm=step_um * 1e-3, duration_s=duration_s)
    res["critical_velocity_bandwidth_hz_at_worst"] = crit
    ser = res.pop("_series")
    res["wall_time_s"] = time.perf_counter() - t0
    res["_series"] = {k: _thin(np.asarray(v), 3000).tolist() for k, v in ser.items()}
    return res


def plot_controller(res: dict, path: str) -> None:
    plt = _plt()
    s = res["_series"]
    t = np.asarray(s["t_s"]) * 1e3
    fig, axs = plt.subplots(1, 2, figsize=(9, 3.6), sharey=True)
    for ax, key, name in ((axs[0], "conventional", "per-strut cascade"),
                          (axs[1], "coupled", "cascade + state feedback via main control")):
        y = np.asarray(s[f"{key}_um"])
        ax.plot(t, y, lw=1.0)
        st = res["step_um"]
        ax.axhspan(st * 0.98, st * 1.02, color="0.85")
        r = res[key]
        ax.set_title(f"{name}\nsettling {r['settling_time_s'] * 1e3:.1f} ms, overshoot {r['overshoot_pct']:.1f} %",
                     fontsize=9)
        ax.set_xlabel("time (ms)")
        ax.grid(alpha=0.3)
        ax.set_xlim(0, min(t[-1], 120))
    axs[0].set_ylabel("tool z (um)")
    fig.suptitle(f"{res['step_um']:.0f} um step at the worst position, bus dead time "
                 f"{res['dead_time_s'] * 1e3:.1f} ms", fontsize=9)
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)
