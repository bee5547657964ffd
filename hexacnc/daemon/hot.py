"""``python -m hexacnc.daemon.hot FD``: the hot loop process.

Started by the supervisor with :mod:`subprocess` (a fresh interpreter: nothing of the
supervisor - threads, sockets, the planner, the parent's ``__main__`` - is imported here).
Reads its arguments as one pickle from stdin, reports "ready"/"error" as one JSON line on
the pipe ``FD``, then runs :func:`hot_main`.
"""
from __future__ import annotations

import json
import logging
import os
import pickle
import sys

from . import shm as S
from .loop import HotLoop, install_signal_handlers

log = logging.getLogger("hexacnc.loop")


def main() -> int:
    import signal
    from .loop import set_parent_death_signal
    # before anything slow: Ctrl-C in the terminal reaches the whole process group, and the hot loop
    # must not die before the supervisor orders the stop; the kernel tells us when the supervisor dies
    install_signal_handlers(signal.SIGUSR1)
    set_parent_death_signal(signal.SIGUSR1)
    fd = int(sys.argv[1])
    args = pickle.load(sys.stdin.buffer)
    sys.stdin.close()
    out = os.fdopen(fd, "w")

    def report(kind: str, payload) -> None:
        out.write(json.dumps([kind, payload], default=str) + "\n")
        out.flush()
        out.close()

    hot_main(args["cfg"], args["shm"], args["io_mode"], args["period_s"], args["realtime"],
             args["log_level"], report, args.get("sim_args"), args.get("cpu"), signal.SIGUSR1)
    return 0


def hot_main(cfg, shm_name: str, io_mode: str, period_s: float, realtime: bool, log_level: str,
             report, sim_args: dict | None = None, cpu: int | None = None,
             pdeath_signal: int | None = None) -> None:
    """Body of the hot process: boot the bus, take privileges, run the cycle.

    ``report(kind, payload)`` sends one message to the supervisor ("ready" or "error").
    """
    logging.basicConfig(level=getattr(logging, str(log_level).upper(), logging.INFO), stream=sys.stderr,
                        format="%(asctime)s hexacnc[hot %(process)d] %(levelname)s %(message)s")
    logging.getLogger("canopen").setLevel(logging.WARNING)
    logging.getLogger("can").setLevel(logging.WARNING)
    sh = S.Shared(shm_name)
    install_signal_handlers(pdeath_signal)
    from . import busio, rt
    # memory lock and CPU first (slow, and the drives must not wait for the cycle after the boot),
    # SCHED_FIFO last: threads the bus boot starts must not inherit it
    locked, m1 = rt.mlockall()
    (log.info if locked else log.warning)("hot loop: %s", m1)
    cpu, m2 = rt.pin_cpu(cfg.cycle.cpu if cpu is None else cpu)
    (log.info if cpu >= 0 else log.warning)("hot loop: %s", m2)
    # the per-cycle transform (generated code) before the bus: between the master's boot (its
    # heartbeat stops) and the first cyclic frame only the codec is set up
    from ..transform import CycleTransform
    ct = CycleTransform(cfg, period_s=period_s)
    io = None
    try:
        io = busio.open_io(cfg, io_mode, period_s, sim_args or {})
    except Exception as exc:
        log.error("hot loop: bus start failed: %s", exc)
        sh.h[S.H_READY] = -1
        report("error", f"{type(exc).__name__}: {exc}")
        sh.close()
        return
    if realtime:
        fifo, m3 = rt.sched_fifo(cfg.cycle.realtime_priority)
    else:
        fifo, m3 = False, "SCHED_FIFO not requested"
    (log.info if fifo else log.warning)("hot loop: %s", m3)
    priv = {"sched_fifo": fifo, "mlockall": locked, "affinity_cpu": cpu, "messages": [m1, m2, m3]}
    sh.h[S.H_PRIV_FIFO] = 1 if priv["sched_fifo"] else 0
    sh.h[S.H_PRIV_MLOCK] = 1 if priv["mlockall"] else 0
    sh.h[S.H_PRIV_AFFINITY] = priv["affinity_cpu"] + 1
    report("ready", {"privileges": priv, "bus_load": getattr(io, "bus_load", 0.0),
                     "io_info": getattr(io, "info", {})})
    loop = HotLoop(cfg, sh, io, ct=ct, priv=priv, period_s=period_s)
    try:
        loop.run()
    finally:
        try:
            io.close()
        finally:
            n = sh.h[S.H_CYCLES]
            sh.h[S.H_STATE] = S.ST_EXITED
            sh.close()
    log.info("hot loop: exited after %d cycles", n)


if __name__ == "__main__":
    sys.exit(main())
