"""The simulated drives built from a machine config: the host glue between ``hexacnc`` and :mod:`drivers.simdrive`.

:mod:`drivers` depends on nothing in ``hexacnc``, so the values that come from the machine description are
computed here and passed down as plain values and factories:

* :func:`home_positions_inc` - the drives' readings at the home pose (inverse kinematics);
* :func:`strut_model_factory` - the strut model ``[dynamics] simulated_drives`` names;
* :func:`sim_drives` - :class:`drivers.simdrive.SimDrives` for a config, with both;
* :func:`spawn` / :func:`main` - the drives as a process on udp_multicast or socketcan::

    python -m hexacnc.sim.drives --config F [--interface udp_multicast] [--channel C] [--fault SPEC]...
                                 [--model package.module:factory]

  It prints ``READY`` on stdout once the nodes have booted and runs until SIGTERM/SIGINT.
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import selectors
import signal
import subprocess
import sys
import threading
import time
from typing import Sequence

from drivers.simdrive import FaultSpec, SimDrives
from drivers.strutmodel import ModelFactory, default_model_factory, load_model_factory

from ..errors import BusError, ConfigError, HexacncError
from ..kinematics import Hexapod

__all__ = ["home_positions_inc", "strut_model_factory", "sim_drives", "spawn", "main"]

MODULE = "hexacnc.sim.drives"


def home_positions_inc(cfg) -> list[int]:
    """The drives' readings (increments) with the machine at ``cfg.home_pose``: (L - strut_offset) * inc/mm."""
    lengths = Hexapod(cfg).lengths(cfg.home_pose)
    k = cfg.bus.increments_per_mm
    return [round((float(lengths[i]) - float(cfg.strut_offset_mm[i])) * k) for i in range(6)]


def strut_model_factory(cfg) -> ModelFactory:
    """The factory ``[dynamics] simulated_drives`` names: ``second_order``
    (:func:`drivers.strutmodel.default_model_factory`) or ``coupled`` (six struts and the carrier through
    the Jacobian, :func:`hexacnc.sim.strut.coupled_model_factory`)."""
    kind = getattr(getattr(cfg, "dynamics", None), "simulated_drives", "second_order")
    if kind == "coupled":
        from .strut import coupled_model_factory
        return coupled_model_factory()
    if kind != "second_order":
        raise ConfigError(f"[dynamics] simulated_drives: unknown strut model {kind!r}")
    return default_model_factory


def sim_drives(cfg, buses, *, faults: Sequence[FaultSpec] = (), model_factory: ModelFactory | None = None,
               start_positions_inc: Sequence[int] | None = None, eds_path=None, load_cfg=None) -> SimDrives:
    """:class:`drivers.simdrive.SimDrives` for ``cfg`` on ``buses`` (not started): the strut model of
    ``[dynamics] simulated_drives`` and the drives at the home pose unless given; their torque and
    current actual values (0x6077 / 0x6078) from the strut load of ``load_cfg`` (default ``cfg``; a
    true machine's plant config carries its payload), :mod:`hexacnc.sim.torque`."""
    from .torque import attach_strut_load
    sim = SimDrives(cfg, buses, faults=faults, eds_path=eds_path,
                    model_factory=model_factory or strut_model_factory(cfg),
                    start_positions_inc=home_positions_inc(cfg) if start_positions_inc is None
                    else start_positions_inc)
    attach_strut_load(sim, cfg if load_cfg is None else load_cfg)
    return sim


def spawn(config_path: str | os.PathLike | None, *, interface: str | None = None, channel: str | None = None,
          faults: Sequence[str] = (), ready_timeout_s: float = 20.0, env: dict | None = None,
          extra_args: Sequence[str] = (), model: str | None = None) -> subprocess.Popen:
    """Start ``python -m hexacnc.sim.drives`` and wait for its ``READY`` line; returns the process.

    Stop it with ``proc.terminate(); proc.wait()``. Raises :class:`BusError` if it exits or
    does not get ready in time (its stderr in the message).
    """
    cmd = [sys.executable, "-m", MODULE]
    if config_path is not None:
        cmd += ["--config", str(config_path)]
    if interface:
        cmd += ["--interface", interface]
    if channel:
        cmd += ["--channel", channel]
    for f in faults:
        cmd += ["--fault", f]
    if model:
        cmd += ["--model", model]
    cmd += list(extra_args)
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    e = dict(os.environ if env is None else env)
    e["PYTHONPATH"] = root + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=e)
    deadline = time.monotonic() + ready_timeout_s
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    while time.monotonic() < deadline:
        if sel.select(timeout=0.1):
            line = proc.stdout.readline()
            if line.strip() == "READY":
                sel.close()
                return proc
            if not line and proc.poll() is not None:
                break
    sel.close()
    proc.kill()
    _, err = proc.communicate(timeout=5)
    raise BusError(f"simulated drives did not start ({' '.join(cmd)}): {err.strip()[-2000:]}")


def main(argv: Sequence[str] | None = None) -> int:
    from drivers.canbus import open_buses

    from ..config import load_config

    ap = argparse.ArgumentParser(prog=f"python -m {MODULE}", description="simulated CiA 402 strut drives")
    ap.add_argument("--config", help="machine description (TOML); default: the embedded default")
    ap.add_argument("--interface", choices=("socketcan", "virtual", "udp_multicast"), help="override [bus] interface")
    ap.add_argument("--channel", help="override [bus] channel")
    ap.add_argument("--fault", action="append", default=[], metavar="SPEC",
                    help="NODE:emcy:CODE@S | NODE:heartbeat@S | NODE:stuck@S | NODE:refuse (S after enable)")
    ap.add_argument("--model", metavar="MODULE:FACTORY",
                    help="strut model factory (strut index, MachineConfig) -> StrutModel; "
                         "default: the one [dynamics] simulated_drives names")
    ap.add_argument("--log-level", default="WARNING")
    args = ap.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr,
                        format="simdrive %(levelname)s %(message)s")
    try:
        cfg = load_config(args.config)
        if args.interface:
            cfg = cfg.replace(bus=dataclasses.replace(cfg.bus, interface=args.interface))
        faults = [FaultSpec.parse(f) for f in args.fault]
        factory = load_model_factory(args.model) if args.model else None
        buses = open_buses(cfg.bus, channel=args.channel)
    except HexacncError as exc:
        print(f"simdrive: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    signal.signal(signal.SIGINT, lambda *a: stop.set())
    sims: list[SimDrives] = []
    try:
        sims.append(sim_drives(cfg, buses, faults=faults, model_factory=factory).start())
        print("READY", flush=True)
        while not stop.wait(0.2):       # wakes for the signal handlers
            pass
    finally:
        close_all(sims, buses)
    return 0


def close_all(sims: Sequence[SimDrives], buses) -> None:
    """Stop the drives (heartbeats, listeners), then shut the bus objects down."""
    for sim in sims:
        sim.stop()
    for b in buses:
        b.shutdown()


if __name__ == "__main__":
    sys.exit(main())
