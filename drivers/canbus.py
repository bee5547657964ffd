"""Open the drive bus(es) with python-can: ``socketcan``, ``virtual`` or ``udp_multicast``.

* ``socketcan``: plain ``can.Bus(interface="socketcan", channel=...)`` (``vcan0`` / ``can0``), nothing
  wrapped, so it runs unchanged on vcan or real hardware. Own frames are not echoed by SocketCAN
  unless asked (``receive_own_messages`` stays False).
* ``virtual``: python-can's in-process bus (unit tests); it does not echo either.
* ``udp_multicast``: python-can sends each frame as a msgpack datagram to a multicast group, and
  the kernel loops it back to every member *including the sender*; the received ``can.Message``
  carries no sender identity (python-can drops the source address, and all members share one
  port anyway). :class:`EchoFilteredUdpBus` stamps every outgoing frame's ``channel`` field (which
  the msgpack format carries through) with a token unique to this bus object and drops received
  frames bearing it. Frames of every other bus object, in this or another process, pass.

With ``[bus] buses`` > 1 the channels are either listed (``"can0,can1"``) or derived from one:
socketcan ``can0`` -> ``can0, can1`` (trailing number counted up), virtual ``name`` ->
``name.0, name.1``, udp_multicast: the group address counted up (a name instead of an address
is hashed into 239.192.0.0/14, organisation-local scope).
"""
from __future__ import annotations

import hashlib
import ipaddress
import os
import re
import socket
import time
from typing import Any

import can
from can.interfaces.udp_multicast import UdpMulticastBus
from can.interfaces.udp_multicast.utils import unpack_message

from .errors import BusError

UDP_PORT = 43113
IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)


class EchoFilteredUdpBus(UdpMulticastBus):
    """python-can ``udp_multicast`` bus that drops the frames it sent itself."""

    def __init__(self, channel: str, port: int = UDP_PORT, **kwargs: Any):
        super().__init__(channel=channel, port=port, **kwargs)
        # Linux delivers a datagram for *any* joined group to every socket bound to the port
        # (IP_MULTICAST_ALL defaults to 1): two buses on two groups would hear each other.
        try:
            self._multicast._socket.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)
        except (OSError, AttributeError):   # pragma: no cover - non-Linux
            pass
        self.echo_token = f"hexacnc:{os.getpid()}:{os.urandom(6).hex()}"
        self._token_bytes = self.echo_token.encode()
        self.echoes_dropped = 0

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.channel != self.echo_token:
            msg.channel = self.echo_token
        super().send(msg, timeout)

    def _recv_internal(self, timeout: float | None):
        # Drop own frames before decoding them: the token is a msgpack str inside the datagram, so
        # a byte search is enough and saves the unpack + can.Message of every echo (half of the
        # traffic a master receives). Keep reading within the same timeout: a drain with timeout 0
        # must not stop at an echo while other frames are queued behind it.
        deadline = None if timeout is None else time.monotonic() + timeout
        token = self._token_bytes
        while True:
            result = self._multicast.recv(timeout)
            if not result:
                return None, False
            data, _, timestamp = result
            if token in data:
                self.echoes_dropped += 1
                if deadline is not None:
                    timeout = max(0.0, deadline - time.monotonic())
                continue
            try:
                msg = unpack_message(data, replace={"timestamp": timestamp}, check=True)
            except Exception as exc:
                raise can.CanOperationError("could not unpack received message") from exc
            if self._can_protocol is not can.CanProtocol.CAN_FD and msg.is_fd:
                return None, False
            return msg, False


def _derive_udp_group(channel: str, i: int) -> str:
    try:
        addr = ipaddress.ip_address(channel)
    except ValueError:
        h = int.from_bytes(hashlib.sha1(channel.encode()).digest()[:4], "big")
        addr = ipaddress.IPv4Address((239 << 24) | (192 << 16) | (h & 0x3FFFF) & ~0xF)
    if not addr.is_multicast:
        raise BusError(f"[bus] channel {channel!r}: udp_multicast needs a multicast group address")
    return str(addr + i)


def bus_channels(bus_cfg, channel: str | None = None) -> list[str]:
    """One channel per bus (see module doc); ``channel`` overrides ``[bus] channel``."""
    ch = bus_cfg.channel if channel is None else channel
    n = bus_cfg.buses
    if "," in ch:
        out = [c.strip() for c in ch.split(",")]
        if not all(out):
            raise BusError(f"[bus] channel {ch!r} has an empty entry")
        if len(out) != n:
            raise BusError(f"[bus] channel {ch!r} lists {len(out)} channels but [bus] buses = {n}")
        if bus_cfg.interface == "udp_multicast":
            out = [_derive_udp_group(c, 0) for c in out]
        return out
    if bus_cfg.interface == "udp_multicast":
        return [_derive_udp_group(ch, i) for i in range(n)]
    if n == 1:
        return [ch]
    if bus_cfg.interface == "virtual":
        return [f"{ch}.{i}" for i in range(n)]
    m = re.fullmatch(r"(.*?)(\d+)", ch)
    if not m:
        raise BusError(f"[bus] channel {ch!r}: {n} buses need a list like 'can0,can1' "
                       "or a name ending in a number")
    return [f"{m.group(1)}{int(m.group(2)) + i}" for i in range(n)]


def open_bus(bus_cfg, *, channel: str | None = None) -> can.BusABC:
    """Open one bus of ``bus_cfg.interface`` on ``channel`` (default ``[bus] channel``, first bus)."""
    ch = channel if channel is not None and "," not in channel else bus_channels(bus_cfg, channel)[0]
    if bus_cfg.interface == "udp_multicast":
        ch = _derive_udp_group(ch, 0)
    iface = bus_cfg.interface
    try:
        if iface == "socketcan":
            return can.Bus(interface="socketcan", channel=ch, fd=bool(bus_cfg.fd))
        if iface == "virtual":
            proto = can.CanProtocol.CAN_FD if bus_cfg.fd else can.CanProtocol.CAN_20
            return can.Bus(interface="virtual", channel=ch, protocol=proto)
        if iface == "udp_multicast":
            return EchoFilteredUdpBus(channel=ch, port=UDP_PORT, fd=True)
    except (can.CanError, OSError, ValueError) as exc:
        raise BusError(f"[bus] cannot open {iface} channel {ch!r}: {exc}") from exc
    raise BusError(f"[bus] interface {iface!r} is not one of socketcan, virtual, udp_multicast")


def open_buses(bus_cfg, *, channel: str | None = None) -> list[can.BusABC]:
    """Open all ``[bus] buses`` buses, in bus order (strut split per :func:`drivers.layout.split_nodes`)."""
    out: list[can.BusABC] = []
    try:
        for ch in bus_channels(bus_cfg, channel):
            out.append(open_bus(bus_cfg, channel=ch))
    except BaseException:
        for b in out:
            b.shutdown()
        raise
    return out
