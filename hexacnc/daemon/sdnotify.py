"""systemd notification (``sd_notify``) without libsystemd: one datagram to $NOTIFY_SOCKET."""
from __future__ import annotations

import os
import socket


class Notifier:
    """``notify("READY=1")``; a no-op when not started by systemd (no NOTIFY_SOCKET)."""

    def __init__(self, env: dict | None = None):
        env = os.environ if env is None else env
        addr = env.get("NOTIFY_SOCKET", "")
        self.addr = None
        self.sock = None
        if addr:
            if addr.startswith("@"):
                addr = "\0" + addr[1:]          # abstract namespace
            self.addr = addr
            self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        wd = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        self.watchdog_s = (int(wd) / 1e6 if wd.isdigit() and (not pid or pid == str(os.getpid()))
                           else 0.0)

    @property
    def enabled(self) -> bool:
        return self.sock is not None

    def notify(self, state: str) -> bool:
        if self.sock is None:
            return False
        try:
            self.sock.sendto(state.encode(), self.addr)
            return True
        except OSError:
            return False

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
