"""``hexacnc reload MACHINE.toml``: the running daemon loads a machine description when idle."""
from __future__ import annotations

from .calibcycle import HELP, configure_reload as configure, main_reload as main

__all__ = ["HELP", "configure", "main"]
