"""Thermal drift with and without compensation, measured on the running daemon (accelerated).

``hexacnc simulate daemon-thermal``: starts the real daemon (hot-loop process, simulated drives)
with the simulated thermal plant (:mod:`hexacnc.sim.thermalplant`) as its probe source, time
scaled by ``--scale``; sends the synthetic milling program (:mod:`hexacnc.sim.program`, the same
as ``simulate thermal``) over and over through the daemon's program path (interpreter, look-ahead
planner, the cycle); the plant heats from the drives' actual strut speeds; the supervisor's
observer feeds the offsets into the cycle.  The status' ``thermal.sim.drift_um`` (tool-tip error
the true growth leaves at the commanded pose, with the applied offsets and spindle growth and
without them) is sampled over the run.

Consistent time scaling: the plant runs ``scale`` times faster than the wall clock, so the offsets'
rate limit is scaled too (``[thermal] max_offset_rate_mm_s`` x scale), but never beyond what the
cycle's acceleration guard takes (:func:`hexacnc.daemon.thermalin.max_safe_offset_rate_mm_s`,
3.9 um/s wall at 0.5 ms): at a large ``scale`` the applied offsets lag the estimate for that reason
alone.  Probes at ``rate_hz`` wall-clock readings per second.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from ..sim.program import synthetic_program, to_gcode_tooltip


def run(cfg, hours: float = 2.5, scale: float = 300.0, rate_hz: float = 2.0, lines: int = 300,
        seed: int = 1, sample_hz: float = 4.0, progress=None) -> dict:
    from . import core
    from .thermalin import max_safe_offset_rate_mm_s
    rate_limit = min(0.999 * max_safe_offset_rate_mm_s(cfg, cfg.cycle.period_s), cfg.thermal.max_offset_rate_mm_s * scale)
    th = dataclasses.replace(cfg.thermal, source="sim", sim_time_scale=float(scale), probe_rate_hz=float(rate_hz),
                             max_offset_rate_mm_s=rate_limit, sim_seed=seed)
    # this measures the thermal path, not bus timing: a loaded development machine may stall the
    # processes for a while without that ending the run (limits on the strut commands stay as they are)
    cy = dataclasses.replace(cfg.cycle, max_overruns_in_row=max(cfg.cycle.max_overruns_in_row, 1000),
                             following_error_mm=max(cfg.cycle.following_error_mm, 25.0))
    bus = dataclasses.replace(cfg.bus, heartbeat_timeout_ms=max(cfg.bus.heartbeat_timeout_ms, 5000))
    run_cfg = cfg.replace(thermal=th, cycle=cy, bus=bus)
    text = to_gcode_tooltip(run_cfg, synthetic_program(run_cfg, lines, seed=seed))
    wall_s = hours * 3600.0 / scale
    rows = []
    passes = 0
    t_wall0 = time.perf_counter()
    faults = []
    with core.Daemon(run_cfg, realtime=True, log_level="WARNING") as d:
        t0 = time.monotonic()
        next_sample = t0
        while True:
            now = time.monotonic()
            st = d.status()
            if st["state"] == "fault":          # e.g. a stall of the loaded machine: note it, go on
                faults.append(st["fault"]["message"])
                if len(faults) > 5:
                    raise RuntimeError(f"daemon faults during the run: {faults}")
                d.reset()
                continue
            tsim = st["thermal"].get("time_s") or 0.0
            if tsim >= hours * 3600.0 or now - t0 > 3 * wall_s + 30:
                break
            if st["state"] == "idle" and (d.current is None and not d.queue):
                d.load_program(text, f"synthetic-{passes + 1}")
                passes += 1
            if now >= next_sample:
                next_sample += 1.0 / sample_hz
                s = st["thermal"].get("sim") or {}
                dr = s.get("drift_um")
                if dr is not None:
                    rows.append([tsim, *dr["uncompensated"], *dr["compensated"],
                                 float(np.mean(s["strut_mean_C"]) - s["frame_C"]),
                                 float(np.mean(s["strut_growth_mm"]) * 1e3),
                                 float(np.mean(st["thermal"]["strut_offsets_est_mm"]) * 1e3),
                                 float(np.mean(st["thermal"]["offsets_mm"]) * 1e3),
                                 s["spindle_growth_mm"] * 1e3, st["thermal"]["spindle_growth_mm"] * 1e3])
                    if progress:
                        progress(tsim, hours * 3600.0)
            time.sleep(0.02)
        d.stop()
        final = d.status()
    S = np.array(rows) if rows else np.zeros((0, 14))
    z_u, z_c = S[:, 3], S[:, 6]
    peak_u = float(np.max(np.abs(z_u))) if len(S) else float("nan")
    peak_c = float(np.max(np.abs(z_c))) if len(S) else float("nan")
    th_st = final["thermal"]
    return {
        "scenario": "daemon, simulated drives and thermal plant, synthetic program repeated",
        "plant_hours": float(S[-1, 0] / 3600.0) if len(S) else 0.0,
        "time_scale": scale, "probe_rate_hz_wall": rate_hz,
        "observer_step_plant_s": scale / rate_hz,
        "offset_rate_limit_mm_s_wall": rate_limit,
        "program_passes": passes,
        "probes": {"per_strut": len(cfg.thermal.probes), "segments": list(cfg.thermal.probes),
                   "noise_K": cfg.thermal.probe_noise_K, "ambient": 1, "frame": 1, "spindle_housing": 1,
                   "spindle_noise_K": cfg.thermal.sim_spindle_noise_K,
                   "total_sensors": 6 * len(cfg.thermal.probes) + 3},
        "peak_drift_z_um": {"uncompensated": peak_u, "compensated": peak_c},
        "reduction_pct": 100.0 * (1.0 - peak_c / peak_u) if peak_u > 0 else float("nan"),
        "rms_drift_z_um": {"uncompensated": float(np.sqrt(np.mean(z_u ** 2))) if len(S) else float("nan"),
                           "compensated": float(np.sqrt(np.mean(z_c ** 2))) if len(S) else float("nan")},
        "strut_frame_dT_K_peak": float(S[:, 7].max()) if len(S) else float("nan"),
        "strut_growth_estimate_error_um": {
            "rms": float(np.sqrt(np.mean((S[:, 9] - S[:, 8]) ** 2))) if len(S) else float("nan")},
        "readings": th_st["readings"], "rejected": th_st["rejected"], "faults_reset": faults,
        "wall_time_s": time.perf_counter() - t_wall0,
        "series": {"columns": ["t_s", "dx_uncomp_um", "dy_uncomp_um", "dz_uncomp_um", "dx_comp_um", "dy_comp_um",
                               "dz_comp_um", "strut_frame_dT_K", "mean_growth_true_um", "mean_growth_est_um",
                               "mean_offset_applied_um", "spindle_growth_true_um", "spindle_growth_applied_um"],
                   "rows": [[round(float(v), 5) for v in r] for r in S]},
    }


def plot(res: dict, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    S = np.array(res["series"]["rows"])
    if not len(S):
        return
    tm = S[:, 0] / 60.0
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7.0, 5.2), sharex=True, gridspec_kw={"height_ratios": [2.2, 1]})
    a1.plot(tm, S[:, 3], color="tab:red", label="uncompensated")
    a1.plot(tm, S[:, 6], color="tab:blue", label="compensated in the daemon")
    a1.axhline(0, color="0.6", lw=0.6)
    a1.set_ylabel("tool z drift at the commanded pose (um)")
    p = res["peak_drift_z_um"]
    a1.set_title(f"Daemon, {res['time_scale']:g}x: peak {p['uncompensated']:.1f} -> {p['compensated']:.1f} um "
                 f"({res['reduction_pct']:.0f} % less)", fontsize=10)
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3)
    a2.plot(tm, S[:, 8], color="k", lw=1, label="true mean growth")
    a2.plot(tm, S[:, 9], color="tab:green", lw=1, ls="--", label="observer estimate")
    a2.plot(tm, S[:, 10], color="tab:blue", lw=1, label="applied offset")
    a2.set_ylabel("strut growth (um)")
    a2.set_xlabel("plant time (min)")
    a2.legend(fontsize=7)
    a2.grid(alpha=0.3)
    fig.tight_layout()
    from ..sim.thermal import save_figure
    save_figure(fig, path)
    plt.close(fig)
