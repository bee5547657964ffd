"""Where the daemon's Unix socket lives, and who may have put it there.

Whoever can write the socket's directory can replace the socket: an impostor then captures
programs and fakes status.  So:

* the default socket lives in a directory only the daemon's user can write:
  ``$RUNTIME_DIRECTORY/hexacnc.sock`` under systemd (``RuntimeDirectory=hexacnc`` gives
  ``/run/hexacnc``), else ``$XDG_RUNTIME_DIR/hexacnc/hexacnc.sock``, else
  ``/tmp/hexacnc-UID/hexacnc.sock`` in a 0700 directory the user owns (created if absent; refused
  when someone else made it first);
* the daemon refuses a socket path whose directory others can write (:func:`check_server_dir`);
* the client refuses a socket (and a server process) not owned by a user it trusts - its own,
  root or ``[daemon] service_user`` (:func:`check_client_socket`, :func:`check_server_peer`).
"""
from __future__ import annotations

import logging
import os
import pwd
import socket
import stat
import struct
import tempfile
from typing import Iterable, Mapping

from .protocol import ConnectionLost

log = logging.getLogger("hexacnc.daemon.sockpath")

SOCKET_NAME = "hexacnc.sock"
#: the service's runtime directory (``RuntimeDirectory=hexacnc``)
SERVICE_DIR = "/run/hexacnc"


class SocketTrustError(ConnectionLost):
    """A socket path or its directory that could have been planted or swapped by another user
    (a :class:`~hexacnc.errors.HexacncError`; clients exit with the connection error code)."""


def user_name(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return f"uid {uid}"


def fallback_dir(uid: int | None = None) -> str:
    """``/tmp/hexacnc-UID`` (or under $TMPDIR): the last resort, a 0700 directory the user owns."""
    return os.path.join(tempfile.gettempdir(), f"hexacnc-{os.geteuid() if uid is None else uid}")


def default_socket_path(env: Mapping[str, str] | None = None) -> str:
    """The daemon's default socket path (see the module doc)."""
    env = os.environ if env is None else env
    rd = env.get("RUNTIME_DIRECTORY", "").split(":")[0]
    if rd and os.path.isabs(rd):
        return os.path.join(rd, SOCKET_NAME)
    xdg = env.get("XDG_RUNTIME_DIR", "")
    if xdg and os.path.isabs(xdg) and os.path.isdir(xdg):
        return os.path.join(xdg, "hexacnc", SOCKET_NAME)
    return os.path.join(fallback_dir(), SOCKET_NAME)


def client_socket_candidates(env: Mapping[str, str] | None = None) -> list[str]:
    """Default places a client looks, in order: the user's own daemon, the service, the fallback."""
    env = os.environ if env is None else env
    out = []
    xdg = env.get("XDG_RUNTIME_DIR", "")
    if xdg and os.path.isabs(xdg):
        out.append(os.path.join(xdg, "hexacnc", SOCKET_NAME))
    out.append(os.path.join(SERVICE_DIR, SOCKET_NAME))
    out.append(os.path.join(fallback_dir(), SOCKET_NAME))
    return out


def _mode(st: os.stat_result) -> str:
    return f"{stat.S_IMODE(st.st_mode):04o}"


def _owner_ok(st: os.stat_result, trusted: Iterable[int]) -> bool:
    return st.st_uid in trusted


def _check_ancestors(d: str, trusted: frozenset[int], err: type) -> None:
    """Every directory above ``d``: owned by a trusted user and not writable by others, unless
    sticky (``/tmp``: nobody else may rename what we own there)."""
    parts = d.split(os.sep)
    for i in range(1, len(parts)):
        a = os.sep.join(parts[:i]) or os.sep
        st = os.stat(a)
        if st.st_mode & 0o022 and not st.st_mode & stat.S_ISVTX:
            raise err(f"socket directory {d}: its parent {a} is writable by others (mode {_mode(st)}) "
                      f"and not sticky: another user could swap the directory")
        if not _owner_ok(st, trusted):
            raise err(f"socket directory {d}: its parent {a} belongs to {user_name(st.st_uid)}")


def check_dir(d: str, trusted: Iterable[int], err: type = SocketTrustError) -> None:
    """Raise ``err`` unless directory ``d`` (symlinks resolved) is owned by a trusted user and
    nobody else can write it (nor any directory above it, sticky ones excepted)."""
    trusted = frozenset(trusted)
    real = os.path.realpath(d)
    try:
        st = os.stat(real)
    except FileNotFoundError:
        raise err(f"socket directory {d} does not exist") from None
    if not stat.S_ISDIR(st.st_mode):
        raise err(f"socket directory {d} is not a directory")
    if not _owner_ok(st, trusted):
        raise err(f"socket directory {d} belongs to {user_name(st.st_uid)} (uid {st.st_uid}), not to "
                  f"{' or '.join(user_name(u) for u in sorted(trusted))}: someone else created it; "
                  f"refusing to use it (remove it, or choose another --socket / [daemon] socket_path)")
    if st.st_mode & 0o022:
        raise err(f"socket directory {d} is writable by {'others' if st.st_mode & 0o002 else 'its group'} "
                  f"(mode {_mode(st)}): another user could replace the socket; use a directory only "
                  f"the daemon's user can write, e.g. $XDG_RUNTIME_DIR/hexacnc or /run/hexacnc")
    _check_ancestors(real, trusted, err)


def server_trusted() -> frozenset[int]:
    return frozenset({os.geteuid(), 0})


def prepare_server_dir(path: str, default_dirs: Iterable[str] = ()) -> str:
    """Check (and for a default place, create 0700) the directory of the daemon's socket ``path``.

    Returns the directory; raises :class:`SocketTrustError` naming it and why."""
    d = os.path.dirname(os.path.abspath(path))
    defaults = {os.path.abspath(x) for x in default_dirs} | {
        os.path.dirname(default_socket_path()), fallback_dir()}
    if d in defaults and not os.path.lexists(d):
        try:
            os.mkdir(d, 0o700)
        except FileNotFoundError:
            raise SocketTrustError(f"socket directory {d}: its parent does not exist") from None
        except FileExistsError:
            pass                      # raced: checked below like any existing directory
    try:
        check_dir(d, server_trusted())
    except SocketTrustError as exc:
        log.error("refused socket path %s: %s", path, exc)
        raise
    return d


def trusted_uids(service_user: str = "") -> frozenset[int]:
    """Users whose socket a client talks to: itself, root and ``service_user`` (when it exists)."""
    out = {os.geteuid(), 0}
    if service_user:
        try:
            out.add(pwd.getpwnam(service_user).pw_uid)
        except KeyError:
            pass
    return frozenset(out)


def check_client_socket(path: str, trusted: Iterable[int]) -> None:
    """Before connecting: ``path`` is a socket owned by a trusted user in a directory nobody else
    can write.  Raises :class:`SocketTrustError` (nothing is sent to an impostor)."""
    trusted = frozenset(trusted)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return                         # connect() reports "no daemon" with the path
    if not stat.S_ISSOCK(st.st_mode):
        raise SocketTrustError(f"{path} is not a socket")
    if st.st_uid not in trusted:
        raise SocketTrustError(f"socket {path} belongs to {user_name(st.st_uid)} (uid {st.st_uid}), not to "
                               f"{' or '.join(user_name(u) for u in sorted(trusted))}: not talking to it "
                               f"(an impostor may have created it)")
    check_dir(os.path.dirname(os.path.abspath(path)), trusted)


def peer_cred(sock: socket.socket) -> tuple[int, int, int]:
    """(pid, uid, gid) of the other end of a connected Unix socket (SO_PEERCRED)."""
    raw = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    return struct.unpack("3i", raw)


def check_server_peer(sock: socket.socket, trusted: Iterable[int]) -> None:
    """After connecting: the process serving the socket runs as a trusted user."""
    pid, uid, _gid = peer_cred(sock)
    if uid not in frozenset(trusted):
        raise SocketTrustError(f"the process serving the socket (pid {pid}) runs as {user_name(uid)} "
                               f"(uid {uid}), a user this client does not trust")


__all__ = ["SocketTrustError", "default_socket_path", "client_socket_candidates", "check_dir",
           "prepare_server_dir", "trusted_uids", "check_client_socket", "check_server_peer", "peer_cred",
           "fallback_dir", "SERVICE_DIR", "SOCKET_NAME"]


def server_socket_path(dcfg, override: str | None = None) -> str:
    """The daemon's socket: ``override`` (``--socket``), else ``[daemon] socket_path``, else the
    default place (:func:`default_socket_path`)."""
    return str(override or getattr(dcfg, "socket_path", "") or default_socket_path())


def client_socket_path(cfg) -> str:
    """The socket a client uses: ``[daemon] socket_path`` when the config file sets it, else the
    first existing default place (:func:`client_socket_candidates`), else the first of them."""
    raw = getattr(cfg, "raw", None) or {}
    if isinstance(raw.get("daemon"), dict) and raw["daemon"].get("socket_path"):
        return cfg.daemon.socket_path
    cands = client_socket_candidates()
    for c in cands:
        if os.path.lexists(c):
            return c
    return cands[0]


def connect_checked(path: str, service_user: str = "", timeout_s: float = 5.0) -> socket.socket:
    """A connected Unix socket to ``path`` after the ownership checks of :func:`check_client_socket`
    and :func:`check_server_peer`.  Raises :class:`SocketTrustError`, or ``ConnectionLost`` when
    nobody serves it."""
    trusted = trusted_uids(service_user)
    check_client_socket(path, trusted)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(path)
        check_server_peer(s, trusted)
    except SocketTrustError:
        s.close()
        raise
    except OSError as exc:
        s.close()
        raise ConnectionLost(f"cannot connect to the daemon at {path}: {exc.strerror or exc}") from exc
    s.settimeout(None)
    return s
