"""Strut heat model: analytic steady state, exact discretisation, observer, observability."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.errors import ConfigError, DataError
from hexacnc.thermal import (ThermalObserver, discretise, observability, probe_matrix,
                             spindle_growth_mm, strut_heat_model)


@pytest.fixture(scope="module")
def cfg():
    return load_config()


def analytic_steady(tc, length_mm, speed, Ta, Tf, x_mm):
    """Continuous 1-D rod: k A T'' - h P (T - Ta) + q' = 0, Robin ends k A T' = +-G (T - Tf)."""
    L = length_mm * 1e-3
    kA = tc.conductivity_W_mK * tc.area_mm2 * 1e-6
    hP = tc.convection_W_m2K * tc.perimeter_mm * 1e-3
    q = tc.heat_per_speed_W_s_mm * speed / L          # W/m, uniform
    G = tc.end_conductance_W_K
    m = math.sqrt(hP / kA)
    T_inf = Ta + q / hP
    c1 = -G * (T_inf - Tf) / (kA * m * math.sinh(m * L / 2) + G * math.cosh(m * L / 2))
    x = np.asarray(x_mm) * 1e-3
    T = T_inf + c1 * np.cosh(m * (x - L / 2))
    mean_theta = T_inf + c1 * (2 / (m * L)) * math.sinh(m * L / 2)   # mean temperature
    return T, mean_theta


@pytest.mark.parametrize("speed,Ta,Tf", [(80.0, 20.0, 20.0), (30.0, 22.0, 19.0), (0.0, 25.0, 20.0)])
def test_steady_state_matches_continuous_solution(cfg, speed, Ta, Tf):
    tc = cfg.thermal
    L = 1000.0
    fine = strut_heat_model(tc, L, segments=400)
    T_fine = fine.steady_state(speed, Ta, Tf)
    T_exact, T_mean = analytic_steady(tc, L, speed, Ta, Tf, fine.segment_centres_mm())
    scale = max(1.0, float(np.max(np.abs(T_exact - Tf))))
    assert np.max(np.abs(T_fine - T_exact)) < 1e-4 * scale
    # the configured coarse grid (10 segments) is second order: still within 2 % of the rise
    coarse = strut_heat_model(tc, L)
    T_c = coarse.steady_state(speed, Ta, Tf)
    T_exact_c, _ = analytic_steady(tc, L, speed, Ta, Tf, coarse.segment_centres_mm())
    rise = max(1e-9, float(np.max(np.abs(T_exact_c - min(Ta, Tf)))))
    assert np.max(np.abs(T_c - T_exact_c)) < 0.02 * rise
    # growth: alpha * L * (mean temperature - reference)
    g_exact = tc.expansion_per_K * L * (T_mean - tc.reference_temperature_C)
    assert coarse.growth_mm(T_c) == pytest.approx(g_exact, rel=0.02, abs=1e-6)
    assert fine.growth_mm(T_fine) == pytest.approx(g_exact, rel=1e-4, abs=1e-9)


def test_discretisation_exact_and_consistent(cfg):
    m = strut_heat_model(cfg.thermal, 1000.0)
    Ad1, Bd1 = discretise(m.A, m.B, 0.5)
    Ad2, Bd2 = discretise(m.A, m.B, 1.0)
    # two half steps equal one full step (semigroup property of the exact ZOH)
    assert np.allclose(Ad1 @ Ad1, Ad2, atol=1e-13)
    assert np.allclose(Ad1 @ Bd1 + Bd1, Bd2, atol=1e-13)
    # the discrete fixed point is the continuous equilibrium
    u = np.array([60.0, 21.0, 20.0])
    T_ss = np.linalg.solve(np.eye(m.n) - Ad2, Bd2 @ u)
    assert np.allclose(T_ss, m.steady_state(60.0, 21.0, 20.0), atol=1e-9)
    # a fine explicit RK4 integration of dT/dt = A T + B u agrees with the exact step
    T0 = np.linspace(18.0, 24.0, m.n)
    h, T = 0.01, T0.copy()
    f = lambda T: m.A @ T + m.B @ u  # noqa: E731
    for _ in range(int(round(60.0 / h))):
        k1 = f(T); k2 = f(T + h / 2 * k1); k3 = f(T + h / 2 * k2); k4 = f(T + h * k3)
        T = T + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    Ad60, Bd60 = discretise(m.A, m.B, 60.0)
    assert np.allclose(Ad60 @ T0 + Bd60 @ u, T, atol=1e-8)
    with pytest.raises(DataError):
        discretise(m.A, m.B, 0.0)


def test_observer_converges_from_wrong_state_with_noisy_probes(cfg):
    tc = cfg.thermal
    dt = 2.0
    rng = np.random.default_rng(7)
    obs = ThermalObserver(cfg, dt, T0_C=26.0)           # 6 K too warm: ~70 um wrong at start
    truth = obs.models                                  # truth: same structure, 40 segments
    fine = [strut_heat_model(tc, mm.length_mm, segments=40) for mm in truth]
    disc = [discretise(f.A, f.B, dt) for f in fine]
    Ad = np.stack([d[0] for d in disc])
    Bd = np.stack([d[1] for d in disc])
    Cf = np.stack([f.C for f in fine])
    T = np.full((6, 40), 20.0)
    centres = obs.models[0].segment_centres_mm()
    probe_idx = [int(centres[p] / fine[0].length_mm * 40) for p in obs.probes]
    errs = []
    for k in range(3600):
        speed = 40.0 + 30.0 * np.sin(2 * np.pi * k * dt / 900.0 + np.arange(6))
        u = np.stack([np.abs(speed), np.full(6, 20.0), np.full(6, 20.0)], axis=1)
        T = np.einsum("ijk,ik->ij", Ad, T) + np.einsum("ijk,ik->ij", Bd, u)
        y = T[:, probe_idx] + rng.normal(0.0, tc.probe_noise_K, (6, len(probe_idx)))
        off = obs.update(speed, 20.0, 20.0, y)
        true_growth = np.einsum("ij,ij->i", T - tc.reference_temperature_C, Cf)
        errs.append(np.max(np.abs(off - true_growth)))
    errs = np.array(errs)
    assert errs[0] > 0.03                      # really started wrong
    assert np.max(errs[-900:]) < 0.002         # last 30 min: within 2 um on every strut
    assert np.all(np.isfinite(obs.T_est))


def test_probe_set_observability(cfg):
    obs = ThermalObserver(cfg, 0.1)
    assert all(o["observable"] for o in obs.observability)
    # a single probe in the middle of an odd grid cannot see the antisymmetric modes
    tc = dataclasses.replace(cfg.thermal, segments=11, probes=(5,))
    m = strut_heat_model(tc, 1000.0)
    rep = observability(m.A, probe_matrix(11, (5,)))
    assert not rep["observable"]
    with pytest.raises(ConfigError, match="not observable"):
        ThermalObserver(cfg.replace(thermal=tc), 0.1)
    # ... while an end probe sees every mode
    assert observability(m.A, probe_matrix(11, (0,)))["observable"]
    with pytest.raises(ConfigError, match="duplicate"):
        probe_matrix(10, (2, 2))


def test_update_rejects_bad_shapes_and_survives_nan(cfg):
    obs = ThermalObserver(cfg, 0.1)
    with pytest.raises(DataError):
        obs.update(np.zeros(6), 20.0, 20.0, np.zeros((6, 3)))
    y = np.full((6, len(obs.probes)), np.nan)
    off = obs.update(np.full(6, 50.0), 20.0, 20.0, y)
    assert np.all(np.isfinite(off)) and obs.status == "predicted"
    before = obs.T_est.copy()
    off = obs.update(np.full(6, 50.0), float("nan"), 20.0, np.full((6, len(obs.probes)), 20.0))
    assert obs.status == "bad_input" and np.array_equal(obs.T_est, before) and np.all(np.isfinite(off))
    with pytest.raises(DataError):
        obs.update(np.zeros(5), 20.0, 20.0, np.zeros((6, len(obs.probes))))
    obs.update(np.zeros(6), 20.0, 20.0, np.full((6, len(obs.probes)), 20.0))
    assert obs.status == "ok"


def test_spindle_growth(cfg):
    assert spindle_growth_mm(cfg.spindle.reference_temperature_C, cfg) == 0.0
    assert spindle_growth_mm(cfg.spindle.reference_temperature_C + 10.0, cfg) == pytest.approx(
        10.0 * cfg.spindle.growth_mm_per_K)
    with pytest.raises(DataError):
        spindle_growth_mm(float("nan"), cfg)
