"""The struts' reference is dropped when it can no longer be trusted (:mod:`hexacnc.daemon.reference`),
against the real daemon and the simulated drives: a fault (incremental encoders, ``[homing] method =
"cia402"``), a drive's power cycle (NMT reset node: its position counter restarts), an encoder error
EMCY (absolute encoders too); with ``[homing] required`` motion is then refused with the reason until
``home`` again."""
from __future__ import annotations

import time

import numpy as np
import pytest

from hexacnc.daemon import protocol as P

from e2e_fixtures import cfg, machine_running  # noqa: F401
from test_e2e_homing import homing_machine, run, start_positions_mm, status

pytestmark = pytest.mark.e2e


def _wait(sock, pred, timeout_s=10.0) -> dict:
    t_end = time.monotonic() + timeout_s
    while True:
        st = status(sock)
        if pred(st):
            return st
        assert time.monotonic() < t_end, st
        time.sleep(0.02)


def _fault_and_reset(daemon, sock, kind, node, value) -> dict:
    daemon.inject_drive(kind, node, value)
    _wait(sock, lambda st: st["state"] == "fault")
    with P.Client.unix(sock) as c:
        c.call("reset", reply_timeout_s=30.0)
    return _wait(sock, lambda st: st["state"] == "idle" and st["drives_enabled"])


def test_incremental_reference_is_lost_on_a_fault_and_motion_refused_until_homed(cfg, capsys):  # noqa: F811
    mc = homing_machine(cfg, 35, start_positions_mm(cfg))
    with machine_running(mc, name="rfi") as (daemon, srv):
        sock = srv.socket_path
        rc, out, err = run(capsys, "home", "--socket", sock)
        assert rc == 0, err
        assert status(sock)["referenced"] is True
        st = _fault_and_reset(daemon, sock, "emcy", 2, 0x2310)         # over-current: drives disabled
        assert st["referenced"] is False
        assert "EMCY from drive 2" in st["reference_lost"]["reason"], st["reference_lost"]
        assert "not referenced" in st["why_idle"]
        rc, out, err = run(capsys, "mdi", "G91 G1 Z-0.2 F300", "--socket", sock)
        assert rc != 0 and "not referenced" in err and "EMCY from drive 2" in err, err
        assert len(err.strip().splitlines()) == 1
        rc, out, err = run(capsys, "jog", "z", "+0.1", "--socket", sock)
        assert rc != 0 and "not referenced" in err
        rc, out, err = run(capsys, "jog", "3", "+0.1", "--socket", sock)     # a strut jog is allowed
        assert rc == 0, err
        with P.Client.unix(sock) as c:
            c.call("wait", timeout_s=30.0)
        rc, out, err = run(capsys, "home", "--socket", sock)
        assert rc == 0, err
        st = status(sock)
        assert st["referenced"] is True and st["reference_lost"] is None
        rc, out, err = run(capsys, "mdi", "G91 G1 Z-0.2 F300", "--socket", sock)
        assert rc == 0, err
        with P.Client.unix(sock) as c:
            assert c.call("wait", timeout_s=30.0)["state"] == "idle"
        # a plain disable keeps the reference (the drives keep counting)
        for cmd in ("disable", "enable"):
            rc, out, err = run(capsys, cmd, "--socket", sock)
            assert rc == 0, err
        assert status(sock)["referenced"] is True


def test_a_homing_error_leaves_it_unreferenced_naming_the_drive(cfg, capsys):  # noqa: F811
    mc = homing_machine(cfg, 99, start_positions_mm(cfg))                 # a method the drives do not have
    with machine_running(mc, name="rfh") as (daemon, srv):
        sock = srv.socket_path
        rc, out, err = run(capsys, "home", "--socket", sock)
        assert rc != 0 and "homing error" in err and len(err.strip().splitlines()) == 1, err
        st = status(sock)
        assert st["referenced"] is False and "homing error" in st["reference_lost"]["reason"]
        rc, out, err = run(capsys, "mdi", "G91 G1 Z-0.2 F300", "--socket", sock)
        assert rc != 0


def test_a_drive_power_cycle_restarts_its_counter_and_drops_the_reference(cfg, capsys):  # noqa: F811
    start = start_positions_mm(cfg)
    delta = np.full(6, 0.25)
    mc = homing_machine(cfg, 35, start + delta)
    with machine_running(mc, name="rfb") as (daemon, srv):
        sock = srv.socket_path
        rc, out, err = run(capsys, "home", "--socket", sock)
        assert rc == 0, err
        assert status(sock)["referenced"] is True
        daemon.inject_drive("nmt", 4, 0x81)                           # reset node: a power cycle
        st = _wait(sock, lambda st: st["referenced"] is False)
        assert "power-cycled" in st["reference_lost"]["reason"], st["reference_lost"]
        _wait(sock, lambda st: st["state"] == "fault")
        rc, out, err = run(capsys, "mdi", "G91 G1 Z-0.2 F300", "--socket", sock)
        assert rc != 0 and len(err.strip().splitlines()) == 1, err


def test_absolute_encoders_keep_the_reference_through_faults_but_not_an_encoder_error(cfg, capsys):  # noqa: F811
    import dataclasses
    from hexacnc.config.operator import HomingConfig
    mc = cfg.replace(operator=dataclasses.replace(cfg.operator, homing=HomingConfig(method="absolute",
                                                                                     required=True)))
    with machine_running(mc, name="rfa") as (daemon, srv):
        sock = srv.socket_path
        assert status(sock)["referenced"] is True
        st = _fault_and_reset(daemon, sock, "emcy", 1, 0x2310)
        assert st["referenced"] is True
        rc, out, err = run(capsys, "mdi", "G91 G1 Z-0.2 F300", "--socket", sock)
        assert rc == 0, err
        with P.Client.unix(sock) as c:
            c.call("wait", timeout_s=30.0)
        st = _fault_and_reset(daemon, sock, "emcy", 5, 0x7305)         # incremental sensor 1 fault
        assert st["referenced"] is False and "encoder error" in st["reference_lost"]["reason"]
        rc, out, err = run(capsys, "mdi", "G91 G1 Z-0.2 F300", "--socket", sock)
        assert rc != 0 and "not referenced" in err and "encoder" in err, err
        rc, out, err = run(capsys, "home", "--socket", sock)           # absolute: acknowledged
        assert rc == 0, err
        assert status(sock)["referenced"] is True


def test_bench_homing_finds_the_switch_edge_within_a_cycle_of_travel(cfg, capsys):  # noqa: F811
    """``hexacnc bench homing`` against the simulated drives: method 18 references all six struts and
    their position values match the drives' true switch edge within one servo cycle at the zero speed."""
    import json

    from hexacnc.cli import main as cli
    rc = cli(["bench", "homing", "--methods", "18", "--repeats", "1", "--no-realtime"])
    out = capsys.readouterr().out
    assert rc == 0
    res = json.loads(out)["methods"]["18"]
    assert res["runs"][0]["referenced_drives"] == 6
    bound_um = 1e3 * 2.0 * cfg.cycle.period_s + res["resolution_um"]      # speed_zero 2 mm/s, one cycle
    assert res["accuracy_um"] <= bound_um, res
    assert 0.0 < res["time_s"]["max"] < 30.0
    rc = cli(["bench", "homing", "--methods", "35,99"])
    assert rc == 2
