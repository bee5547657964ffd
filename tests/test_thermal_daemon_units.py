"""Units of the daemon's thermal compensation: config keys, reading validation, the simulated plant,
and the simulated drives' strut model selection."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hexacnc.config import load_config, parse_config
from hexacnc.daemon.thermalin import ThermalInputError, parse_reading, resolve_source
from hexacnc.errors import ConfigError
from hexacnc.sim.thermalplant import ThermalPlant


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def _doc_with(cfg, section, **kv):
    import copy
    doc = copy.deepcopy(cfg.raw)
    doc.setdefault(section, {}).update(kv)
    return doc


@pytest.mark.parametrize("key,value", [("max_offset_mm", 0.0), ("max_offset_mm", 10.0),
                                       ("max_offset_rate_mm_s", -1.0), ("probe_rate_hz", 0.0),
                                       ("sim_time_scale", 0.5), ("stale_after_s", 0.0),
                                       ("source", "probes"), ("probe_max_C", -30.0), ("max_offset_mm", math.nan)])
def test_thermal_daemon_keys_are_range_checked(cfg, key, value):
    with pytest.raises(ConfigError, match=key):
        parse_config(_doc_with(cfg, "thermal", **{key: value}))


def test_thermal_keys_parse_and_source_resolution(cfg):
    c = parse_config(_doc_with(cfg, "thermal", source="socket", max_offset_mm=0.05, sim_time_scale=600.0))
    assert c.thermal.source == "socket" and c.thermal.max_offset_mm == 0.05 and c.thermal.sim_time_scale == 600.0
    assert resolve_source(cfg) == "socket"                 # the embedded default: readings pushed
    auto = cfg.replace(thermal=dataclasses.replace(cfg.thermal, source="auto"))
    assert resolve_source(auto) == "sim"                   # auto on a simulated bus: the plant
    real = auto.replace(bus=dataclasses.replace(cfg.bus, simulate=False))
    assert resolve_source(real) == "socket"
    off = cfg.replace(thermal=dataclasses.replace(cfg.thermal, enabled=False))
    assert resolve_source(off) == "none"


def test_parse_reading_both_forms_agree(cfg):
    tc = cfg.thermal
    rows = [[20.0 + i, 21.0 + i] for i in range(6)]
    a = parse_reading({"probes_C": {"struts": rows, "ambient": 19.5, "frame": 19.8}, "spindle_C": 25.0}, tc)
    flat = [v for r in rows for v in r] + [19.5, 19.8]
    b = parse_reading({"probes_C": flat, "spindle_C": 25.0, "time_s": 12.0}, tc)
    assert np.array_equal(a["struts"], b["struts"]) and a["ambient"] == b["ambient"] == 19.5
    assert a["frame"] == 19.8 and a["spindle"] == 25.0 and b["time_s"] == 12.0 and a["time_s"] is None


@pytest.mark.parametrize("bad,field", [(True, "probes_C[3]"), (None, "probes_C[3]"), ("20", "probes_C[3]")])
def test_parse_reading_rejects_non_numbers(cfg, bad, field):
    flat = [20.0] * 14
    flat[3] = bad
    with pytest.raises(ThermalInputError) as ei:
        parse_reading({"probes_C": flat}, cfg.thermal)
    assert ei.value.field == field and ei.value.code == "bad_type"


def test_plant_heats_with_speed_and_probes_are_noisy_around_truth(cfg):
    p = ThermalPlant(cfg, seed=3)
    g0 = p.growth_mm().copy()
    assert np.allclose(g0, 0.0)                            # from cold at the reference temperature
    for _ in range(60):
        p.step(60.0, [20.0, 20.0, 10.0, 10.0, 0.0, 0.0], True)
    g = p.growth_mm()
    assert g[0] > g[2] > g[4] >= -1e-3 and g[0] > 0.01    # more speed, more heat, more growth
    assert p.spindle_growth_mm() > 0.0 and p.housing_C > p.shaft_C > p.ambient_C - 0.2
    r = p.readings()
    truth = p.T[:, p.pidx]
    err = np.array(r["probes_C"]["struts"]) - truth
    assert 0 < np.std(err) < 5 * cfg.thermal.probe_noise_K
    assert r["time_s"] == pytest.approx(3600.0)
    # the plant's heat is the configured model's times the scenario's truth ratio (model is wrong on purpose)
    assert p.heat_per_speed_W_s_mm == pytest.approx(cfg.thermal.heat_per_speed_W_s_mm * 1.15)


def test_simulated_drives_model_selected_by_config(cfg):
    from drivers.strutmodel import SecondOrderStrut
    from hexacnc.sim.drives import strut_model_factory as config_model_factory
    assert isinstance(config_model_factory(cfg)(0, cfg), SecondOrderStrut)
    cc = cfg.replace(dynamics=dataclasses.replace(cfg.dynamics, simulated_drives="coupled"))
    f = config_model_factory(cc)
    views = [f(i, cc) for i in range(6)]
    assert type(views[0]).__name__ == "_StrutView" and views[0].s is views[5].s     # one coupled model
    with pytest.raises(ConfigError, match="simulated_drives"):
        parse_config(_doc_with(cfg, "dynamics", simulated_drives="rigid"))


def test_offset_rate_the_cycle_cannot_take_is_refused(cfg):
    from hexacnc.daemon.thermalin import check_offset_rate, max_safe_offset_rate_mm_s
    lim = max_safe_offset_rate_mm_s(cfg, 0.0005)
    assert cfg.thermal.max_offset_rate_mm_s <= lim             # the default fits the default cycle
    fast = cfg.replace(thermal=dataclasses.replace(cfg.thermal, max_offset_rate_mm_s=0.05))
    with pytest.raises(ConfigError, match="max_offset_rate_mm_s"):
        check_offset_rate(fast, 0.0005)
    check_offset_rate(fast, 0.01)                              # a slower cycle takes it


def test_coupled_views_stay_in_step_when_bus_threads_interleave(cfg):
    """Drives stepped out of order (bus 0's cycle k+1 before bus 1's cycle k) see exactly what the
    coupled model gives for the same commands stepped in order."""
    from hexacnc.kinematics import Hexapod
    from hexacnc.sim.strut import CoupledStruts, coupled_model_factory
    hx = Hexapod(cfg)
    dt = 0.0005
    n = 400
    t = np.arange(n) * dt
    poses = np.tile(np.asarray(cfg.home_pose, dtype=float), (n, 1))
    poses[:, 0] += 20.0 * (1 - np.cos(2 * np.pi * 2.5 * t))          # 2.5 Hz, 20 mm: strong accelerations
    L = hx.inverse_batch(poses)
    off = np.asarray(cfg.strut_offset_mm, dtype=float)
    ref = CoupledStruts(cfg)
    ref.reset(L[0])
    want = np.array([ref.step(L[k], dt).copy() for k in range(n)])
    f = coupled_model_factory(gains=ref.g)
    views = [f(i, cfg) for i in range(6)]
    for i in range(6):
        views[i].reset(L[0, i] - off[i])
    got = np.full((n, 6), np.nan)
    bus0, bus1 = (0, 1, 2), (3, 4, 5)
    for k in range(n + 1):           # bus 0 runs one cycle ahead of bus 1
        if k < n:
            for i in bus0:
                got[k, i] = views[i].step(L[k, i] - off[i], dt, True)
        if k >= 1:
            for i in bus1:
                got[k - 1, i] = views[i].step(L[k - 1, i] - off[i], dt, True)
    # the last drive of a cycle reads the model exactly; drives stepped before it read their command
    # plus the model's error of the last completed cycle (bus 1: one cycle old, bus 0 ahead: two)
    e = want - L
    np.testing.assert_allclose(got[:, 5] + off[5], want[:, 5], atol=1e-9)
    np.testing.assert_allclose(got[1:, 3:5] + off[3:5] - L[1:, 3:5], e[:-1, 3:5], atol=1e-9)
    np.testing.assert_allclose(got[2:, :3] + off[:3] - L[2:, :3], e[:-2, :3], atol=1e-9)
    assert np.max(np.abs(want - L)) > 1e-4           # the model does have following errors here


def test_spindle_probe_lag_key(cfg):
    c = parse_config(_doc_with(cfg, "spindle", probe_lag_s=300.0))
    assert c.spindle.probe_lag_s == 300.0 and cfg.spindle.probe_lag_s == 0.0
    with pytest.raises(ConfigError, match="probe_lag_s"):
        parse_config(_doc_with(cfg, "spindle", probe_lag_s=-1.0))


def test_supervisor_spindle_lag_and_target_ramp_without_a_daemon(cfg):
    """ThermalSupervisor on a bare shared-memory block (no hot loop, no thread): the shaft lags the
    housing probe by [spindle] probe_lag_s, and the targets ramp at the rate limit."""
    from hexacnc.daemon import shm as S
    from hexacnc.daemon.thermalsup import ThermalSupervisor
    c = cfg.replace(spindle=dataclasses.replace(cfg.spindle, probe_lag_s=300.0),
                    thermal=dataclasses.replace(cfg.thermal, source="socket"))
    sh = S.Shared(create=True)
    try:
        ts = ThermalSupervisor(c, sh)
        flat = [20.0] * 14
        for t_s, T_sp in ((0.0, 20.0), (300.0, 30.0)):
            ts.push({"probes_C": flat, "spindle_C": T_sp, "time_s": t_s})
            ts._observe(ts.pending.popleft())
        shaft = 20.0 + (1.0 - math.exp(-1.0)) * 10.0          # housing stepped 10 K, one time constant
        assert ts.shaft_C == pytest.approx(shaft, abs=1e-9)
        assert ts.spindle_est == pytest.approx(c.spindle.growth_mm_per_K * (shaft - 20.0), abs=1e-12)
        # targets: from what the loop applies (0) towards the estimate at max_offset_rate_mm_s
        t0, sp0 = ts.tgt_wall, sh.s[S.S_SPINDLE_TGT]
        assert 0.0 <= sp0 < ts.spindle_est
        with ts.lock:                       # 0.2 s later on the supervisor's clock (no sleep)
            ts._write_targets(t0 + 0.2)
        dt = ts.tgt_wall - t0
        step = sh.s[S.S_SPINDLE_TGT] - sp0
        assert step == pytest.approx(min(ts.spindle_est - sp0, c.thermal.max_offset_rate_mm_s * dt), abs=1e-12)
        assert 0.0 < step <= c.thermal.max_offset_rate_mm_s * dt + 1e-12
    finally:
        sh.close()
