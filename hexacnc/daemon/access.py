"""Who may do what on the daemon's socket: peer credentials, roles, refusals.

A Unix client's role comes from its peer credentials (``SO_PEERCRED``, and its supplementary
groups from ``SO_PEERGROUPS``), decided once at connect time:

* the daemon's own user and root: ``controller``;
* a member of ``[daemon] controller_group``: ``controller`` (may command motion);
* a member of ``[daemon] sensor_group``: ``sensor`` (reads, and sends ``temperatures``);
* a member of ``[daemon] observer_group``: ``observer`` (reads only);
* anyone else: refused at connect, with the reason sent and logged.

A TCP client gets ``[daemon] tcp_role`` once it has authenticated with the token.

Ops: :data:`READ_OPS` are open to every role; ``temperatures`` needs controller or sensor;
every other op - ``program``, ``pause``, ``reset``, ``enable`` and any op added later - changes
a command and needs ``controller`` (default deny).  Holding the motion control (the ``role`` key
of ``hello``/``status``, first come first served) is a separate matter among controllers.
"""
from __future__ import annotations

import grp
import logging
import os
import socket
import struct
from dataclasses import dataclass

from ..errors import HexacncError
from .sockpath import peer_cred, user_name

log = logging.getLogger("hexacnc.daemon.access")

CONTROLLER = "controller"
SENSOR = "sensor"
OBSERVER = "observer"
ROLES = (CONTROLLER, SENSOR, OBSERVER)

#: ops every role may send (they change no command)
READ_OPS = frozenset({"hello", "status", "wait", "subscribe", "unsubscribe", "release"})
#: ops a sensor may send besides the read ops
SENSOR_OPS = frozenset({"temperatures"})

_SO_PEERGROUPS = getattr(socket, "SO_PEERGROUPS", 59)   # Linux >= 4.13
_MAX_GROUPS = 1024


@dataclass(frozen=True)
class Peer:
    """The other end of a connection: Unix credentials, or a TCP address."""
    kind: str                         #: "unix" | "tcp"
    uid: int = -1
    gid: int = -1
    pid: int = -1
    groups: tuple[int, ...] = ()
    address: str = ""                 #: "host:port" for TCP

    def describe(self) -> str:
        if self.kind == "tcp":
            return f"tcp {self.address}"
        return f"uid {self.uid} ({user_name(self.uid)}) pid {self.pid}"


def _peer_groups(sock: socket.socket, pid: int, gid: int) -> tuple[int, ...]:
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, _SO_PEERGROUPS, 4 * _MAX_GROUPS)
        return tuple(sorted(set(struct.unpack(f"{len(raw) // 4}I", raw[: len(raw) // 4 * 4])) | {gid}))
    except OSError:
        pass
    try:                              # older kernels: the process' groups as /proc shows them
        with open(f"/proc/{pid}/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Groups:"):
                    return tuple(sorted({int(g) for g in line.split()[1:]} | {gid}))
    except (OSError, ValueError):
        pass
    return (gid,)


def unix_peer(sock: socket.socket) -> Peer:
    """Peer credentials of a connected Unix socket."""
    pid, uid, gid = peer_cred(sock)
    return Peer("unix", uid=uid, gid=gid, pid=pid, groups=_peer_groups(sock, pid, gid))


def _gid(key: str, name: str) -> int | None:
    if not name:
        return None
    try:
        return grp.getgrnam(name).gr_gid
    except KeyError:
        raise HexacncError(f"[daemon] {key} = {name!r}: no such group on this host") from None


class AccessPolicy:
    """Roles from ``[daemon] controller_group`` / ``sensor_group`` / ``observer_group``."""

    def __init__(self, controller_group: str = "", observer_group: str = "", sensor_group: str = "",
                 tcp_role: str = CONTROLLER, owner_uid: int | None = None):
        self.names = {"controller_group": controller_group, "sensor_group": sensor_group,
                      "observer_group": observer_group}
        self.gids = {k: _gid(k, v) for k, v in self.names.items()}
        self.tcp_role = tcp_role if tcp_role in ROLES else CONTROLLER
        self.owner_uid = os.geteuid() if owner_uid is None else int(owner_uid)

    @classmethod
    def from_config(cls, dcfg) -> "AccessPolicy":
        return cls(getattr(dcfg, "controller_group", ""), getattr(dcfg, "observer_group", ""),
                   getattr(dcfg, "sensor_group", ""), getattr(dcfg, "tcp_role", CONTROLLER))

    @property
    def groups_configured(self) -> bool:
        return any(g is not None for g in self.gids.values())

    def role_for(self, peer: Peer) -> tuple[str | None, str]:
        """(role or None, why) for a Unix peer."""
        if peer.uid == self.owner_uid or peer.uid == 0:
            return CONTROLLER, "the daemon's own user" if peer.uid == self.owner_uid else "root"
        for key, role in (("controller_group", CONTROLLER), ("sensor_group", SENSOR),
                          ("observer_group", OBSERVER)):
            g = self.gids[key]
            if g is not None and g in peer.groups:
                return role, f"member of [daemon] {key} {self.names[key]!r}"
        named = ", ".join(f"{k} {v!r}" for k, v in self.names.items() if v) or "no group configured"
        return None, (f"{peer.describe()} is not the daemon's user ({user_name(self.owner_uid)}) and in none "
                      f"of the [daemon] groups ({named})")


def allowed(role: str | None, op: str) -> bool:
    """May a connection with ``role`` send ``op``?"""
    if role is None:
        return False
    if op in READ_OPS or role == CONTROLLER:
        return True
    return role == SENSOR and op in SENSOR_OPS


def refusal(role: str | None, op: str) -> str:
    need = "controller or sensor" if op in SENSOR_OPS else CONTROLLER
    return f"op {op!r} needs the {need} role; this connection is {'an' if role == OBSERVER else 'a'} {role}"


def log_refusal(who: str, op: str, why: str) -> None:
    """One line per refusal: who (peer uid/pid or address), which op, why."""
    log.warning("refused %s: op %s: %s", who, op, why)


__all__ = ["Peer", "AccessPolicy", "unix_peer", "allowed", "refusal", "log_refusal", "READ_OPS",
           "SENSOR_OPS", "CONTROLLER", "SENSOR", "OBSERVER", "ROLES"]
