"""Strut dynamics model for the simulated drives; the simulate command end to end."""
from __future__ import annotations

import json

import numpy as np
import pytest

from hexacnc.cli import main as cli_main
from hexacnc.config import load_config
from hexacnc.sim.dynamics import CoupledModel, simulate_path
from hexacnc.sim.program import synthetic_program, trajectory
from hexacnc.sim.strut import CoupledStruts, coupled_model_factory, default_gains


@pytest.fixture(scope="module")
def cfg():
    return load_config()


def test_factory_views_follow_like_the_path_simulation(cfg):
    f = coupled_model_factory()
    views = [f(i, cfg) for i in range(6)]
    tr = trajectory(cfg, synthetic_program(cfg, 6, seed=4), dt_s=cfg.cycle.period_s)
    n = min(len(tr.t_s), 8000)
    q = tr.lengths_mm[:n] - np.asarray(cfg.strut_offset_mm)
    for i, v in enumerate(views):
        v.reset(q[0, i])
    err = np.empty((n, 6))
    for k in range(n):
        err[k] = [q[k, i] - v.step(q[k, i], tr.dt_s, True) for i, v in enumerate(views)]
    model = CoupledModel(cfg)
    ref = simulate_path(model, default_gains(model), tr.poses[:n], tr.dt_s)
    fe = np.abs(err).max(axis=0) * 1e3
    assert np.allclose(fe, ref["following_error_um"]["max_per_strut"], rtol=0.15, atol=1.0)
    assert max(fe) > 1.0                     # realistic: a moving drive lags
    assert all(abs(v.velocity_mm_s) < 1e3 for v in views)


def test_rest_and_disable_hold_position(cfg):
    cs = CoupledStruts(cfg)
    L0 = cs.position_mm.copy()
    for _ in range(200):
        out = cs.step(L0, 0.0005)
    assert np.allclose(out, L0, atol=1e-9)
    f = coupled_model_factory()
    v = [f(i, cfg) for i in range(6)]
    v[0].reset(100.0)
    for _ in range(50):
        p = [vi.step(123.0, 0.0005, False) for vi in v]   # disabled: brake holds
    assert p[0] == pytest.approx(100.0, abs=1e-9)


def test_simulate_controller_command_writes_json_and_png(tmp_path, capsys):
    rc = cli_main(["simulate", "controller", "--out", str(tmp_path), "--grid", "3"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["coupled"]["settling_time_s"] < out["conventional"]["settling_time_s"]
    saved = json.loads((tmp_path / "controller.json").read_text())
    assert "series" in saved and saved["step_um"] == 50.0
    assert (tmp_path / "controller.png").stat().st_size > 1000
    assert not list(tmp_path.glob("*.tmp*"))


def test_simulate_rejects_bad_arguments(tmp_path, capsys):
    assert cli_main(["simulate", "thermal", "--hours", "-1", "--out", str(tmp_path)]) == 2
    assert "--hours" in capsys.readouterr().err
    assert cli_main(["simulate", "dynamics", "--lines", "1", "--out", str(tmp_path)]) == 2


@pytest.mark.bus
def test_plugs_into_the_simulated_drives():
    import math
    import time

    from drivers.cyclic import EV_EMCY, SEND_OK
    from hexacnc.sim.rig import SimRig

    with SimRig(model_factory=coupled_model_factory()) as rig:
        rig.master.bring_up()
        start = rig.master.positions_inc()
        io = rig.cyclic()
        amp = [20000, -15000, 10000, -5000, 30000, 25000]        # up to 3 mm
        n = 600
        ev = 0
        lag = 0
        for k in range(n + 300):
            s = 0.5 - 0.5 * math.cos(math.pi * min(k, n) / n)
            assert io.send([start[i] + round(amp[i] * s) for i in range(6)]) == SEND_OK
            time.sleep(0.0005)
            ev |= io.poll()
            if k == n // 2:
                pos = rig.sim.positions_inc()
                tgt = [start[i] + round(amp[i] * s) for i in range(6)]
                lag = max(abs(pos[i] - tgt[i]) for i in range(6))
        assert not ev & EV_EMCY, list(io.emcy)
        final = rig.sim.positions_inc()
        for i in range(6):
            assert abs(final[i] - (start[i] + amp[i])) <= 5, (i, final[i], start[i] + amp[i])
        assert lag > 0          # the coupled drives lag while moving (realistic following error)
