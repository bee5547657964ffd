"""Bus I/O for the hot loop: the mode, the simulated drives process and the codec.

Modes (``Daemon(io_mode=...)``; ``auto`` picks from the config):

* ``bus`` - the real path: ``drivers.master`` boots the drives (NMT, SDO PDO mapping, mode 8)
  inside the hot process *before* the loop starts, then ``drivers.cyclic`` does the hot-path
  frames; the loop walks the drives to Operation Enabled in those frames.  With ``[bus] simulate`` the supervisor starts ``hexacnc.sim.drives`` as a separate
  process on the same bus (``udp_multicast``: only inside a network namespace or on loopback).
* ``shm`` - the default for ``[bus] simulate`` with ``interface = "virtual"`` (python-can's
  virtual bus does not cross processes): the simulated drives run in their own process
  (:mod:`hexacnc.daemon.simhost`) and the frames travel through a shared-memory frame ring per bus
  (:mod:`hexacnc.daemon.shmbus`): no system call per cycle in the hot loop.
* ``pipe`` - the same, over one Unix stream socket pair per bus (:mod:`hexacnc.daemon.pipebus`):
  one ``send(2)`` and one ``recv(2)`` per bus per cycle.
* ``inproc`` - the hot loop drives an in-process model (:class:`~hexacnc.daemon.simio.SimIO`)
  instead of a bus: no second process, no CAN frames (the lower bound of the cycle's cost).
"""
from __future__ import annotations

import logging
import os

from ..errors import BusError
from .rt import sim_drives_priority

log = logging.getLogger("hexacnc.busio")


MODES = ("auto", "bus", "shm", "pipe", "inproc")


def resolve_mode(cfg, mode: str) -> str:
    if mode not in MODES:
        raise ValueError(f"io mode {mode!r} is not one of {', '.join(MODES)}")
    if mode != "auto":
        return mode
    if cfg.bus.simulate and cfg.bus.interface == "virtual":
        return "shm"
    return "bus"


class PipeSim:
    """The simulated drives process (:mod:`hexacnc.daemon.simhost`) and the hot loop's ends of its
    buses: Unix socket pairs (``transport="pipe"``) or shared-memory frame rings (``"shm"``)."""

    def __init__(self, cfg, faults=(), transport: str = "pipe"):
        import pickle
        import subprocess
        import sys
        import time
        self.transport = transport
        self.hot_fds: list[int] = []
        self.segments = []
        sim_fds: list[int] = []
        payload = {"cfg": cfg, "faults": list(faults)}
        if transport == "shm":
            from .shmbus import create_segments
            self.segments = create_segments(cfg.bus.buses)
            payload["shm"] = [seg.name for seg in self.segments]
        else:
            from .pipebus import socket_pairs
            pairs = socket_pairs(cfg.bus.buses)
            self.hot_fds = [a.detach() for a, _ in pairs]
            sim_fds = [b.detach() for _, b in pairs]
            payload["fds"] = sim_fds
        try:
            self.proc = subprocess.Popen([sys.executable, "-m", "hexacnc.daemon.simhost"], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, pass_fds=sim_fds,
                                         text=False)
        except BaseException:
            self.close_fds()
            self.release()
            raise
        finally:
            for fd in sim_fds:
                os.close(fd)
        self.proc.stdin.write(pickle.dumps(payload))
        self.proc.stdin.flush()     # stdin stays open: STOP / inject lines (hexacnc.daemon.simhost)
        import selectors
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        t_end = time.monotonic() + 20.0
        ok = False
        while time.monotonic() < t_end:
            if sel.select(0.1):
                line = self.proc.stdout.readline()
                if line.strip() == b"READY":
                    ok = True
                    break
                if not line:
                    break
            elif self.proc.poll() is not None:
                break
        sel.close()
        if not ok:
            self.kill()             # never started: nothing to stop gently
            err = self.proc.stderr.read().decode(errors="replace")[-2000:]
            self.close_fds()
            self.release()
            raise BusError(f"simulated drives did not start: {err.strip()}")

    def close_fds(self) -> None:
        for fd in self.hot_fds:
            try:
                os.close(fd)
            except OSError:
                pass
        self.hot_fds = []

    def release(self) -> None:
        """Unlink the shared-memory rings (after both processes are done with them)."""
        from .shmbus import release_segments
        release_segments(self.segments)
        self.segments = []

    def _line(self, text: str) -> bool:
        try:
            self.proc.stdin.write(text.encode() + b"\n")
            self.proc.stdin.flush()
            return True
        except (BrokenPipeError, ValueError, OSError):
            return False

    def inject(self, kind: str, node: int, value=0) -> None:
        """Fault injection into the simulated drives (:func:`hexacnc.daemon.simhost.inject`)."""
        if not self._line(f"inject {kind} {int(node)} {value}"):
            raise BusError("the simulated drives process is not running")

    def truth(self, path: str, timeout_s: float = 5.0) -> dict:
        """The drives' physical state (:func:`hexacnc.daemon.simhost.write_truth`), for benchmarks."""
        import json
        import time
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass
        if not self._line(f"truth {path}"):
            raise BusError("the simulated drives process is not running")
        t_end = time.monotonic() + timeout_s
        while not os.path.exists(path):
            if time.monotonic() > t_end:
                raise BusError(f"the simulated drives wrote no state within {timeout_s:g} s")
            time.sleep(0.005)
        with open(path) as f:
            return {int(k): v for k, v in json.load(f).items()}

    def iolog(self, path: str) -> None:
        """Ask the simulated drives to write their digital I/O and its log to ``path`` (JSON; tests)."""
        if not self._line(f"iolog {path}"):
            raise BusError("the simulated drives process is not running")

    def terminate(self) -> None:
        """Ask the simulated drives to end (they ignore SIGTERM: they stand for hardware)."""
        if self.proc.poll() is None:
            self._line("STOP")
        try:
            self.proc.stdin.close()
        except (BrokenPipeError, OSError, ValueError):
            pass

    def wait(self, timeout=None):
        return self.proc.wait(timeout)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()

    @property
    def stdout(self):
        return self.proc.stdout

    @property
    def stderr(self):
        return self.proc.stderr


def start_simulation(cfg, mode: str, period_s: float, faults=(), channel: str | None = None):
    """Start the simulated drives process when the mode needs one; returns its handle or None."""
    if mode in ("pipe", "shm"):
        return PipeSim(cfg, faults, transport=mode)
    if mode != "bus" or not cfg.bus.simulate:
        return None
    from ..sim import drives as simdrive
    if cfg.bus.interface == "virtual":
        raise BusError("[bus] interface 'virtual' cannot reach simulated drives in another process: "
                       "use udp_multicast (inside a network namespace) or socketcan (vcan)")
    ch = channel or cfg.bus.channel
    log.info("starting simulated drives (%s %s)", cfg.bus.interface, ch)
    proc = simdrive.spawn(cfg.path, interface=cfg.bus.interface, channel=ch, faults=list(faults))
    drives_realtime(proc.pid, sim_drives_priority(cfg.cycle.realtime_priority))
    return proc


def drives_realtime(pid: int, priority: int) -> bool:
    """SCHED_FIFO for every thread of the simulated drives process, when permitted.

    The simulated drives stand for hardware that keeps time; on a loaded machine a normal-priority
    process misses SYNCs and SDO answers.  Returns False (logged) when not permitted.
    """
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        for tid in tids:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (OSError, AttributeError, ValueError) as exc:
        log.warning("simulated drives at normal priority: %s", exc)
        return False


def child_args(sim, channel: str | None = None) -> dict:
    if isinstance(sim, PipeSim):
        if sim.transport == "shm":
            return {"channel": channel, "shm_rings": [seg.name for seg in sim.segments]}
        return {"channel": channel, "pipe_fds": list(sim.hot_fds)}
    return {"channel": channel}


def pass_fds(sim) -> tuple:
    return tuple(sim.hot_fds) if isinstance(sim, PipeSim) else ()


def stop_simulation(sim) -> None:
    if sim is None:
        return
    if isinstance(sim, PipeSim):
        sim.close_fds()
    sim.terminate()
    try:
        sim.wait(5)
    except Exception:
        sim.kill()
        sim.wait(5)
    for f in (sim.stdout, sim.stderr):
        try:
            f.close()
        except Exception:
            pass
    if isinstance(sim, PipeSim):
        sim.release()


class CyclicAdapter:
    """:class:`drivers.cyclic.CyclicIO` seen through the loop's :class:`~hexacnc.daemon.loop.IOProtocol`."""

    def __init__(self, cio, bus_load: float, info: dict):
        from drivers import cyclic
        self.cio = cio
        self.n = cio.n
        self.target = self._target = [0] * 6
        self._send = cio.send
        self.pos = cio.pos_inc                # same list objects: no copies per cycle
        self.statusword = cio.status
        self.pos_count = cio.pos_count        # counted by the codec as it decodes
        self.pos_sync = cio.pos_sync          # the SYNC each drive's last sample answers
        self.sync_every = cio.sync_every      # loop cycles per bus cycle (pos_sync counts loop cycles)
        self.nmt_state = cio.nmt_state        # from the drives' heartbeats (0: boot-up)
        self.hb_ns = [0] * 6
        self.emcy_count = [0] * 6
        self.emcy_code = [0] * 6
        self._emcy_last = [None] * 6
        self.bootups = 0                #: boot-up messages seen (a drive was reset or power-cycled)
        self.encoder_errors = 0         #: EMCYs 0x73xx (sensor / encoder)
        self.bus_load = bus_load
        self.info = info
        self._EV_EMCY = cyclic.EV_EMCY
        self._EV_BOOTUP = cyclic.EV_BOOTUP
        self._EV_FEEDBACK = cyclic.EV_FEEDBACK
        self._EV_HEARTBEAT = cyclic.EV_HEARTBEAT
        self._hb_first = True           # hb_ns from the construction time until the first heartbeat
        self._hb = cio.last_heartbeat_s
        self.sdo_resp = cio.sdo_resp          # SDO answers (homing: hexacnc.daemon.homeloop)
        self.sdo_count = cio.sdo_count
        self.send_sdo = cio.send_sdo
        self.torque_pdo_permille = cio.torque_pdo_permille    # TPDO3 drive torque (drivers/torquepdo.py)
        self.torque_pdo_time_s = cio.torque_pdo_time_s
        self.torque_pdo_count = cio.torque_pdo_count

    def poll(self, now_ns: int) -> int:
        cio = self.cio
        ev = cio.poll()
        if ev & self._EV_HEARTBEAT or self._hb_first:
            self._hb_first = False
            hb = self._hb
            hb_ns = self.hb_ns
            for i in range(6):
                hb_ns[i] = int(hb[i] * 1e9)
        if ev & self._EV_EMCY:
            q = cio.emcy
            while q:
                i, code, reg, extra, t = q.popleft()
                if code == 0:          # "error reset / no error" EMCY
                    continue
                self.emcy_code[i] = code
                self._emcy_last[i] = (code, reg, bytes(extra))
                self.emcy_count[i] += 1
                if code & 0xFF00 == 0x7300:     # sensor / encoder error: the position cannot be trusted
                    self.encoder_errors += 1
        if ev & self._EV_BOOTUP:
            self.bootups = cio.bootups
        return ev

    def send(self) -> int:
        return self._send(self._target)

    def set_controlword(self, i: int, cw: int) -> None:
        self.cio.set_controlword(i, cw)

    def emcy_text(self, i: int) -> str:
        from drivers import cia402
        e = self._emcy_last[i]
        return cia402.emcy_text(*e) if e else ""

    def close(self) -> None:
        self.cio.end_session()          # NMT pre-operational: drives stop PDOs and RPDO deadline monitoring
        for b in self.cio.buses:
            try:
                b.shutdown()
            except Exception:
                pass


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
    from drivers import busload, canbus, cia402, cyclic
    from drivers.master import Master
    rep = busload.check_layout(cfg.bus, period_s)      # BusError with the figures if it does not fit
    load = float(rep["load"])
    if sim_args.get("shm_rings"):
        from .shmbus import ShmBus
        buses = [ShmBus(name, side=0) for name in sim_args["shm_rings"]]
        transport = "shared-memory frame ring"
    elif sim_args.get("pipe_fds"):
        from .pipebus import PipeBus
        buses = [PipeBus(fd=fd) for fd in sim_args["pipe_fds"]]
        transport = "pipe (Unix socket pair)"
    else:
        transport = cfg.bus.interface
        buses = canbus.open_buses(cfg.bus, channel=sim_args.get("channel"))
    from drivers.pcap import capture_buses
    buses = capture_buses(buses)        # hexacnc run --capture FILE.pcap ($HEXACNC_CAPTURE): every frame
    try:
        m = Master(cfg, buses)
        for attempt in (1, 2, 3):   # a loaded machine can miss an SDO answer: boot again from NMT reset
            try:
                # no enable here: the hot loop walks the drives to Operation Enabled in the cyclic
                # frames, with SYNC running and the measured positions as targets (never by SDO
                # before the loop: the drives would sit enabled with nothing to follow)
                m.bring_up(enable=False)
                break
            except BusError as exc:
                if attempt == 3:
                    raise
                log.warning("bus start attempt %d failed (%s); retrying", attempt, exc)
        sw = m.statuswords()
        pos = m.positions_inc()
        m.detach()
        cio = cyclic.CyclicIO(buses, cfg.bus, limits_inc=cyclic.limits_inc(cfg),
                              controlword=cia402.CW_DISABLE_VOLTAGE, period_s=period_s,
                              sync_every=m.sync_every)   # bus period per 0x60C2 (drivers.commission)
        for i in range(6):
            cio.status[i] = sw[i]
            cio.pos_inc[i] = pos[i]
    except BaseException:
        for b in buses:
            try:
                b.shutdown()
            except Exception:
                pass
        raise
    info = {"mode": mode, "interface": transport, "layout": cfg.bus.layout, "buses": cfg.bus.buses,
            "bus_load": load, "bus_summary": busload.describe(rep),
            "frame_batch": cio.batch}     # one write/read per bus per cycle (drivers.framerec)
    return CyclicAdapter(cio, load, info)
