"""In-process stand-in for the bus codec: six drives as plain-float models.

Used by the loop's unit tests (no bus, no second process) and nothing else; the
product path is :mod:`hexacnc.daemon.busio` with ``drivers.simdrive``.  Each drive
follows its target with a one-cycle transport delay and a first-order lag
(``tau_s``) under a velocity limit, walks the CiA 402 states by controlword, and
can be told to fail: ``hb_lost``, ``emcy(code)``, ``stuck`` (stops following).
"""
from __future__ import annotations

from drivers import cia402
from drivers.cia402 import SW_DRIVE_FOLLOWS, SW_REMOTE

#: statuswords of the model (CiA 402 states, remote bit 9 set; CSP bit 12 "follows" when enabled)
SW_SWITCH_ON_DISABLED = 0x0040 | SW_REMOTE
SW_READY = 0x0021 | SW_REMOTE
SW_SWITCHED_ON = 0x0023 | SW_REMOTE
SW_OP_ENABLED = 0x0027 | SW_REMOTE | SW_DRIVE_FOLLOWS
SW_FAULT_BIT = 0x0008


class SimIO:
    def __init__(self, cfg, period_s: float | None = None, tau_s: float = 0.002, start_pos=None):
        self.dt = float(period_s or cfg.cycle.period_s)
        self.tau_s = tau_s
        self.ipm = float(cfg.bus.increments_per_mm)
        self.vmax = [float(v) * 1.2 for v in cfg.max_velocity_mm_s]
        self.target = [0] * 6
        self.pos = [0] * 6
        self.pos_count = [0] * 6
        self.pos_sync = [0] * 6                 # SYNC each sample answers (the last send)
        self.nmt_state = [5] * 6                # NMT operational
        self.sends = 0
        self.statusword = [SW_SWITCH_ON_DISABLED] * 6
        self.hb_ns = [0] * 6
        self.emcy_count = [0] * 6
        self.emcy_code = [0] * 6
        self.bootups = 0
        self.encoder_errors = 0
        self.bus_load = 0.0
        self.frames_tx = 0
        self._x = [0.0] * 6                     # drive positions, mm of reading
        if start_pos is not None:
            for i in range(6):
                self._x[i] = float(start_pos[i])
        for i in range(6):
            self.pos[i] = round(self._x[i] * self.ipm)
        self._latched = [None] * 6
        self._cw = [0] * 6
        self.hb_lost = [False] * 6
        self.stuck = [False] * 6
        self.sent = []                          # (targets) history for tests, bounded by the test

    def set_controlword(self, i: int, cw: int) -> None:
        """The drive side of the one CiA 402 state machine (:func:`drivers.cia402.drive_step`)."""
        prev, self._cw[i] = self._cw[i], cw
        state = cia402.state_from_status(self.statusword[i])
        for _ in range(2):                      # 0x0F from Ready to switch on: transitions 3 then 4
            new, num = cia402.drive_step(state, cw, prev)
            if not num:
                break
            if num in (4, 16):
                self._latched[i] = None
            state, prev = new, cw
        state = cia402.SWITCH_ON_DISABLED if state == cia402.QUICK_STOP_ACTIVE else state  # 0x605A 2: stops at once, 12
        sw = cia402.drive_statusword(state)
        self.statusword[i] = sw | SW_DRIVE_FOLLOWS if cia402.is_operation_enabled(sw) else sw

    def emcy(self, i: int, code: int) -> None:
        self.emcy_code[i] = code
        self.emcy_count[i] += 1
        if code & 0xFF00 == 0x7300:
            self.encoder_errors += 1
        self.statusword[i] = SW_FAULT_BIT | SW_REMOTE

    def poll(self, now_ns: int) -> int:
        dt = self.dt
        a = dt / (self.tau_s + dt)
        for i in range(6):
            if not self.hb_lost[i]:
                self.hb_ns[i] = now_ns
            t = self._latched[i]
            if t is not None and (self.statusword[i] & 0x6F) == 0x27 and not self.stuck[i]:
                step = (t / self.ipm - self._x[i]) * a
                lim = self.vmax[i] * dt
                step = lim if step > lim else (-lim if step < -lim else step)
                self._x[i] += step
            self.pos[i] = round(self._x[i] * self.ipm)
            self.pos_count[i] += 1
            self.pos_sync[i] = self.sends
        return 6

    def send(self) -> int:
        for i in range(6):
            self._latched[i] = self.target[i]
        self.sends += 1
        self.frames_tx += 4
        return 0

    def emcy_text(self, i: int) -> str:
        return f"simulated EMCY 0x{self.emcy_code[i]:04X}"

    def close(self) -> None:
        pass
