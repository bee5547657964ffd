"""``[cycle]``, ``[bus]`` (with ``nodes``) and ``[daemon]``: the typed sections of the running daemon,
each beside its parse function."""
from __future__ import annotations

import dataclasses
import ipaddress
import os
from dataclasses import dataclass

import numpy as np

from .section import Section, _expand_user_vars, _freeze

@dataclass(frozen=True)
class CycleConfig:
    period_s: float = 0.0005
    max_overruns_in_row: int = 3
    setpoint_timeout_s: float = 0.05
    realtime_priority: int = 80
    cpu: int = -1                              #: -1: last CPU
    following_error_mm: float = 1.0
    watchdog_s: float = 2.0
    spin_s: float = 0.0002                     #: the hot loop spins this long before each deadline
    #: a drive without a fresh position sample this long faults (stale feedback), heartbeat or not; also
    #: the longest stall of the feedback the following-error check still matches to its SYNC
    feedback_timeout_s: float = 0.35


@dataclass(frozen=True)
class BusConfig:
    interface: str = "virtual"                 #: socketcan | virtual | udp_multicast
    channel: str = "hexacnc"
    bitrate: int = 1_000_000
    fd: bool = False
    data_bitrate: int = 2_000_000
    buses: int = 2                             #: 1 Mbit/s classic: 2 buses so feedback fits 0.5 ms
    node_ids: tuple[int, ...] = (1, 2, 3, 4, 5, 6)
    layout: str = "paired"                     #: single | paired | fd | separate (no dummies)
    feedback_divider: int = 3                  #: TPDO every n-th SYNC (staggered per drive)
    max_load: float = 0.95                     #: worst-case bus time / cycle
    increments_per_mm: float = 10000.0
    #: heartbeat producer period (drives' 0x1017, staggered +3 ms per strut; the master's own heartbeat).
    #: 250 ms: with 3 drives a bus, their heartbeats, the master's and the statusword refreshes ride on
    #: under 1 % of the 0.5 ms bus cycles, so the bus demand's p99 stays within 10 % of its median
    #: (``hexacnc bus demand``; 100 ms: 1.9 % of the cycles, p99/median 1.17). A silent drive is found by
    #: its stale feedback ([cycle] feedback_timeout_s), a silent master by comm_loss_timeout_s: neither
    #: waits for a heartbeat
    heartbeat_ms: int = 250
    #: heartbeat consumer time: the master's limit for a drive's heartbeat (at least feedback_timeout_s +
    #: heartbeat_ms, hexacnc.daemon.supervise) and the drives' 0x1016 for the master's (2.4 periods)
    heartbeat_timeout_ms: int = 600
    simulate: bool = True                      #: start the simulated drives process
    simulate_profile: str = "permissive"       #: permissive | strict (simulated drives, see drivers/README.md)
    node_eds: tuple = ()                       #: per node: EDS/DCF path ("" = bundled default), from [bus] nodes
    node_identity: tuple = ()                  #: per node: (vendor, product, revision), -1 = from the EDS
    boot_timeout_s: float = 15.0               #: boot-up messages after NMT reset
    #: drives stop on their own (quick stop) when the master is silent this long (configured at boot:
    #: RPDO deadline 0x1400:05 and SYNC time-out 0x1006; the heartbeat consumer 0x1016 is heartbeat_timeout_ms)
    comm_loss_timeout_s: float = 0.02
    feed_mm_per_rev: float = 0.0               #: strut travel per driving-shaft revolution (0: units unchecked)
    write_factor_group: bool = False           #: write 0x6092 feed constant from increments_per_mm x feed_mm_per_rev
    #: drive torque 0x6077 in a decimated TPDO3 every n-th SYNC (0: off; drivers/torquepdo.py)
    torque_pdo_every: int = 0


@dataclass(frozen=True)
class DaemonConfig:
    #: "" = the default place (hexacnc.daemon.sockpath.server_socket_path): $RUNTIME_DIRECTORY under
    #: systemd, else $XDG_RUNTIME_DIR/hexacnc/, else a 0700 /tmp/hexacnc-UID/ the user owns
    socket_path: str = ""
    tcp_port: int = 0                          #: 0: no TCP
    tcp_token: str = ""                        #: legacy: prefer token_file; >= 128 bits either way (checked
                                               #: with the file modes at start: hexacnc.daemon.admission.preflight)
    token_file: str = ""                       #: TCP token, a file only the daemon's user can read
    controller_group: str = ""                 #: Unix peers in this group may command motion
    observer_group: str = ""                   #: Unix peers in this group may only read
    sensor_group: str = ""                     #: Unix peers in this group may read and send temperatures
    tcp_role: str = "controller"               #: role of an authenticated TCP client
    service_user: str = "hexacnc"              #: clients trust sockets owned by this user (and own/root)
    idle_timeout_s: float = 600.0              #: a connection silent this long (no wait/stream running) is closed
    max_unauthenticated: int = 16              #: TCP connections before "hello": own pool, never a client slot
    enable_at_start: bool = True               #: resolved at load: default true only with [bus] simulate
    tcp_host: str = "127.0.0.1"                #: TCP address; other than loopback only with TLS
    tls_cert: str = ""                         #: PEM certificate: TLS on the TCP socket (with tls_key)
    tls_key: str = ""                          #: PEM private key, readable by the daemon's user only
    status_rate_hz: float = 20.0
    log_level: str = "INFO"
    max_clients: int = 32                      #: simultaneous socket clients
    #: largest protocol message accepted: one message is decoded in the socket loop at ~2 ms per MiB
    #: (with the GIL held), so a larger program goes in chunks (program_begin/program_chunk/program_end)
    max_message_bytes: int = 2 * 1024 * 1024
    #: a program is interpreted and planned in a child process with at most this address space (MB)
    max_plan_memory_mb: int = 4096
    #: ... and at most this long (s); over either it is refused naming the limit and the line reached
    max_plan_s: float = 300.0
    #: seconds of a program's or move's setpoints kept queued ahead of the hot loop: how long the
    #: supervisor (not real-time) may go unscheduled before the loop runs dry and stops the motion.
    #: Pause, stop and override take queued rows back (a 5 ms lead), so they do not wait behind it;
    #: jogs keep a short queue (hexacnc.daemon.feeding.JOG_AHEAD_S) for their dead-man stop
    feed_ahead_s: float = 1.0


def parse_cycle(cy: Section, s: Section) -> tuple[CycleConfig, np.ndarray | None]:
    """``[cycle]`` and ``[struts] max_following_error_mm`` (None: ``[cycle] following_error_mm``)."""
    cd = CycleConfig()
    cycle = CycleConfig(
        period_s=cy.getfloat("period_s", cd.period_s, minval=1e-4, maxval=0.1),
        max_overruns_in_row=cy.getint("max_overruns_in_row", cd.max_overruns_in_row, minval=1, maxval=1000),
        setpoint_timeout_s=cy.getfloat("setpoint_timeout_s", cd.setpoint_timeout_s, above=0.0, maxval=10.0),
        realtime_priority=cy.getint("realtime_priority", cd.realtime_priority, minval=1, maxval=99),
        cpu=cy.getint("cpu", cd.cpu, minval=-1, maxval=1023),
        following_error_mm=cy.getfloat("following_error_mm", cd.following_error_mm, above=0.0),
        watchdog_s=cy.getfloat("watchdog_s", cd.watchdog_s, above=0.0, maxval=600.0),
        spin_s=cy.getfloat("spin_s", cd.spin_s, minval=0.0, maxval=0.1),
        feedback_timeout_s=cy.getfloat("feedback_timeout_s", cd.feedback_timeout_s, above=0.0, maxval=10.0),
    )
    ferr = (s.getvec("max_following_error_mm", 6, above=0.0, maxval=1000.0, allow_scalar=True)
            if s.has("max_following_error_mm") else None)
    if cycle.spin_s > 0.8 * cycle.period_s:
        raise cy.error("spin_s", f"{cycle.spin_s:g} s is more than 80 % of period_s = {cycle.period_s:g} s: "
                                 "the hot loop must sleep part of every period (SCHED_FIFO throttling)")
    return cycle, None if ferr is None else _freeze(ferr)


def parse_bus(b: Section) -> BusConfig:
    """``[bus]``: interface, bit rates, layout, node ids (or ``nodes``), timing, simulated drives."""
    bd = BusConfig()
    node_ids = b.getvec("node_ids", 6, list(bd.node_ids), minval=1, maxval=127)
    if len(set(int(x) for x in node_ids)) != 6 or any(x != int(x) for x in node_ids):
        raise b.error("node_ids", f"must be 6 distinct integers 1..127, got {node_ids.tolist()}")
    bus = BusConfig(
        interface=b.getchoice("interface", ("socketcan", "virtual", "udp_multicast"), bd.interface),
        channel=b.getstr("channel", bd.channel),
        bitrate=b.getint("bitrate", bd.bitrate, minval=10_000, maxval=1_000_000),
        fd=b.getbool("fd", bd.fd),
        data_bitrate=b.getint("data_bitrate", bd.data_bitrate, minval=10_000, maxval=8_000_000),
        buses=b.getint("buses", bd.buses, minval=1, maxval=6),
        node_ids=tuple(int(x) for x in node_ids),
        layout=b.getchoice("layout", ("single", "paired", "fd", "separate"), bd.layout),
        feedback_divider=b.getint("feedback_divider", bd.feedback_divider, minval=1, maxval=100),
        max_load=b.getfloat("max_load", bd.max_load, above=0.0, maxval=1.0),
        increments_per_mm=b.getfloat("increments_per_mm", bd.increments_per_mm, above=0.0, maxval=1e7),
        heartbeat_ms=b.getint("heartbeat_ms", bd.heartbeat_ms, minval=1, maxval=10000),
        heartbeat_timeout_ms=b.getint("heartbeat_timeout_ms", bd.heartbeat_timeout_ms, minval=1, maxval=60000),
        comm_loss_timeout_s=b.getfloat("comm_loss_timeout_s", bd.comm_loss_timeout_s, minval=0.002, maxval=10.0),
        simulate=b.getbool("simulate", bd.simulate),
        simulate_profile=b.getchoice("simulate_profile", ("permissive", "strict"), bd.simulate_profile),
        boot_timeout_s=b.getfloat("boot_timeout_s", bd.boot_timeout_s, above=0.0, maxval=600.0),
        feed_mm_per_rev=b.getfloat("feed_mm_per_rev", bd.feed_mm_per_rev, minval=0.0, maxval=1e4),
        write_factor_group=b.getbool("write_factor_group", bd.write_factor_group),
        torque_pdo_every=b.getint("torque_pdo_every", bd.torque_pdo_every, minval=0, maxval=240),
    )
    return _bus_nodes(b, bus)


def _bus_nodes(b: "Section", bus: "BusConfig") -> "BusConfig":
    """``[bus] nodes``: a list of tables ``{node_id = N, eds = "file.eds|dcf", vendor_id = ...,
    product_code = ..., revision = ...}`` (all but node_id optional), one per drive in strut order.
    Sets node_ids (must agree with an explicit ``node_ids``), node_eds, node_identity."""
    if not b.has("nodes"):
        return bus
    entries = b._get("nodes", None)
    if not isinstance(entries, list) or len(entries) != 6 or not all(isinstance(e, dict) for e in entries):
        raise b.error("nodes", "expected a list of 6 tables like {node_id = 1, eds = \"drive.eds\"}")
    base = os.path.dirname(os.path.abspath(b.path)) if os.path.isfile(b.path) else os.getcwd()
    ids, eds, idents = [], [], []
    for k, e in enumerate(entries):
        where = f"nodes[{k}]"
        extra = set(e) - {"node_id", "eds", "vendor_id", "product_code", "revision"}
        if extra:
            raise b.error(where, f"unknown key(s) {sorted(extra)}")
        nid = e.get("node_id")
        if isinstance(nid, bool) or not isinstance(nid, int) or not 1 <= nid <= 127:
            raise b.error(where, f"node_id must be an integer 1..127, got {nid!r}")
        ids.append(nid)
        path = e.get("eds", "")
        if not isinstance(path, str):
            raise b.error(where, f"eds must be a file name, got {path!r}")
        if path:
            path = os.path.join(base, os.path.expanduser(path))
            if not os.path.isfile(path):
                raise b.error(where, f"eds {path!r}: no such file")
        eds.append(path)
        ident = []
        for key in ("vendor_id", "product_code", "revision"):
            v = e.get(key, -1)
            if isinstance(v, bool) or not isinstance(v, int) or not -1 <= v <= 0xFFFFFFFF:
                raise b.error(where, f"{key} must be an integer 0..0xFFFFFFFF, got {v!r}")
            ident.append(v)
        idents.append(tuple(ident))
    if len(set(ids)) != 6:
        raise b.error("nodes", f"node ids must be 6 distinct integers, got {ids}")
    if b.has("node_ids") and tuple(ids) != tuple(bus.node_ids):
        raise b.error("nodes", f"node ids {ids} disagree with [bus] node_ids {list(bus.node_ids)}")
    return dataclasses.replace(bus, node_ids=tuple(ids), node_eds=tuple(eds), node_identity=tuple(idents))


def _daemon_config(d: Section, bus: BusConfig) -> DaemonConfig:
    """``[daemon]``: socket, access (groups, TCP token, TLS), time-outs, enable at start."""
    dd = DaemonConfig()
    daemon = DaemonConfig(
        socket_path=_expand_user_vars(d.getstr("socket_path", dd.socket_path)),
        tcp_port=d.getint("tcp_port", dd.tcp_port, minval=0, maxval=65535),
        tcp_token=d.getstr("tcp_token", dd.tcp_token),
        status_rate_hz=d.getfloat("status_rate_hz", dd.status_rate_hz, above=0.0, maxval=1000.0),
        log_level=d.getchoice("log_level", ("DEBUG", "INFO", "WARNING", "ERROR"), dd.log_level),
        max_clients=d.getint("max_clients", dd.max_clients, minval=1, maxval=1024),
        max_message_bytes=d.getint("max_message_bytes", dd.max_message_bytes, minval=4096, maxval=1 << 30),
        max_plan_memory_mb=d.getint("max_plan_memory_mb", dd.max_plan_memory_mb, minval=512, maxval=1 << 20),
        max_plan_s=d.getfloat("max_plan_s", dd.max_plan_s, above=0.0, maxval=86400.0),
        feed_ahead_s=d.getfloat("feed_ahead_s", dd.feed_ahead_s, minval=0.05, maxval=8.0),
        token_file=_expand_user_vars(d.getstr("token_file", dd.token_file)),
        controller_group=d.getstr("controller_group", dd.controller_group),
        observer_group=d.getstr("observer_group", dd.observer_group),
        sensor_group=d.getstr("sensor_group", dd.sensor_group),
        tcp_role=d.getchoice("tcp_role", ("controller", "sensor", "observer"), dd.tcp_role),
        service_user=d.getstr("service_user", dd.service_user),
        idle_timeout_s=d.getfloat("idle_timeout_s", dd.idle_timeout_s, minval=1.0, maxval=86400.0),
        max_unauthenticated=d.getint("max_unauthenticated", dd.max_unauthenticated, minval=1, maxval=1024),
        enable_at_start=d.getbool("enable_at_start", bool(bus.simulate)),
        tcp_host=_tcp_host(d),
        tls_cert=_expand_user_vars(d.getstr("tls_cert", dd.tls_cert)),
        tls_key=_expand_user_vars(d.getstr("tls_key", dd.tls_key)),
    )
    if bool(daemon.tls_cert) != bool(daemon.tls_key):
        raise d.error("tls_key" if daemon.tls_cert else "tls_cert", "tls_cert and tls_key go together")
    if not daemon.tls_cert and not ipaddress.ip_address(daemon.tcp_host).is_loopback:
        raise d.error("tcp_host", f"value {daemon.tcp_host!r} is not a loopback address: off the host the "
                                  f"token needs TLS (set tls_cert and tls_key)")
    if daemon.tcp_port and not (daemon.tcp_token or daemon.token_file):
        raise d.error("token_file", "a token is required when tcp_port is set (token_file, or legacy tcp_token)")
    return daemon


def _tcp_host(d: Section) -> str:
    v = d.getstr("tcp_host", "127.0.0.1")
    try:
        return str(ipaddress.ip_address(v))
    except ValueError:
        raise d.error("tcp_host", f"value {v!r} is not an IP address") from None
