"""``python -m hexacnc.daemon.simhost``: the simulated drives process on pipe buses.

Runs :class:`drivers.simdrive.SimDrives` (six CiA 402 nodes from the EDS) on
:class:`~hexacnc.daemon.pipebus.PipeBus` ends inherited from the supervisor, or on side 1 of
:class:`~hexacnc.daemon.shmbus.ShmBus` frame rings.  Arguments come as one pickle on stdin:
``{"cfg": MachineConfig, "fds": [fd per bus] | "shm": [segment name per bus], "faults": [spec, ...]}``.
Prints ``READY`` once the nodes are up; runs until SIGTERM/SIGINT or until the supervisor's
end of stdin... (it stops when its parent dies: the pipe buses report EOF).
"""
from __future__ import annotations

import logging
import os
import pickle
import signal
import sys
import threading

#: the simulated drives look for frames this often (s); 0.4 of the default 0.5 ms cycle
POLL_INTERVAL_S = 0.0002


def main() -> int:
    args = pickle.load(sys.stdin.buffer)
    logging.basicConfig(level=args.get("log_level", "WARNING"), stream=sys.stderr,
                        format="simdrive %(levelname)s %(message)s")
    from drivers.simdrive import FaultSpec, SimDrives
    from .pipebus import PipeBus
    cfg = args["cfg"]
    # the simulated drives stand for hardware that keeps time: real-time priority just below the
    # hot loop when permitted (inherited by the canopen threads started below)
    prio = int(args.get("priority", max(1, cfg.cycle.realtime_priority - 10)))
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
    except (OSError, AttributeError) as exc:
        logging.getLogger("hexacnc.simhost").warning("simulated drives without SCHED_FIFO: %s", exc)
    # look for frames on a timer instead of being woken by each write: the wake-up would be paid by
    # the hot loop on its CPU every cycle (see PipeBus); the drives answer within this interval
    poll_s = float(args.get("poll_interval_s", POLL_INTERVAL_S))
    if args.get("shm"):        # shared-memory frame rings (hexacnc.daemon.shmbus), side 1
        from .shmbus import ShmBus
        buses = [ShmBus(name, side=1, poll_interval_s=poll_s) for name in args["shm"]]
    else:
        buses = [PipeBus(fd=fd, poll_interval_s=poll_s) for fd in args["fds"]]
    faults = [FaultSpec.parse(f) for f in args.get("faults", ())]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    signal.signal(signal.SIGINT, lambda *a: stop.set())
    ppid = os.getppid()
    sim = SimDrives(cfg, buses, faults=faults)
    if getattr(cfg, "simulation_truth", ""):     # touch-probe input from the true machine (hexacnc.sim.probesignal)
        from ..sim.probesignal import attach_probe_signal
        try:
            attach_probe_signal(sim, cfg.simulation_truth)
        except Exception as exc:   # the drives run without a probe input rather than not at all
            logging.getLogger("hexacnc.simhost").warning("no touch-probe input: %s", exc)
    try:
        sim.start()
        print("READY", flush=True)
        while not stop.wait(0.2):
            if os.getppid() != ppid:
                break
    finally:
        sim.stop()
        for b in buses:
            b.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
