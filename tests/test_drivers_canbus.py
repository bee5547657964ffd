"""Bus opening: channel derivation per interface, errors naming the channel, virtual bus round trip."""
import dataclasses

import can
import pytest

from hexacnc.config import BusConfig
from hexacnc.errors import BusError
from drivers.canbus import EchoFilteredUdpBus, bus_channels, open_bus, open_buses


def bus(**kw):
    return dataclasses.replace(BusConfig(), **kw)


def test_channel_derivation():
    assert bus_channels(bus(interface="socketcan", channel="vcan0", buses=2)) == ["vcan0", "vcan1"]
    assert bus_channels(bus(interface="socketcan", channel="can0,can7", buses=2)) == ["can0", "can7"]
    assert bus_channels(bus(interface="socketcan", channel="can0", buses=1)) == ["can0"]
    assert bus_channels(bus(interface="virtual", channel="x", buses=3)) == ["x.0", "x.1", "x.2"]
    assert bus_channels(bus(interface="udp_multicast", channel="239.74.163.2", buses=2)) == \
        ["239.74.163.2", "239.74.163.3"]
    named = bus_channels(bus(interface="udp_multicast", channel="hexacnc", buses=2))
    assert all(c.startswith("239.19") for c in named) and named[0] != named[1]
    assert bus_channels(bus(interface="udp_multicast", channel="hexacnc", buses=2)) == named   # deterministic
    with pytest.raises(BusError, match="lists 3 channels but \\[bus\\] buses = 2"):
        bus_channels(bus(interface="socketcan", channel="can0,can1,can2", buses=2))
    with pytest.raises(BusError, match="empty entry"):
        bus_channels(bus(interface="socketcan", channel="can0,", buses=2))
    with pytest.raises(BusError, match="ending in a number"):
        bus_channels(bus(interface="socketcan", channel="canbus", buses=2))
    with pytest.raises(BusError, match="multicast group"):
        bus_channels(bus(interface="udp_multicast", channel="10.0.0.1", buses=1))


def test_socketcan_error_names_the_channel():
    # this kernel has no CAN support; where vcan0 exists the bus simply opens
    try:
        b = open_bus(bus(interface="socketcan", channel="vcan0", buses=1))
    except BusError as exc:
        assert "socketcan channel 'vcan0'" in str(exc)
    else:
        assert isinstance(b, can.BusABC) and not isinstance(b, EchoFilteredUdpBus)
        b.shutdown()


def test_virtual_buses_are_separate_and_do_not_echo():
    cfg = bus(interface="virtual", channel="canbus-test", buses=2)
    a, b = open_buses(cfg), open_buses(cfg)
    try:
        a[1].send(can.Message(arbitration_id=0x55, data=b"\x07", is_extended_id=False))
        assert b[1].recv(0.5).arbitration_id == 0x55
        assert b[0].recv(0.05) is None and a[1].recv(0.05) is None
    finally:
        for x in a + b:
            x.shutdown()
