"""CiA 402 homing end to end (``[homing] method = "cia402"``): ``hexacnc home`` against the real
daemon (hot-loop process) and the simulated drives (homing mode 6, :mod:`drivers.simhoming`)."""
from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
import pytest

from drivers import cia402, simhoming
from hexacnc.cli import main as cli
from hexacnc.daemon import protocol as P
from hexacnc.kinematics import Hexapod
from hexacnc.config.operator import HomingConfig

from e2e_fixtures import cfg, machine_running  # noqa: F401

pytestmark = pytest.mark.e2e


def start_positions_mm(c) -> np.ndarray:
    """The simulated drives' power-up position values (mm): the home pose."""
    return Hexapod(c).lengths(c.home_pose) - np.asarray(c.strut_offset_mm, dtype=float)


def homing_machine(c, method: int, offset_mm, speed_search_mm_s: float = 10.0):
    hm = HomingConfig(method="cia402", required=True, homing_method=method, speed_search_mm_s=speed_search_mm_s,
                      speed_zero_mm_s=2.0, acceleration_mm_s2=100.0, offset_mm=np.asarray(offset_mm, dtype=float))
    return c.replace(operator=dataclasses.replace(c.operator, homing=hm))


def run(capsys, *argv):
    rc = cli(list(argv))
    out = capsys.readouterr()
    return rc, out.out, out.err


def status(sock) -> dict:
    with P.Client.unix(sock) as c:
        return c.call("status")


def check_back_in_csp(st: dict) -> None:
    for sw in st["statuswords"]:
        assert cia402.state_from_status(sw) == cia402.OPERATION_ENABLED, hex(sw)
        assert sw & cia402.SW_DRIVE_FOLLOWS, hex(sw)       # cyclic synchronous position again
    assert st["state"] == "idle" and st["drives_enabled"]


def test_home_method_35_sets_the_offsets_and_unlocks_motion(cfg, capsys):  # noqa: F811
    start = start_positions_mm(cfg)
    delta = np.array([0.3, -0.25, 0.2, -0.15, 0.35, -0.3])
    mc = homing_machine(cfg, 35, start + delta)
    with machine_running(mc, name="hm35") as (daemon, srv):
        sock = srv.socket_path
        st = status(sock)
        assert st["referenced"] is False
        act0 = np.array(st["struts_act_mm"])
        rc, out, err = run(capsys, "mdi", "G91 G1 Z-0.5 F300", "--socket", sock)
        assert rc != 0 and "not referenced" in err
        with P.Client.unix(sock) as c:                      # a program: refused, nothing queued
            with pytest.raises(Exception, match="not referenced"):
                c.call("program", text="G91 G1 Z-0.5 F300\nM2\n", name="before-home")
        rc, out, err = run(capsys, "jog", "z", "+0.1", "--socket", sock)
        assert rc != 0 and "not referenced" in err
        assert status(sock)["pose_cmd"] == st["pose_cmd"]
        rc, out, err = run(capsys, "home", "--socket", sock)
        assert rc == 0, err
        assert "referenced" in out
        st = status(sock)
        assert st["referenced"] is True
        check_back_in_csp(st)
        act = np.array(st["struts_act_mm"])
        ipm = mc.bus.increments_per_mm
        # the position values are the home offsets now (the struts did not move): act jumped by delta;
        # the re-seeded command IK(FK(measured)) may differ from the measurement by a few um
        want = start + delta + np.asarray(mc.strut_offset_mm, dtype=float)
        assert np.all(np.abs(act - want) <= 0.01 + 2.0 / ipm), (act - want)
        assert np.all(np.abs((act - act0) - delta) < 0.01)
        # the loop was re-seeded from them: command = measured, no step, no fault
        assert np.all(np.abs(np.array(st["struts_cmd_mm"]) - act) < 0.01)
        # program motion is accepted now, and runs
        rc, out, err = run(capsys, "mdi", "G91 G1 Z-0.5 F300", "--socket", sock)
        assert rc == 0, err
        with P.Client.unix(sock) as c:
            assert c.call("wait", timeout_s=30.0)["state"] == "idle"


def test_home_on_the_limit_switches_moves_each_strut_there(cfg, capsys):  # noqa: F811
    start = start_positions_mm(cfg)
    # method 18: positive limit switch, SWITCH_FROM_START_MM above the power-up position; the offset
    # makes the position value there read the true distance again
    offsets = start + simhoming.SWITCH_FROM_START_MM
    mc = homing_machine(cfg, 18, offsets)
    with machine_running(mc, name="hm18") as (daemon, srv):
        sock = srv.socket_path
        act0 = np.array(status(sock)["struts_act_mm"])
        result = {}

        def home():
            with P.Client.unix(sock) as c:
                result["reply"] = c.call("home", reply_timeout_s=60.0)
        th = threading.Thread(target=home)
        th.start()
        peak = np.zeros(6)
        states = set()
        while th.is_alive():
            st = status(sock)
            states.add(st.get("loop_state"))
            peak = np.maximum(peak, np.array(st["struts_act_mm"]) - act0)
            time.sleep(0.02)
        th.join()
        assert result["reply"]["referenced"] is True
        assert "homing" in states
        # every strut went up to its switch (and backed off it at the zero speed)
        assert np.all(peak > simhoming.SWITCH_FROM_START_MM - 0.1), peak
        st = status(sock)
        check_back_in_csp(st)
        act = np.array(st["struts_act_mm"])
        want = offsets + np.asarray(mc.strut_offset_mm, dtype=float)
        # position value := offset at the switch edge; the strut stopped within the zero-speed ramp
        assert np.all(np.abs(act - want) < 0.1), act - want
        assert np.all(np.abs(np.array(st["struts_cmd_mm"]) - act) < 0.01)
        assert st["referenced"] is True


def test_stop_and_disable_during_homing_leave_it_unreferenced(cfg, capsys):  # noqa: F811
    start = start_positions_mm(cfg)
    mc = homing_machine(cfg, 17, start - simhoming.SWITCH_FROM_START_MM, speed_search_mm_s=0.5)   # ~4 s
    with machine_running(mc, name="hmst") as (daemon, srv):
        sock = srv.socket_path
        for how in ("stop", "disable"):
            result = {}

            def home():
                with P.Client.unix(sock) as c:
                    try:
                        result["reply"] = c.call("home", reply_timeout_s=60.0)
                    except Exception as exc:      # the refusal the client gets
                        result["error"] = str(exc)
            th = threading.Thread(target=home)
            th.start()
            t_end = time.monotonic() + 10.0
            while status(sock).get("loop_state") != "homing" and time.monotonic() < t_end:
                time.sleep(0.01)
            time.sleep(0.1)                       # the struts are on their way to the switches
            assert status(sock).get("loop_state") == "homing"
            with P.Client.unix(sock) as c2:
                c2.call("take")
                c2.call(how, reply_timeout_s=30.0)
            th.join(30.0)
            assert "reply" not in result and "stopped" in result["error"], result
            st = status(sock)
            assert st["referenced"] is False
            if how == "stop":
                assert st["loop_state"] == "idle" and st["drives_enabled"] and st["fault"] is None
                assert np.all(np.abs(np.array(st["struts_cmd_mm"]) - np.array(st["struts_act_mm"])) < 0.05)
            else:
                assert st["loop_state"] == "disabled" and not st["drives_enabled"]
            rc, out, err = run(capsys, "mdi", "G91 G1 Z-0.5 F300", "--socket", sock)
            assert rc != 0 and ("not referenced" in err or "disabled" in err), err
