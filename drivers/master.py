"""CANopen master for the non-cyclic work, with the ``canopen`` package. Never call it in the cycle.

::

    m = Master(cfg, buses)          # cfg: MachineConfig; buses: one python-can bus per [bus] buses
    m.bring_up()                    # boot (NMT reset, boot-up), configure (SDO: heartbeats, limits,
                                    # PDO mapping per layout, SYNC counter, mode 8), NMT start, enable
    m.detach()                      # stop canopen's listener threads; hand the buses to CyclicIO
    ...                             # hot loop: drivers.cyclic.CyclicIO (SYNC, targets, controlwords)
    m.attach(); m.disable(); m.pre_operational(); m.close()   # attach resumes the master heartbeat

Every failure is a :class:`hexacnc.errors.BusError` naming the node, its strut and the step.
While attached the master produces its heartbeat (0x700 + 0x7F), which the drives consume
(0x1016); the cyclic codec takes that over when cycling.
"""
from __future__ import annotations

import logging
import time
from typing import Sequence

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from .errors import BusError

from . import cia402, commission, torquepdo
from .cyclic import limits_inc
from .description import node_descriptions
from .layout import (MASTER_NODE_ID, NodePlan, heartbeat_producer_ms, plan_layout, status_event_timer_ms,
                     status_inhibit_100us)

log = logging.getLogger("hexacnc.master")


def interpolation_period(period_s: float) -> tuple[int, int]:
    """0x60C2 (value, index) with value * 10**index == period_s, value 1..255."""
    for idx in range(-6, 1):
        v = period_s / 10.0 ** idx
        if abs(v - round(v)) < 1e-6 * max(1.0, v) and 1 <= round(v) <= 255:
            return int(round(v)), idx
    raise BusError(f"[cycle] period_s = {period_s} cannot be written as 0x60C2 value * 10^index (value 1..255)")


class Master:
    """Master of the six drives on ``buses`` (see module doc)."""

    def __init__(self, cfg, buses: can.BusABC | Sequence[can.BusABC], *, eds_path=None,
                 sdo_timeout_s: float = 0.5):
        """``eds_path``: one description for every node (default: per node, see
        :mod:`drivers.description`: ``[bus] nodes`` entries, else the bundled EDS)."""
        if isinstance(buses, can.BusABC):
            buses = [buses]
        self.cfg = cfg
        self.bus_cfg = cfg.bus
        self.plan = plan_layout(cfg.bus)
        if len(buses) != self.plan.buses:
            raise BusError(f"Master: {len(buses)} bus objects for [bus] buses = {self.plan.buses}")
        self.buses = list(buses)
        self.networks = [canopen.Network(b) for b in self.buses]
        self.nodes: list[canopen.RemoteNode] = []
        self.last_heartbeat_s = [0.0] * len(self.plan.nodes)
        self.nmt_states = [-1] * len(self.plan.nodes)
        self.bootup_s = [0.0] * len(self.plan.nodes)
        self.emcy_log: list[tuple[int, int, int, bytes, float]] = []   #: (strut, code, register, data, t_s)
        self._cw = [0] * len(self.plan.nodes)
        if eds_path is not None:
            from .description import load_description
            self.descriptions = [load_description(str(eds_path))] * len(self.plan.nodes)
        else:
            self.descriptions = node_descriptions(cfg.bus)
        paths = [d.path for d in self.descriptions]
        #: boot report: identity, timing (0x60C2, bus period, sync_every), units, reactions
        self.report: dict = {"descriptions": paths}
        self.bus_period_s = cfg.cycle.period_s
        self.sync_every = 1
        for nd in self.plan.nodes:
            node = canopen.RemoteNode(nd.node_id, canopen.import_od(paths[nd.index], nd.node_id))
            node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
            self.networks[nd.bus].add_node(node)
            node.nmt.add_heartbeat_callback(self._heartbeat_cb(nd.index))
            node.emcy.add_callback(self._emcy_cb(nd.index))
            self.nodes.append(node)
        self._hb_tasks: list = []
        self._heartbeat_wanted = False
        self.attached = False
        self.attach()

    # -- listeners ---------------------------------------------------------------------------
    def _heartbeat_cb(self, i: int):
        def cb(state: int) -> None:
            now = time.monotonic()
            self.last_heartbeat_s[i] = now
            if state == 0:
                self.bootup_s[i] = now
            self.nmt_states[i] = state
        return cb

    def _emcy_cb(self, i: int):
        def cb(err) -> None:
            self.emcy_log.append((i, err.code, err.register, bytes(err.data), time.monotonic()))
            log.warning("node %d (strut %d): EMCY %s", self.plan.nodes[i].node_id, i + 1,
                        cia402.emcy_text(err.code, err.register, err.data))
        return cb

    def attach(self) -> None:
        """(Re)start canopen's listener threads on the buses."""
        if self.attached:
            return
        for net in self.networks:
            net.notifier = can.Notifier(net.bus, net.listeners, 0.05)
        self.attached = True
        if self._heartbeat_wanted:
            self.start_heartbeat()

    def detach(self) -> list[can.BusABC]:
        """Stop listener threads and the master heartbeat; the buses stay open. Returns them."""
        wanted = self._heartbeat_wanted
        self.stop_heartbeat()
        self._heartbeat_wanted = wanted
        for net in self.networks:
            if net.notifier is not None:
                net.notifier.stop(2.0)
                net.notifier = None
        self.attached = False
        return self.buses

    def close(self) -> None:
        self.detach()

    # -- helpers -------------------------------------------------------------------------------
    def who(self, nd: NodePlan) -> str:
        return f"node {nd.node_id} (strut {nd.index + 1}, bus {nd.bus})"

    def fail(self, nd: NodePlan, step: str, msg: str, exc: Exception | None = None) -> BusError:
        return BusError(f"{self.who(nd)}: {step}: {msg}" + (f": {exc}" if exc is not None else ""))

    _who = who
    _fail = fail

    def sdo_read(self, nd: NodePlan, step: str, index: int, sub: int | None = None) -> int:
        return self._read(nd, step, index, sub)

    def sdo_write(self, nd: NodePlan, step: str, index: int, sub: int | None, value: int) -> None:
        self._write(nd, step, index, sub, value)

    def sdo_write_raw(self, nd: NodePlan, index: int, sub: int | None, value: int) -> None:
        """SDO write that lets :class:`SdoAbortedError` through (callers try alternatives)."""
        node = self.nodes[nd.index]
        try:
            (node.sdo[index] if sub is None else node.sdo[index][sub]).raw = value
        except SdoCommunicationError as exc:
            if isinstance(exc, SdoAbortedError):
                raise
            raise self.fail(nd, f"write 0x{index:04X}", "no SDO answer", exc) from exc

    def sdo_read_optional(self, nd: NodePlan, index: int, sub: int | None = None):
        """Value of an optional object, None when the drive or its description lacks it."""
        node = self.nodes[nd.index]
        try:
            obj = node.sdo[index] if sub is None else node.sdo[index][sub]
            return obj.raw
        except (SdoAbortedError, KeyError):
            return None
        except SdoCommunicationError as exc:
            raise self.fail(nd, f"read 0x{index:04X}", "no SDO answer", exc) from exc

    def _write(self, nd: NodePlan, step: str, index: int, sub: int | None, value: int) -> None:
        node = self.nodes[nd.index]
        try:
            var = node.sdo[index] if sub is None else node.sdo[index][sub]
            var.raw = value
        except SdoAbortedError as exc:
            raise self._fail(nd, step, f"drive refused SDO write 0x{index:04X}:{sub or 0:02X} = {value}", exc) from exc
        except SdoCommunicationError as exc:
            raise self._fail(nd, step, f"no SDO answer writing 0x{index:04X}:{sub or 0:02X}", exc) from exc

    def _read(self, nd: NodePlan, step: str, index: int, sub: int | None = None) -> int:
        node = self.nodes[nd.index]
        try:
            var = node.sdo[index] if sub is None else node.sdo[index][sub]
            return var.raw
        except SdoAbortedError as exc:
            raise self._fail(nd, step, f"drive refused SDO read 0x{index:04X}:{sub or 0:02X}", exc) from exc
        except SdoCommunicationError as exc:
            raise self._fail(nd, step, f"no SDO answer reading 0x{index:04X}:{sub or 0:02X}", exc) from exc

    # -- NMT ----------------------------------------------------------------------------------
    def boot(self, timeout_s: float | None = None) -> None:
        """NMT reset node for every drive and wait for the six boot-up messages (then pre-operational).

        ``timeout_s`` default ``[bus] boot_timeout_s`` (real drives need 5-15 s after power-up);
        progress (which nodes are still silent) is logged every second."""
        if timeout_s is None:
            timeout_s = float(getattr(self.bus_cfg, "boot_timeout_s", 15.0))
        t0 = time.monotonic()
        for nd in self.plan.nodes:
            self.nodes[nd.index].nmt.send_command(0x81)
        log.info("NMT reset sent to nodes %s; waiting up to %g s for their boot-up messages",
                 [nd.node_id for nd in self.plan.nodes], timeout_s)
        deadline = t0 + timeout_s
        next_log = t0 + 1.0
        while time.monotonic() < deadline:
            if all(t > t0 for t in self.bootup_s):
                log.info("all %d drives booted after %.2f s", len(self.plan.nodes), time.monotonic() - t0)
                return
            now = time.monotonic()
            if now >= next_log:
                next_log = now + 1.0
                log.info("boot: %.0f s of %g s, waiting for nodes %s", now - t0, timeout_s,
                         [nd.node_id for nd in self.plan.nodes if self.bootup_s[nd.index] <= t0])
            time.sleep(0.005)
        missing = [nd for nd in self.plan.nodes if self.bootup_s[nd.index] <= t0]
        raise self._fail(missing[0], "boot", f"no boot-up message within {timeout_s:g} s after NMT reset "
                         "([bus] boot_timeout_s)"
                         + (f" (also silent: nodes {[n.node_id for n in missing[1:]]})" if len(missing) > 1 else ""))

    def start(self, timeout_s: float = 1.0) -> None:
        """NMT start (operational) and wait for each drive's heartbeat to report OPERATIONAL."""
        t0 = time.monotonic()
        for nd in self.plan.nodes:
            self.nodes[nd.index].nmt.send_command(0x01)
        if self.bus_cfg.heartbeat_ms <= 0:
            return
        deadline = t0 + max(timeout_s, 3 * self.bus_cfg.heartbeat_ms * 1e-3)
        while time.monotonic() < deadline:
            if all(self.nmt_states[i] == 5 and self.last_heartbeat_s[i] > t0 for i in range(len(self.nodes))):
                return
            time.sleep(0.005)
        bad = [nd for nd in self.plan.nodes
               if not (self.nmt_states[nd.index] == 5 and self.last_heartbeat_s[nd.index] > t0)]
        raise self._fail(bad[0], "NMT start", "no heartbeat reporting OPERATIONAL "
                         f"(last NMT state {self.nmt_states[bad[0].index]})")

    def pre_operational(self) -> None:
        """NMT enter pre-operational (PDOs off) for every drive."""
        for node in self.nodes:
            node.nmt.send_command(0x80)

    def start_heartbeat(self) -> None:
        """Produce the master heartbeat (0x700 + 0x7F, state operational) on every bus."""
        self.stop_heartbeat()
        self._heartbeat_wanted = True
        if self.bus_cfg.heartbeat_ms > 0:
            for net in self.networks:
                self._hb_tasks.append(net.send_periodic(0x700 + MASTER_NODE_ID, [5],
                                                        self.bus_cfg.heartbeat_ms * 1e-3))

    def stop_heartbeat(self) -> None:
        """Stop producing the master heartbeat (the drives will fault 0x8130 once enabled)."""
        for t in self._hb_tasks:
            t.stop()
        self._hb_tasks = []
        self._heartbeat_wanted = False

    # -- configuration -------------------------------------------------------------------------
    def configure(self) -> None:
        """SDO configuration of every drive (pre-operational), nothing enabled: identity check
        (0x1000/0x1018/0x6502), 0x60C2 in a format the drives take, units (factor group),
        heartbeats, limits, PDOs (RPDO event timers = ``[bus] comm_loss_timeout_s``), reactions
        (0x1006, 0x6007, 0x1029, 0x605A, 0x605C, 0x605E, read back), mode 8. Results in ``report``."""
        cfg, b = self.cfg, self.bus_cfg
        self.report["identity"] = commission.check_identity(self)
        timing = commission.set_interpolation_period(self, cfg.cycle.period_s)
        self.report["timing"] = timing
        self.bus_period_s, self.sync_every = timing["bus_period_s"], timing["sync_every"]
        self.report["units"] = commission.configure_units(self)
        lo, hi = limits_inc(cfg)
        window = max(1, round(cfg.cycle.following_error_mm * b.increments_per_mm))
        for nd in self.plan.nodes:
            w = self._write_verified
            w(nd, "heartbeat producer", 0x1017, None, heartbeat_producer_ms(b.heartbeat_ms, nd.index))
            w(nd, "heartbeat consumer", 0x1016, 1, (MASTER_NODE_ID << 16) | min(0xFFFF, b.heartbeat_timeout_ms))
            w(nd, "SYNC counter", 0x1019, None, self.plan.sync_counter_overflow)
            w(nd, "software position limits", 0x607D, 1, lo[nd.index])
            w(nd, "software position limits", 0x607D, 2, hi[nd.index])
            w(nd, "following error window", 0x6065, None, window)
            self._map_pdos(nd)
            self.select_mode(nd, cia402.MODE_CSP)
        self.report["reactions"] = commission.configure_reactions(self, self.bus_period_s)
        self.start_heartbeat()

    def comm_loss_ms(self) -> int:
        """RPDO1 event timer (deadline monitoring) in ms: ``[bus] comm_loss_timeout_s``, at least
        3 bus periods."""
        t = float(getattr(self.bus_cfg, "comm_loss_timeout_s", 0.02))
        return max(1, int(round(max(t, 3 * self.bus_period_s) * 1e3)))

    def _map_pdos(self, nd: NodePlan) -> None:
        node = self.nodes[nd.index]
        step = "PDO mapping"
        rp = [(nd.rpdo1_cob_id, 1, nd.rpdo1_map, None, self.comm_loss_ms(), None)]
        if nd.rpdo2_cob_id is not None:
            rp.append((nd.rpdo2_cob_id, 255, nd.rpdo2_map, None, None, None))
        tp = [(nd.tpdo1_cob_id, nd.tpdo1_trans_type, nd.tpdo1_map, None, None,
               nd.tpdo1_sync_start if self.plan.sync_counter_overflow else None),
              (nd.tpdo2_cob_id, 255, nd.tpdo2_map, status_inhibit_100us(nd.index),
               status_event_timer_ms(nd.index), None)]
        tq = torquepdo.tpdo_entry(self.bus_cfg, self.plan, nd)     # TPDO3 drive torque (drivers/torquepdo.py)
        if tq is not None:
            tp.append(tq)
        try:
            for maps, wanted, default_base in ((node.rpdo, rp, 0x200), (node.tpdo, tp, 0x180)):
                for n in range(1, 5):
                    m = maps[n]
                    m.clear()
                    if n <= len(wanted):
                        cob, trans, mapping, inhibit, event, start = wanted[n - 1]
                        m.cob_id = cob
                        m.trans_type = trans
                        m.inhibit_time = inhibit
                        m.event_timer = event
                        m.sync_start_value = start
                        for index, sub, bits in mapping:
                            m.add_variable(index, sub, bits)
                        m.enabled = True
                    else:
                        m.cob_id = default_base + 0x100 * (n - 1) + nd.node_id
                        m.enabled = False
                    m.save()
            self._verify_pdos(nd, rp, tp)
        except SdoAbortedError as exc:
            raise self._fail(nd, step, "drive refused the PDO configuration", exc) from exc
        except SdoCommunicationError as exc:
            raise self._fail(nd, step, "no SDO answer", exc) from exc

    def _write_verified(self, nd: NodePlan, step: str, index: int, sub: int | None, value: int) -> None:
        """SDO write, then read back: BusError naming the object when the drive holds another value."""
        self._write(nd, step, index, sub, value)
        back = self._read(nd, f"{step} read-back", index, sub)
        if back != value:
            raise self._fail(nd, step, f"0x{index:04X}:{sub or 0:02X} written {value}, read back {back}")

    def _verify_pdos(self, nd: NodePlan, rp: list, tp: list) -> None:
        """Read back every PDO communication and mapping parameter written by :meth:`_map_pdos`."""
        r = self._read
        for comm, mapi, wanted in ((0x1400, 0x1600, rp), (0x1800, 0x1A00, tp)):
            for n in range(4):
                cob = r(nd, "PDO read-back", comm + n, 1)
                if n >= len(wanted):
                    if not cob & 0x80000000:
                        raise self._fail(nd, "PDO read-back", f"0x{comm + n:04X}:01 = 0x{cob:08X}: PDO still valid")
                    continue
                want_cob, trans, mapping, inhibit, event, start = wanted[n]
                got = {"COB-ID": cob & 0x9FFFFFFF, "transmission type": r(nd, "PDO read-back", comm + n, 2),
                       "mapping": tuple(r(nd, "PDO read-back", mapi + n, k)
                                        for k in range(1, r(nd, "PDO read-back", mapi + n, 0) + 1))}
                want = {"COB-ID": want_cob, "transmission type": trans,
                        "mapping": tuple(i << 16 | s << 8 | b for i, s, b in mapping)}
                for sub, name, v in ((3, "inhibit time", inhibit), (5, "event timer", event), (6, "SYNC start", start)):
                    if v is not None:
                        got[name], want[name] = r(nd, "PDO read-back", comm + n, sub), v
                if got != want:
                    bad = {k: (want[k], got[k]) for k in want if want[k] != got[k]}
                    raise self._fail(nd, "PDO read-back", f"0x{comm + n:04X}/0x{mapi + n:04X} (expected, found): {bad}")

    def select_mode(self, nd: NodePlan, mode: int, timeout_s: float = 0.5) -> None:
        """Write 0x6060 and wait until 0x6061 shows it."""
        self._write(nd, f"mode of operation {mode}", 0x6060, None, mode)
        deadline = time.monotonic() + timeout_s
        while True:
            shown = self._read(nd, "mode of operation display", 0x6061)
            if shown == mode:
                return
            if time.monotonic() > deadline:
                raise self._fail(nd, "mode of operation", f"0x6061 shows {shown}, not {mode}, after {timeout_s:g} s")
            time.sleep(0.01)

    # -- CiA 402 ------------------------------------------------------------------------------
    def statuswords(self) -> list[int]:
        return [self._read(nd, "statusword", 0x6041) for nd in self.plan.nodes]

    def positions_inc(self) -> list[int]:
        return [self._read(nd, "position actual", 0x6064) for nd in self.plan.nodes]

    def walk(self, wanted: int, timeout_s: float = 1.0, reset_faults: bool = False) -> None:
        """Walk every drive through the CiA 402 state machine to ``wanted`` (SDO 0x6040 / 0x6041).

        Before enabling, the target position is set to the actual one. A drive in Fault is an
        error unless ``reset_faults``. Raises :class:`BusError` naming node, state and transition.
        """
        name = cia402.state_name(wanted)
        pending = list(self.plan.nodes)
        last_t = {nd.index: 0 for nd in pending}
        deadline = time.monotonic() + timeout_s
        while pending:
            still = []
            for nd in pending:
                sw = self._read(nd, f"walk to {name!r}", 0x6041)
                state = cia402.state_from_status(sw)
                if state == wanted:
                    continue
                still.append(nd)
                if state == cia402.FAULT and not reset_faults and wanted != cia402.SWITCH_ON_DISABLED:
                    codes = [cia402.emcy_text(c, r) for s, c, r, _, _ in self.emcy_log if s == nd.index]
                    raise self._fail(nd, f"walk to {name!r}", "drive is in Fault"
                                     + (f" (last EMCY {codes[-1]})" if codes else "") + "; reset the fault first")
                if wanted == cia402.OPERATION_ENABLED and not sw & cia402.SW_REMOTE:
                    raise self._fail(nd, f"walk to {name!r}", f"statusword 0x{sw:04X} has bit 9 (remote) clear: "
                                     "the drive is in local mode and ignores the controlword")
                cw, t = cia402.controlword_towards(state, wanted, self._cw[nd.index])
                if t == 4 or t == 16:
                    pos = self._read(nd, "hold position before enable", 0x6064)
                    self._write(nd, "hold position before enable", 0x607A, None, pos)
                if cw != self._cw[nd.index] or t:
                    self._write(nd, f"transition {t} towards {name!r}", 0x6040, None, cw)
                    self._cw[nd.index] = cw
                    last_t[nd.index] = t
            pending = still
            if not pending:
                return
            if time.monotonic() > deadline:
                nd = pending[0]
                sw = self._read(nd, f"walk to {name!r}", 0x6041)
                raise self._fail(nd, f"walk to {name!r}",
                                 f"still {cia402.status_text(sw)} after {timeout_s:g} s: the drive did not "
                                 f"follow transition {last_t[nd.index]} (controlword 0x{self._cw[nd.index]:04X})"
                                 + (f"; also not there: nodes {[n.node_id for n in pending[1:]]}" if len(pending) > 1 else ""))
            time.sleep(0.005)

    def enable(self, timeout_s: float = 1.0, reset_faults: bool = False) -> None:
        """All drives to Operation enabled (holding their actual positions)."""
        self.walk(cia402.OPERATION_ENABLED, timeout_s, reset_faults)

    def disable(self, timeout_s: float = 1.0) -> None:
        """All drives to Switch on disabled (power stage off)."""
        self.walk(cia402.SWITCH_ON_DISABLED, timeout_s, reset_faults=False)

    def quick_stop(self) -> None:
        """Quick stop command to every drive (no waiting)."""
        for nd in self.plan.nodes:
            self._write(nd, "quick stop", 0x6040, None, cia402.CW_QUICK_STOP)
            self._cw[nd.index] = cia402.CW_QUICK_STOP

    def fault_reset(self, timeout_s: float = 1.0) -> None:
        """Rising edge of controlword bit 7 on drives in Fault; wait for Switch on disabled."""
        for nd in self.plan.nodes:
            if cia402.state_from_status(self._read(nd, "fault reset", 0x6041)) == cia402.FAULT:
                self._write(nd, "fault reset", 0x6040, None, 0)
                self._write(nd, "fault reset", 0x6040, None, cia402.CW_FAULT_RESET)
                self._cw[nd.index] = cia402.CW_FAULT_RESET
        self.walk(cia402.SWITCH_ON_DISABLED, timeout_s)

    def bring_up(self, enable: bool = True, timeout_s: float = 2.0) -> None:
        """boot (``[bus] boot_timeout_s``) -> configure -> NMT start -> (enable). Raises BusError
        naming node and step, always before any drive is enabled when a check fails."""
        self.boot()
        self.configure()
        self.start(timeout_s)
        if enable:
            self.enable(timeout_s)

    def emcy_texts(self) -> list[str]:
        return [f"node {self.plan.nodes[i].node_id} (strut {i + 1}): {cia402.emcy_text(c, r, d)}"
                for i, c, r, d, _ in self.emcy_log]
