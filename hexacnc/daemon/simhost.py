"""``python -m hexacnc.daemon.simhost``: the simulated drives process on pipe buses.

Runs :class:`drivers.simdrive.SimDrives` (six CiA 402 nodes from the EDS, built by :mod:`hexacnc.sim.drives`) on
:class:`~hexacnc.daemon.pipebus.PipeBus` ends inherited from the supervisor, or on side 1 of
:class:`~hexacnc.daemon.shmbus.ShmBus` frame rings.  Arguments come as one pickle on stdin:
``{"cfg": MachineConfig, "fds": [fd per bus] | "shm": [segment name per bus], "faults": [spec, ...]}``.
Prints ``READY`` once the nodes are up.

The drives stand for hardware: signals meant for the daemon (Ctrl-C to the process group,
SIGTERM/SIGHUP to the unit) are ignored, so the drives are still there while the hot loop stops
the motion and disables them.  The rest of stdin is a line protocol from the supervisor:

* ``STOP`` - end (the supervisor has stopped the hot loop): at once when every drive is disabled or
  stands still; a drive still enabled (the hot loop died before it disabled them) is left to its
  own communication-loss reaction first, as hardware would be (at most ``[bus] comm_loss_timeout_s``
  + ``REACTION_S``);
* end of file without ``STOP`` - the supervisor died: run on while the master (the hot loop, which
  stops the motion and disables the drives on its own) still sends SYNCs, end
  ``MASTER_SILENT_S`` after the last one;
* ``inject KIND NODE [VALUE]`` - fault injection for tests and ``hexacnc bench faults``
  (see :func:`inject`).
"""
from __future__ import annotations

import logging
import os
import pickle
import random
import signal
import sys
import threading
import time

from drivers import cia402

#: the simulated drives look for frames this often (s); 0.4 of the default 0.5 ms cycle
POLL_INTERVAL_S = 0.0002
#: after the supervisor died: end this long after the master's last SYNC
MASTER_SILENT_S = 1.0
#: after STOP: how long (beyond [bus] comm_loss_timeout_s) drives still enabled may take to stop on their own
REACTION_S = 1.5

log = logging.getLogger("hexacnc.simhost")

INJECTIONS = ("nmt", "emcy", "silent", "offset", "drop", "stuck", "dinput")


def inject(sim, kind: str, node: int, value: float = 0.0) -> None:
    """Fault injection into the running simulated drives (all under the drives' lock):

    * ``nmt NODE CMD``: the NMT command CMD (e.g. 0x81 reset node, 0x80 pre-operational) reaches NODE;
    * ``emcy NODE CODE``: NODE faults with EMCY CODE;
    * ``silent NODE``: NODE stops sending PDOs (position and statusword); its heartbeat goes on;
    * ``offset NODE MM``: NODE reports its position MM off (a following error the drive hides);
    * ``drop 0 FRACTION``: that fraction of every drive's position frames (TPDO1) is lost;
    * ``stuck NODE``: NODE's strut stops moving whatever the demand;
    * ``dinput NODE BITS``: NODE's digital inputs (0x60FD) become BITS (:mod:`drivers.simdio`).
    """
    if kind == "drop":
        frac = float(value)
        send = sim.send
        tpdo1 = {nd.tpdo1_cob_id for nd in sim.plan.nodes}
        rnd = random.Random(1)

        def lossy(bus_index, cob_id, data):
            if cob_id in tpdo1 and rnd.random() < frac:
                return
            send(bus_index, cob_id, data)
        sim.send = lossy
        return
    d = sim.by_node.get(node)
    if d is None:
        raise ValueError(f"inject {kind}: no node {node}")
    with sim.lock:
        if kind == "nmt":
            d.on_nmt(int(value))
        elif kind == "emcy":
            d.fault(int(value))
        elif kind == "silent":
            d.send_tpdo = lambda tp, now: None
        elif kind == "offset":
            off = int(round(float(value) * sim.increments_per_mm))
            cob = 0x180 + node
            for tp in d.tpdos:
                if tp.cob_id == cob:
                    tp.getters = [lambda: d.pos_inc + off]
        elif kind == "stuck":
            d.stuck = True
        elif kind == "dinput":
            d.dio.inputs = int(value) & 0xFFFFFFFF
        else:
            raise ValueError(f"inject: unknown kind {kind!r} (one of {', '.join(INJECTIONS)})")


def write_truth(sim, path: str) -> None:
    """Each drive's physical state as JSON at ``path`` (written whole: temporary file, then rename):
    ``position_mm`` (its position value), ``raw_mm`` (the encoder count without the home shift),
    ``home_shift_mm``, ``switch_mm`` (its simulated limit switches, raw scale), ``referenced``."""
    import json
    out = {}
    with sim.lock:
        for node, d in sim.by_node.items():
            hm = getattr(d, "homing", None)
            shift = hm.shift_inc if hm is not None else 0
            out[str(node)] = {"position_mm": d.pos_inc / d.k, "raw_mm": (d.pos_inc - shift) / d.k,
                              "home_shift_mm": shift / d.k,
                              "switch_mm": list(hm.home_switch_mm) if hm is not None else None,
                              "referenced": bool(hm.referenced) if hm is not None else False}
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(out, f)
    os.replace(tmp, path)


def _number(text: str) -> float:
    try:
        return int(text, 0)
    except ValueError:
        return float(text)


def _write_iolog(sim, path: str) -> None:
    """``iolog PATH``: every drive's digital I/O (:mod:`drivers.simdio`) as JSON ``{node: {...}}``,
    written to PATH.tmp then renamed (a reader never sees half a file)."""
    import json
    with sim.lock:
        doc = {str(node): {**d.dio.snapshot(), "strut": int(d.strut)} for node, d in sim.by_node.items()}
    try:
        with open(path + ".tmp", "w") as f:
            json.dump(doc, f)
        os.replace(path + ".tmp", path)
    except OSError as exc:
        log.error("iolog %s: %s", path, exc)


def _at_rest(d) -> bool:
    """The drive holds no enabled strut: disabled (or in Fault), or stopped by its own reaction."""
    if d.react.ramp is not None:
        return False
    return d.state != cia402.OPERATION_ENABLED and abs(d.model.velocity_mm_s) < 1e-3


def _let_drives_react(sim, bound_s: float) -> bool:
    """After STOP: wait (at most ``bound_s``) until every drive is at rest; True if they all are.
    With the hot loop's own stop they already are; after it died they stop on their own."""
    t_end = time.monotonic() + bound_s
    while True:
        with sim.lock:
            moving = [d.node_id for d in sim.drives if not _at_rest(d)]
        if not moving:
            return True
        if time.monotonic() > t_end:
            log.warning("nodes %s still enabled %.1f s after STOP: ended", moving, bound_s)
            return False
        time.sleep(0.01)


def _serve_stdin(sim) -> bool:
    """Read the supervisor's lines until STOP (True) or end of file (False: the supervisor died)."""
    for raw in sys.stdin.buffer:
        parts = raw.decode(errors="replace").split()
        if not parts:
            continue
        if parts[0] == "STOP":
            return True
        if parts[0] == "truth" and len(parts) == 2:      # benchmarks: the drives' physical state
            try:
                write_truth(sim, parts[1])
            except OSError as exc:
                log.error("truth %r: %s", parts[1], exc)
            continue
        if parts[0] == "iolog" and len(parts) == 2:
            _write_iolog(sim, parts[1])
            continue
        if parts[0] == "inject" and len(parts) >= 3:
            try:
                inject(sim, parts[1], int(parts[2], 0), _number(parts[3]) if len(parts) > 3 else 0.0)
                log.warning("injected %s", " ".join(parts[1:]))
            except (ValueError, KeyError) as exc:
                log.error("bad injection %r: %s", raw, exc)
    return False


def _truth(cfg):
    """The true machine of ``[simulation] truth`` (``hexacnc run --truth``), or None."""
    if not getattr(cfg, "simulation_truth", ""):
        return None
    from ..sim.truth import load_truth
    return load_truth(cfg.simulation_truth)       # checked by the supervisor before it started us


def _plant_factory(truth):
    """The strut model of the drives: the true machine's (its ``[dynamics] simulated_drives``,
    per-strut stiffness, carrier mass and centre of gravity with the payload, strut offsets and
    limits), not the controller's description; None: the controller's (no truth)."""
    if truth is None:
        return None
    from ..sim.drives import strut_model_factory
    plant_cfg = truth.plant_config()
    base = strut_model_factory(plant_cfg)
    return lambda strut, _controller_cfg: base(strut, plant_cfg)


def main() -> int:
    for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, signal.SIG_IGN)
    args = pickle.load(sys.stdin.buffer)
    logging.basicConfig(level=args.get("log_level", "WARNING"), stream=sys.stderr,
                        format="simdrive %(levelname)s %(message)s")
    from drivers.simdrive import FaultSpec

    from ..sim.drives import sim_drives
    from .pipebus import PipeBus
    cfg = args["cfg"]
    # the simulated drives stand for hardware that keeps time: real-time priority when permitted
    # (inherited by the canopen threads started below), just below the hot loop (rt.sim_drives_priority)
    from .rt import sim_drives_priority
    prio = int(args.get("priority", sim_drives_priority(cfg.cycle.realtime_priority)))
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
    except (OSError, AttributeError) as exc:
        log.warning("simulated drives without SCHED_FIFO: %s", exc)
    # look for frames on a timer instead of being woken by each write: the wake-up would be paid by
    # the hot loop on its CPU every cycle (see PipeBus); the drives answer within this interval
    poll_s = float(args.get("poll_interval_s", POLL_INTERVAL_S))
    if args.get("shm"):        # shared-memory frame rings (hexacnc.daemon.shmbus), side 1
        from .shmbus import ShmBus
        buses = [ShmBus(name, side=1, poll_interval_s=poll_s) for name in args["shm"]]
    else:
        buses = [PipeBus(fd=fd, poll_interval_s=poll_s) for fd in args["fds"]]
    capture = os.environ.get("HEXACNC_CAPTURE", "")      # hexacnc run --capture FILE.pcap (drivers.pcap)
    if capture:     # the drives' side of the buses: FILE-drives.pcap, FILE-drives-bus1.pcap (outlives the master)
        from drivers.pcap import capture_buses, drives_capture_path
        buses = capture_buses(buses, drives_capture_path(capture), background=True)
    faults = [FaultSpec.parse(f) for f in args.get("faults", ())]
    truth = _truth(cfg)
    sim = sim_drives(cfg, buses, faults=faults, model_factory=_plant_factory(truth),
                     load_cfg=None if truth is None else truth.plant_config())
    if truth is not None:        # touch-probe input from the true machine (hexacnc.sim.probesignal)
        from ..sim.probesignal import attach_probe_signal
        attach_probe_signal(sim, truth)
    try:
        sim.start()
        print("READY", flush=True)
        done = threading.Event()
        ordered = [False]

        def serve():
            ordered[0] = _serve_stdin(sim)
            done.set()
        threading.Thread(target=serve, name="simhost-stdin", daemon=True).start()
        done.wait()
        if ordered[0]:
            _let_drives_react(sim, float(cfg.bus.comm_loss_timeout_s) + REACTION_S)
        else:
            t_eof = time.monotonic()
            log.warning("supervisor gone: the drives run on until the master is silent")
            while True:
                with sim.lock:
                    last = max([d.last_sync_s for d in sim.drives] + [t_eof])
                if time.monotonic() - last > MASTER_SILENT_S:
                    break
                time.sleep(0.05)
    finally:
        sim.stop()
        for b in buses:
            b.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
