"""Bus I/O for the hot loop: the mode, the simulated drives process and the codec.

Modes (``Daemon(io_mode=...)``; ``auto`` picks from the config):

* ``bus`` - the real path: ``drivers.master`` boots the drives (NMT, SDO PDO mapping, mode 8)
  inside the hot process *before* the loop starts, then ``drivers.cyclic`` does the hot-path
  frames.  With ``[bus] simulate`` the supervisor starts ``drivers.simdrive`` as a separate
  process on the same bus (``udp_multicast``: only inside a network namespace or on loopback).
* ``inproc`` - the hot loop drives an in-process model (:class:`~hexacnc.daemon.simio.SimIO`)
  instead of a bus: no second process, no sockets.  Used by ``auto`` for ``[bus] interface =
  "virtual"`` with ``simulate``, because python-can's virtual bus does not cross processes.
"""
from __future__ import annotations

import logging

log = logging.getLogger("hexacnc.busio")


def resolve_mode(cfg, mode: str) -> str:
    if mode not in ("auto", "bus", "inproc"):
        raise ValueError(f"io mode {mode!r} is not one of auto, bus, inproc")
    if mode != "auto":
        return mode
    if cfg.bus.simulate and cfg.bus.interface == "virtual":
        return "inproc"
    return "bus"


def start_simulation(cfg, mode: str, period_s: float):
    """Start the simulated drives process when the mode needs one; returns a handle or None."""
    if mode != "bus" or not cfg.bus.simulate:
        return None
    from drivers import simdrive  # noqa: F401  (provided by the drivers layer)
    return simdrive.start_process(cfg)


def child_args(sim) -> dict:
    return {}


def stop_simulation(sim) -> None:
    if sim is None:
        return
    from drivers import simdrive
    simdrive.stop_process(sim)


def open_io(cfg, mode: str, period_s: float, sim_args: dict):
    """The codec object for :class:`~hexacnc.daemon.loop.HotLoop` (boots the drives in ``bus`` mode)."""
    if mode == "inproc":
        from ..kinematics import Hexapod
        from .simio import SimIO
        hx = Hexapod(cfg)
        start = hx.lengths(cfg.home_pose) - cfg.strut_offset_mm
        io = SimIO(cfg, period_s, tau_s=0.0005, start_pos=start)
        io.info = {"mode": "inproc", "drives": "in-process model"}
        return io
    raise NotImplementedError("bus mode: waiting for drivers.cyclic / drivers.master")
