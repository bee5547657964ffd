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
                        help="drive I/O: bus = [bus] interface (with drivers.simdrive when [bus] simulate); "
                             "shm = simulated drives over a shared-memory frame ring; pipe = over a Unix "
                             "socket pair; inproc = model inside the loop; "
                             "auto: shm for interface 'virtual' with simulate, else bus")
    parser.add_argument("--demo", action="store_true",
                        help="run the embedded demo program (a small 5-axis part) and show its progress; "
                             "without --duration, exit when it has finished")
    parser.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO")
    parser.add_argument("--log-level", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                        help="default: [daemon] log_level")


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


def _demo_progress(daemon, log) -> bool:
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
        return False
    if st["state"] == "idle" and not (prog.get("queued") or 0) and float(prog.get("percent") or 0.0) >= 100.0:
        log.info("demo: finished; strut commands %s mm",
                 ", ".join(f"{v:.4f}" for v in st.get("struts_cmd_mm") or []))
        return False
    return True


def main(args: argparse.Namespace) -> int:
    from ..config import load_config
    from ..daemon.core import Daemon
    from ..daemon.sdnotify import Notifier
    from ..daemon.server import SocketServer

    cfg = load_config(args.config)
    level = args.log_level or cfg.daemon.log_level
    logging.basicConfig(level=getattr(logging, level), format="%(asctime)s hexacnc %(levelname)s %(message)s")
    log = logging.getLogger("hexacnc.run")
    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    notifier = Notifier()
    daemon = server = wd = None
    try:
        log.info("machine %s (%s)", cfg.name, cfg.path)
        daemon = Daemon(cfg, io_mode=args.io, realtime=not args.no_realtime, log_level=level)
        info = daemon.info
        io_info = info.get("io_info", {})
        log.info("drives: %s, transport %s", info.get("io_mode"), io_info.get("interface", io_info.get("drives")))
        log.info("bus: %s", info.get("bus_summary"))
        for m in (info.get("privileges") or {}).get("messages", []):
            log.info("hot loop privileges: %s", m)
        server = SocketServer(daemon, cfg, args.socket).start()
        log.info("socket %s (hexacnc send PROGRAM.ngc --socket %s; hexacnc status --socket %s)",
                 server.socket_path, server.socket_path, server.socket_path)
        notifier.notify("READY=1\nSTATUS=drives enabled, cycle running")
        wd_s = notifier.watchdog_s or (cfg.cycle.watchdog_s if notifier.enabled else 0.0)
        if notifier.enabled and wd_s > 0:
            wd = Watchdog(daemon, notifier, wd_s / 3.0)
            wd.start()
        log.info("running (cycle %.3f ms); Ctrl-C stops", daemon.period_s * 1e3)
        t_end = None if args.duration is None else time.monotonic() + args.duration
        last_log = time.monotonic()
        demo_running = False
        if args.demo:
            demo_running = _start_demo(daemon, log)
        while not stop.is_set():
            if t_end is not None and time.monotonic() >= t_end:
                break
            stop.wait(0.1)
            if not daemon.alive:
                log.error("hot loop process ended: %s", (daemon.status().get("fault") or {}).get("message"))
                return 1
            if demo_running and time.monotonic() - last_log >= 1.0:
                last_log = time.monotonic()
                demo_running = _demo_progress(daemon, log)
                if not demo_running and t_end is None:
                    break
                continue
            if time.monotonic() - last_log >= 10.0:
                last_log = time.monotonic()
                st = daemon.status()
                c = st["cycle"]
                log.info("state %s, cycles %d, compute p99 %s us, lateness p99 %s us, overruns %d (max %d in a row)",
                         st["state"], c["cycles"], c["compute_us"]["p99"], c["lateness_us"]["p99"],
                         c["overruns"], c["max_overruns_in_row"])
        st = daemon.status()
        c = st["cycle"]
        log.info("stopping: %d cycles, compute median/p99/max %s/%s/%.0f us, overruns %d",
                 c["cycles"], c["compute_us"]["median"], c["compute_us"]["p99"], c["compute_us"]["max"],
                 c["overruns"])
        notifier.notify("STOPPING=1")
        return 0
    finally:
        if wd is not None:
            wd.stop_event.set()
        if server is not None:
            server.close()
        if daemon is not None:
            daemon.close()
        for s, h in old.items():
            signal.signal(s, h)
        notifier.close()
