"""``hexacnc run``: start the daemon - drives (or simulated drives), hot loop, socket server."""
from __future__ import annotations

import argparse
import logging
import signal
import threading
import time

HELP = "run the daemon: boot the drives, start the hot loop and serve the socket"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="F", help="machine description (TOML); default: the embedded "
                        "default machine with simulated drives (no root, no network)")
    parser.add_argument("--socket", metavar="PATH", help="Unix socket path (default: [daemon] socket_path)")
    parser.add_argument("--duration", type=float, metavar="S", help="run S seconds, then stop cleanly (exit 0)")
    parser.add_argument("--io", choices=("auto", "bus", "shm", "pipe", "inproc"), default="auto",
                        help="drive I/O: bus = [bus] interface (with hexacnc.sim.drives when [bus] simulate); "
                             "shm = simulated drives over a shared-memory frame ring; pipe = over a Unix "
                             "socket pair; inproc = model inside the loop; "
                             "auto: shm for interface 'virtual' with simulate, else bus")
    parser.add_argument("--demo", action="store_true",
                        help="run the embedded demo program (a small 5-axis part) and show its progress; "
                             "without --duration, exit when it has finished")
    parser.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO")
    parser.add_argument("--log-level", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                        help="default: [daemon] log_level")
    parser.add_argument("--truth", metavar="TRUE.toml",
                        help="simulated drives only: the plant and the simulated instruments follow this true "
                             "machine (hexacnc calib synth-machine); overrides [simulation] truth")
    parser.add_argument("--capture", metavar="FILE.pcap", help="write every CAN frame of the session to a "
                        "SocketCAN pcap (Wireshark link type 227; more buses: FILE-bus1.pcap, ...); with simulated "
                        "drives also their side of the buses, which outlives the master: FILE-drives.pcap, ...")


class Watchdog(threading.Thread):
    """sd_notify WATCHDOG=1, only while the hot loop's cycle counter advances and it is not in fault."""

    def __init__(self, daemon, notifier, interval_s: float):
        super().__init__(name="hexacnc-watchdog", daemon=True)
        self.daemon_ = daemon
        self.notifier = notifier
        self.interval_s = interval_s
        self.stop_event = threading.Event()
        self.pets = 0

    def run(self) -> None:
        from ..daemon import shm as S
        last = -1
        while not self.stop_event.wait(self.interval_s):
            sh = self.daemon_.sh
            if sh is None or not self.daemon_.alive:
                continue
            cycles = sh.h[S.H_CYCLES]
            beat = sh.h[S.H_LOOP_BEAT_NS]
            fresh = time.monotonic_ns() - beat < 1_000_000_000
            if cycles != last and fresh:
                self.notifier.notify("WATCHDOG=1")
                self.pets += 1
            last = cycles


def _start_demo(daemon, log) -> bool:
    from importlib import resources
    text = (resources.files("hexacnc") / "data" / "demo.ngc").read_text(encoding="utf-8")
    reply = daemon.load_program(text, "demo.ngc")
    log.info("demo: program demo.ngc checked against every limit and queued: %d blocks, %.1f s",
             reply.get("blocks", 0), reply.get("duration_s", 0.0))
    return True


def _demo_progress(daemon, log) -> bool | None:
    """True while the demo runs, False when it finished, None when it ended in a fault."""
    st = daemon.status()
    prog = st.get("program") or {}
    pc = st.get("pose_cmd") or [0.0] * 6
    c = st["cycle"]
    log.info("demo: %-8s line %-3s %5.1f %%  platform x %7.2f y %7.2f z %8.2f a %6.2f b %6.2f  "
             "compute p99 %s us, overruns %d", st["state"], prog.get("line", st.get("line")),
             float(prog.get("percent") or 0.0), pc[0], pc[1], pc[2], pc[3], pc[4],
             c["compute_us"]["p99"], c["overruns"])
    if st.get("fault"):
        log.error("demo: fault %s", st["fault"])
        return None
    if st["state"] == "idle" and not (prog.get("queued") or 0) and float(prog.get("percent") or 0.0) >= 100.0:
        log.info("demo: finished; strut commands %s mm",
                 ", ".join(f"{v:.4f}" for v in st.get("struts_cmd_mm") or []))
        return False
    return True


def _load_truth(cfg, path):
    """The true machine of ``--truth`` or ``[simulation] truth`` (simulated drives only), else None."""
    from ..errors import ConfigError
    path = path or cfg.simulation_truth
    if not path:
        return None
    if not cfg.bus.simulate:
        raise ConfigError(f"--truth {path}: a true machine is for simulated drives ([bus] simulate = true "
                          f"in {cfg.path})")
    from ..sim.truth import load_truth
    return load_truth(path)


def main(args: argparse.Namespace) -> int:
    from ..config import load_config
    from ..daemon.core import Daemon
    from ..daemon.sdnotify import Notifier
    from ..daemon.server import SocketServer

    cfg = load_config(args.config)
    if getattr(args, "capture", None):      # read by the hot process when it opens the buses (drivers.pcap)
        import os
        os.environ["HEXACNC_CAPTURE"] = os.path.abspath(args.capture)
    truth = _load_truth(cfg, getattr(args, "truth", None))
    if truth is not None and not cfg.simulation_truth:
        from pathlib import Path
        cfg = cfg.replace(simulation_truth=str(Path(truth.path).resolve()))      # the simulated drives' probe input reads it
    level = args.log_level or cfg.daemon.log_level
    logging.basicConfig(level=getattr(logging, level), format="%(asctime)s hexacnc %(levelname)s %(message)s")
    log = logging.getLogger("hexacnc.run")
    stop = threading.Event()

    got = []

    def on_signal(signum, frame):
        got.append(signum)
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    notifier = Notifier()
    daemon = server = wd = sock_lock = None
    rc = 0
    try:
        log.info("machine %s (%s)", cfg.name, cfg.path)
        from ..daemon.admission import preflight
        sock_path = preflight(cfg, args.socket)   # socket directory, token, TLS: refused before the drives boot
        # before any frame: nobody else serves this socket (lock naming its pid, then a probe)
        sock_lock = _claim_socket(sock_path)
        daemon = Daemon(cfg, io_mode=args.io, realtime=not args.no_realtime, log_level=level)
        from ..daemon.calibops import attach
        attach(daemon, truth)
        if truth is not None:
            log.info("simulated plant follows the true machine %s (the controller uses %s)", truth.path, cfg.path)
        _log_start(daemon, log)
        server = SocketServer(daemon, cfg, sock_path).start()
        log.info("socket %s (hexacnc send PROGRAM.ngc --socket %s; hexacnc status --socket %s)",
                 server.socket_path, server.socket_path, server.socket_path)
        notifier.notify("READY=1\nSTATUS=" + ("drives disabled, waiting for enable" if daemon.awaiting_enable
                                              else "drives enabled, cycle running"))
        wd_s = notifier.watchdog_s or (cfg.cycle.watchdog_s if notifier.enabled else 0.0)
        if notifier.enabled and wd_s > 0:
            wd = Watchdog(daemon, notifier, wd_s / 3.0)
            wd.start()
        log.info("running (cycle %.3f ms); Ctrl-C stops", daemon.period_s * 1e3)
        rc = _serve(daemon, server, args, stop, log)
        daemon = server.daemon          # the daemon now serving (a reload replaces it)
        st = daemon.status()
        c = st["cycle"]
        log.info("stopping%s: %d cycles, compute median/p99/max %s/%s/%.0f us, overruns %d",
                 f" on {signal.Signals(got[0]).name}" if got else "",
                 c["cycles"], c["compute_us"]["median"], c["compute_us"]["p99"], c["compute_us"]["max"],
                 c["overruns"])
        notifier.notify("STOPPING=1")
    finally:
        if wd is not None:
            wd.stop_event.set()
        if server is not None:
            server.close()
            if server.daemon is not daemon:     # reloaded while starting up or stopping
                daemon = server.daemon
        if daemon is not None:
            daemon.close()          # controlled stop, drives disabled
            if daemon.final_fault is not None:
                log.error("ended in fault %s: %s", daemon.final_fault.get("code"),
                          daemon.final_fault.get("message"))
                rc = 1
        if sock_lock is not None:
            from ..daemon.procs import release_lock
            release_lock(sock_lock)
        for s, h in old.items():
            signal.signal(s, h)
        notifier.close()
    return rc


def _log_start(daemon, log) -> None:
    """The start-up summary: drives and transport, frame rings, bus load, privileges."""
    info = daemon.info
    io_info = info.get("io_info", {})
    log.info("drives: %s, transport %s", info.get("io_mode"), io_info.get("interface", io_info.get("drives")))
    segs = getattr(daemon.sim, "segments", None)
    if segs:
        log.info("frame rings: %s", " ".join(seg.name for seg in segs))
    log.info("bus: %s", info.get("bus_summary"))
    for m in (info.get("privileges") or {}).get("messages", []):
        log.info("hot loop privileges: %s", m)


def _serve(daemon, server, args, stop: threading.Event, log) -> int:
    """Run until a signal, ``--duration``, the end of ``--demo`` or the hot loop's end; returns
    the exit status so far (1: the hot loop was lost or the demo faulted). Follows the server's
    daemon when the op ``reload`` replaces it."""
    t_end = None if args.duration is None else time.monotonic() + args.duration
    last_log = time.monotonic()
    demo_running = _start_demo(daemon, log) if args.demo else False
    while not stop.is_set():
        if t_end is not None and time.monotonic() >= t_end:
            return 0
        stop.wait(0.1)
        if server.daemon is not daemon:     # reloaded (op reload)
            daemon = server.daemon
        if getattr(server, "calib_reloading", False):
            continue
        if not daemon.alive:
            end = daemon.await_hot_end(2.0)     # the watch thread classifies the exit (it polls)
            msg = end.message if end is not None else (daemon.status().get("fault") or {}).get("message")
            if end is not None and end.clean:
                log.warning("%s; exiting", msg)
                return 0
            log.error("hot loop process ended: %s", msg)
            return 1
        if demo_running and time.monotonic() - last_log >= 1.0:
            last_log = time.monotonic()
            demo_running = _demo_progress(daemon, log)
            if demo_running is None:
                return 1
            if not demo_running and t_end is None:
                return 0
            continue
        if time.monotonic() - last_log >= 10.0:
            last_log = time.monotonic()
            st = daemon.status()
            c = st["cycle"]
            log.info("state %s, cycles %d, compute p99 %s us, lateness p99 %s us, overruns %d (max %d in a row)",
                     st["state"], c["cycles"], c["compute_us"]["p99"], c["lateness_us"]["p99"],
                     c["overruns"], c["max_overruns_in_row"])
    return 0


def _claim_socket(path: str):
    """Lock ``<socket>.lock`` (naming our pid) and check nobody answers on the socket; returns the
    lock fd. Raises HexacncError naming the other daemon."""
    import os
    from ..daemon.procs import acquire_lock, release_lock
    from ..daemon.server import check_socket_path
    if not os.path.isdir(os.path.dirname(os.path.abspath(path))):
        check_socket_path(path)         # the clear error about the directory
    fd = acquire_lock(path + ".lock", f"socket {path}")
    try:
        check_socket_path(path)
    except BaseException:
        release_lock(fd)
        raise
    return fd
