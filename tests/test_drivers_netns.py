"""Cross-process: master here, simulated drives in their own process, udp_multicast in a private netns.

Each test re-runs itself inside a fresh network namespace (``drivers.testing.netns_or_rerun``);
it is skipped cleanly where ``unshare -n`` is not available.
"""
import dataclasses
import math
import time

import can
import pytest

from hexacnc.config import load_config
from drivers import cia402
from drivers.canbus import open_buses
from drivers.cyclic import EV_EMCY, SEND_OK, CyclicIO, limits_inc
from drivers.master import Master
from hexacnc.sim.drives import spawn
from drivers.testing import PdoDecoder, netns_or_rerun

pytestmark = [pytest.mark.bus, pytest.mark.netns]

CHANNEL = "239.74.163.20"


def udp_cfg():
    cfg = load_config()
    # loaded test machine: the drives' RPDO deadline (comm_loss_timeout_s) must outlast its stalls
    return cfg.replace(bus=dataclasses.replace(cfg.bus, interface="udp_multicast", channel=CHANNEL,
                                               comm_loss_timeout_s=0.5))


@pytest.mark.slow
def test_echo_filter_between_processes_and_buses(request):
    if not netns_or_rerun(request):
        return
    cfg = udp_cfg()
    a, b = open_buses(cfg.bus), open_buses(cfg.bus)
    try:
        a[0].send(can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False))
        got = b[0].recv(1.0)
        assert got is not None and got.arbitration_id == 0x123 and bytes(got.data) == b"\x01\x02"
        assert a[0].recv(0.2) is None and a[0].echoes_dropped == 1      # own frame filtered
        assert b[1].recv(0.2) is None                                    # the other bus is another group
    finally:
        for x in a + b:
            x.shutdown()


def test_master_and_simulated_drives_process_reach_operation_enabled(request):
    if not netns_or_rerun(request):
        return
    cfg = udp_cfg()
    proc = spawn(None, interface="udp_multicast", channel=CHANNEL)
    buses = open_buses(cfg.bus)
    dec = None
    try:
        m = Master(cfg, buses)
        m.bring_up(timeout_s=3.0)
        sw = m.statuswords()
        assert [cia402.state_from_status(s) for s in sw] == [cia402.OPERATION_ENABLED] * 6
        start = m.positions_inc()
        dec = PdoDecoder(cfg)
        m.detach()
        io = CyclicIO(buses, cfg.bus, limits_inc=limits_inc(cfg), status=sw, positions_inc=start)
        sent = []
        amp = [5000, -5000, 4000, -4000, 3000, -3000]
        n = 300
        for k in range(n + 300):
            s = 0.5 - 0.5 * math.cos(math.pi * min(k, n) / n)
            tg = [start[i] + round(amp[i] * s) for i in range(6)]
            sent.append(tg)
            assert io.send(tg) == SEND_OK
            time.sleep(0.001)
            io.poll()
        for _ in range(50):         # keep cycling: a silent master is stopped by the drives (0x1400:05)
            assert io.send(tg) == SEND_OK
            sent.append(tg)
            time.sleep(0.002)
            io.poll()
        assert not io.emcy, [cia402.emcy_text(e[1], e[2]) for e in io.emcy]
        for i in range(6):
            # every frame on the bus, decoded by canopen from the drives' own mapping, is what was sent
            assert dec.targets[i] == [t[i] for t in sent], f"strut {i + 1}"
            # the drives followed: their feedback (decoded both ways) ends at the final target
            assert abs(dec.positions[i][-1] - sent[-1][i]) <= 2
            assert io.pos_inc[i] == dec.positions[i][-1]
            assert cia402.state_from_status(io.status[i]) == cia402.OPERATION_ENABLED
        assert io.heartbeat_lost() == 0
    finally:
        if dec is not None:
            dec.close()
        proc.terminate()
        proc.wait(5)
        for b in buses:
            b.shutdown()
    assert proc.returncode == 0


def test_injected_faults_across_processes(request):
    if not netns_or_rerun(request):
        return
    cfg = udp_cfg()
    proc = spawn(None, interface="udp_multicast", channel=CHANNEL,
                 faults=["2:emcy:0x2310@0.2", "4:heartbeat@0.2", "6:stuck@0.2"])
    buses = open_buses(cfg.bus)
    try:
        m = Master(cfg, buses)
        m.bring_up(timeout_s=3.0)
        sw, start = m.statuswords(), m.positions_inc()
        m.detach()
        io = CyclicIO(buses, cfg.bus, limits_inc=limits_inc(cfg), status=sw, positions_inc=start)
        ev = 0
        deadline = time.monotonic() + 3.0
        k = 0
        while time.monotonic() < deadline:
            assert io.send([s + 40 * k for s in start]) == SEND_OK       # 40 mm/s at 1 ms
            time.sleep(0.001)
            ev |= io.poll()
            k += 1
            codes = {(e[0], e[1]) for e in io.emcy}
            if (1, 0x2310) in codes and (5, 0x8611) in codes and io.heartbeat_lost():
                break
        assert ev & EV_EMCY
        codes = {(e[0], e[1]) for e in io.emcy}
        assert (1, 0x2310) in codes, [cia402.emcy_text(e[1]) for e in io.emcy]
        assert (5, 0x8611) in codes, [cia402.emcy_text(e[1]) for e in io.emcy]
        assert io.heartbeat_lost() == 1 << 3
        t_end = time.monotonic() + 2.0       # a following-error fault ramps down first (0x605E: Fault reaction active)
        while time.monotonic() < t_end:
            io.send([s + 40 * k for s in start])
            time.sleep(0.001)
            io.poll()
            states = io.states()
            if states[1] == cia402.FAULT and states[5] == cia402.FAULT:
                break
        assert states[1] == cia402.FAULT and states[5] == cia402.FAULT, states
        assert states[0] == states[2] == states[4] == cia402.OPERATION_ENABLED
    finally:
        proc.terminate()
        proc.wait(5)
        for b in buses:
            b.shutdown()
