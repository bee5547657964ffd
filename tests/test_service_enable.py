"""A start never moves the machine unless told: with ``[daemon] enable_at_start = false`` (the
default on a real bus) the real daemon cycles with its drives disabled, says why it waits, refuses
motion, and enables only on a controller's ``enable``; the simulated default still enables at start."""
from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import time

import pytest

from hexacnc.config import load_config
from hexacnc.daemon import protocol as P
from hexacnc.daemon.core import Daemon
from hexacnc.daemon.server import SocketServer

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def cfg():
    base = load_config(None)
    cycle = dataclasses.replace(base.cycle, max_overruns_in_row=1000, following_error_mm=25.0)
    return base.replace(cycle=cycle, daemon=dataclasses.replace(base.daemon, enable_at_start=False),
                        bus=dataclasses.replace(base.bus, comm_loss_timeout_s=0.5))     # VM stalls: as e2e_fixtures


@pytest.mark.slow
def test_drives_stay_disabled_until_a_controller_sends_enable(cfg):
    d = tempfile.mkdtemp(prefix="hxe", dir="/tmp")
    try:
        with Daemon(cfg, realtime=False) as daemon, SocketServer(daemon, cfg, os.path.join(d, "e.sock")) as srv:
            with P.Client.unix(srv.socket_path) as c:
                st = c.call("status")
                assert st["drives_enabled"] is False and st["fault"] is None
                assert st["waiting"].startswith("waiting for enable") and "enable_at_start" in st["waiting"]
                assert all((sw & 0x6F) != 0x27 for sw in st["statuswords"])     # none in Operation Enabled
                time.sleep(0.3)
                later = c.call("status")
                assert later["struts_act_mm"] == st["struts_act_mm"]            # nothing moved
                assert later["waiting"] == st["waiting"]
                with pytest.raises(P.DaemonError, match="waiting for enable"):
                    c.call("program", text="G0 X1\n", name="early.ngc")
                r = c.call("enable", reply_timeout_s=30)
                assert r["drives_enabled"] is True and r["waiting"] is None
                st = c.call("status")
                assert all((sw & 0x6F) == 0x27 for sw in st["statuswords"])
                c.call("program", text="G91 G1 X1 F600\n", name="after.ngc")
                assert c.call("wait", timeout_s=30)["state"] == "idle"
                assert c.call("status")["fault"] is None
    finally:
        shutil.rmtree(d, ignore_errors=True)


def test_the_simulated_default_still_enables_at_start():
    base = load_config(None)
    assert base.bus.simulate and base.daemon.enable_at_start
    with Daemon(base, realtime=False) as daemon:
        st = daemon.status()
        assert st["drives_enabled"] is True and st["waiting"] is None
