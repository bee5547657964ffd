"""Thermal compensation in the running daemon: probe readings in, strut offsets and spindle growth out.

Runs in the **supervisor** process (never in the hot loop's), on its own thread:

* readings come from the simulated machine (:class:`hexacnc.sim.thermalplant.ThermalPlant`,
  ``[thermal] source = "sim"``, or ``"auto"`` with ``[bus] simulate``) at ``[thermal]
  probe_rate_hz``, or from an acquisition client through the socket op ``temperatures``
  (``source = "socket"``, or ``"auto"`` on a real bus);
* every reading is validated as a whole (:func:`parse_reading`): a NaN, an out-of-range value
  (``[thermal] probe_min_C``..``probe_max_C``), a wrong count or a missing field refuses it with
  :class:`ThermalInputError` naming the field; nothing of a refused reading is used;
* the observer (:class:`hexacnc.thermal.ThermalObserver`, one Kalman filter per strut) steps at
  the probe rate on the plant time between readings (``time_s``, else the wall clock), with the
  commanded strut speeds from the hot loop's travel counters as its heat input;
* its strut offsets and the spindle growth of the spindle probe are clamped to
  ``[thermal] max_offset_mm`` and rate-limited to ``max_offset_rate_mm_s`` (wall clock), then
  written to the shared status block (``S_THERMAL_TGT``, ``S_SPINDLE_TGT``); the hot loop slews
  its applied values towards them at the same rate and only adds them in the cycle;
* no reading for ``[thermal] stale_after_s``: a warning in status, and the targets are set to the
  values the loop applies at that moment (offsets frozen) until readings resume (the observer then
  predicts across the gap from the strut travel, corrects with the new reading, and the rate limit
  takes the offsets there smoothly).  The spindle probe goes stale on its own in the same way.

Units: degC, mm, s.  Probe layout (the ``temperatures`` op and ``status["thermal"]``):
per strut the ``[thermal] probes`` segments (segment ``j`` of ``[thermal] segments`` sits at
``(j + 0.5) / segments`` of the strut length from the base joint), one ambient (air) and one frame
sensor, one spindle-housing probe.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque

import numpy as np

from ..kinematics import Hexapod
from ..pose import matrix_from_euler
from . import shm as S
from .thermalin import ThermalInputError, parse_reading, resolve_source

log = logging.getLogger("hexacnc.thermal")

#: the thermal thread's tick (wall s): sim sampling, observer, stale check
TICK_S = 0.05
#: a gap between readings longer than this (plant s) re-initialises the estimate from the probes
MAX_GAP_S = 86400.0
#: readings closer than this (plant s) are shown but not observed separately
MIN_STEP_S = 1e-3
#: observer step quantisation (1 %): one discretisation per step size, cached
_LOG_Q = math.log(1.01)


class ThermalSupervisor:
    """Observer, limits and (with ``source == "sim"``) the simulated plant; see the module docstring.

    ``sample_travel()`` is called by the feeder thread (every few ms) to integrate the actual strut
    travel for the simulated plant; ``push()`` takes a reading; ``status(s)`` builds the status map
    from a status-block copy ``s``.
    """

    def __init__(self, cfg, sh: S.Shared, state_fn=None):
        self.cfg = cfg
        self.tc = tc = cfg.thermal
        self.sh = sh
        self.source = resolve_source(cfg)
        self.state_fn = state_fn or (lambda: "idle")
        self.lock = threading.Lock()
        self.stop_ev = threading.Event()
        self.thread: threading.Thread | None = None
        self.hx = Hexapod(cfg)
        self.vmax = np.asarray(cfg.max_velocity_mm_s, dtype=float)
        self.rate = float(tc.probe_rate_hz)
        self.scale = float(tc.sim_time_scale) if self.source == "sim" else 1.0
        self.observer = None
        self._obs_cache: dict = {}
        if self.source != "none":
            self.observer = self._observer_for_init(self.scale / self.rate)
        self.plant = None
        if self.source == "sim":
            from ..sim.thermalplant import thermal_plant
            self.plant = thermal_plant(cfg)
        # readings
        self.pending: deque = deque(maxlen=256)  #: accepted readings not yet observed (oldest dropped)
        self._busy = False                       #: a reading is being observed
        self.last: dict | None = None           #: last accepted reading
        self.last_wall = None                   #: monotonic s of the last accepted reading
        self.spindle_wall = None
        self.readings = 0
        self.rejected = 0
        self.last_error: str | None = None
        self.stale = False
        self.spindle_stale = False
        self.warning: str | None = None
        # observer time line
        self.obs_t: float | None = None         #: plant time of the estimate
        self.obs_carry = 0.0
        self.obs_travel = None
        self.obs_wall = None
        self.offsets_est = np.zeros(6)
        self.spindle_est = 0.0
        self.shaft_C: float | None = None       #: estimated spindle shaft temperature (degC)
        self.shaft_t: float | None = None
        # targets written to the shared memory
        self.tgt = np.zeros(6)
        self.sp_tgt = 0.0
        self.tgt_wall = None
        # simulated plant: actual travel from the feedback
        self._act_last: list | None = None
        self.act_travel = [0.0] * 6
        self.sim_wall = None
        self.sim_travel = None
        self.drift: dict | None = None
        self.peak_um = {"compensated": 0.0, "uncompensated": 0.0}

    # ------------------------------------------------------------------ life cycle
    def start(self) -> "ThermalSupervisor":
        if self.source != "none" and self.thread is None:
            self.thread = threading.Thread(target=self._run, name="hexacnc-thermal", daemon=True)
            self.thread.start()
        return self

    def close(self) -> None:
        self.stop_ev.set()
        if self.thread is not None:
            self.thread.join(2.0)

    # ------------------------------------------------------------------ inputs
    def sample_travel(self) -> None:
        """Feeder thread: integrate |change| of the measured strut lengths (simulated plant input)."""
        if self.plant is None:
            return
        s = self.sh.s
        a = [s[S.S_STRUT_ACT + i] for i in range(6)]
        last = self._act_last
        if last is not None:
            tr = self.act_travel
            for i in range(6):
                d = a[i] - last[i]
                if d == d:
                    tr[i] += d if d >= 0.0 else -d
        self._act_last = a

    def push(self, fields: dict, origin: str = "socket") -> dict:
        """Take one reading (validated as a whole; raises :class:`ThermalInputError`)."""
        if self.source == "none":
            raise ThermalInputError("refused", "op", "thermal compensation is off ([thermal] enabled = false or "
                                                     "source = \"none\")")
        if origin != "sim" and self.source == "sim":
            raise ThermalInputError("refused", "op", "the simulated machine feeds the probes ([thermal] source = "
                                                     "\"sim\"); set source = \"socket\" to push readings")
        try:
            r = parse_reading(fields, self.tc)
        except ThermalInputError as exc:
            with self.lock:
                self.rejected += 1
                self.last_error = f"{exc.field}: {exc}"
            raise
        now = time.monotonic()
        with self.lock:
            prev = self.pending[-1] if self.pending else self.last
            prev_t = None if prev is None else prev["time_s"]
            if r["time_s"] is not None and prev_t is not None and r["time_s"] <= prev_t:
                self.rejected += 1
                self.last_error = "time_s: not after the previous reading"
                raise ThermalInputError("bad_value", "time_s", f"time_s = {r['time_s']:g} s is not after the previous "
                                                               f"reading's {prev_t:g} s")
            if r["time_s"] is None:
                r["time_s"] = self._wall_time_s(now)
            r["wall"] = now
            r["travel"] = self._travel_cmd()      # the heat input's window ends with the reading
            if origin == "sim":
                r["truth_growth_mm"] = fields.get("truth_growth_mm")
            self.pending.append(r)
            self.readings += 1
        return {"accepted": True, "readings": self.readings}

    def _wall_time_s(self, now: float) -> float:
        """Plant time for a reading without time_s: the previous one's plus the wall time since."""
        ref = self.pending[-1] if self.pending else self.last
        if ref is None:
            return 0.0
        return ref["time_s"] + (now - ref["wall"])

    # ------------------------------------------------------------------ thread
    def _run(self) -> None:
        period = 1.0 / self.rate
        next_sim = time.monotonic() + period
        while not self.stop_ev.wait(TICK_S):
            try:
                now = time.monotonic()
                if self.plant is not None and now >= next_sim:
                    next_sim = max(next_sim + period, now - period)
                    self._sim_step(now)
                while True:
                    with self.lock:
                        r = self.pending.popleft() if self.pending else None
                        self._busy = r is not None
                    if r is None:
                        break
                    try:
                        self._observe(r)
                    finally:
                        self._busy = False
                with self.lock:
                    if self.last is not None:
                        self._write_targets(time.monotonic())
                self._check_stale(time.monotonic())
            except Exception:
                log.exception("thermal thread error (offsets held)")

    def _sim_step(self, now: float) -> None:
        tr = list(self.act_travel)
        if self.sim_wall is None:
            self.sim_wall, self.sim_travel = now, tr
            return
        dt_wall = now - self.sim_wall
        speed = np.minimum(np.abs(np.array(tr) - np.array(self.sim_travel)) / max(dt_wall, 1e-3), self.vmax)
        self.sim_wall, self.sim_travel = now, tr
        self.plant.step(dt_wall * self.scale, speed, self.state_fn() == "running")
        self.push({**self.plant.readings(), "truth_growth_mm": self.plant.growth_mm().tolist()}, origin="sim")

    def _travel_cmd(self) -> np.ndarray:
        s = self.sh.s
        return np.array([s[S.S_TRAVEL + i] for i in range(6)])

    def _observer_for_init(self, dt_s: float):
        from ..thermal import thermal_observer
        key = round(math.log(dt_s) / _LOG_Q)
        ob = self._obs_cache[key] = thermal_observer(self.cfg, math.exp(key * _LOG_Q))
        return ob

    def _observer_for(self, dt_s: float):
        """Observer discretised for a step of ``dt_s`` (quantised to 1 % steps, cached), holding the
        current estimate."""
        key = round(math.log(dt_s) / _LOG_Q)
        ob = self._obs_cache.get(key)
        if ob is None:
            from ..thermal import thermal_observer
            if len(self._obs_cache) >= 32:
                self._obs_cache.pop(next(iter(self._obs_cache)))
            ob = self._obs_cache[key] = thermal_observer(self.cfg, math.exp(key * _LOG_Q))
        if ob is not self.observer:
            ob.T_est = self.observer.T_est.copy()
            self.observer = ob
        return ob

    def _observe(self, r: dict) -> None:
        """One reading: predict over the plant time since the last one (exact ZOH with the mean
        commanded strut speed), correct with the probes."""
        obs = self.observer
        travel = r["travel"]
        if self.obs_t is None or r["time_s"] - self.obs_t > MAX_GAP_S:
            # first reading (or after a very long gap): the field from the probes, linear along
            # each strut through its probes (constant beyond them)
            x = np.arange(obs.n) + 0.5
            xp = np.array(obs.probes, dtype=float) + 0.5
            order = np.argsort(xp)
            T0 = np.stack([np.interp(x, xp[order], r["struts"][i][order]) for i in range(6)])
            obs.reset(T0)
            self.obs_t, self.obs_carry = r["time_s"], 0.0
        else:
            dt = r["time_s"] - self.obs_t + self.obs_carry
            self.obs_t = r["time_s"]
            if dt < MIN_STEP_S:
                self.obs_carry = dt        # too soon: the reading is shown, the next step covers the time
            else:
                dt_wall = max(1e-3, r["wall"] - self.obs_wall)
                # mean commanded speed; never above the strut limit (guards against a counter jump)
                speed = np.minimum(np.abs(travel - self.obs_travel) / dt_wall, self.vmax)
                obs = self._observer_for(dt)
                self.obs_carry = dt - obs.dt_s
                obs.update(speed, r["ambient"], r["frame"], r["struts"])
        self.obs_travel, self.obs_wall = travel, r["wall"]
        off = np.asarray(obs.offsets_mm, dtype=float)
        with self.lock:
            if np.all(np.isfinite(off)):
                self.offsets_est = off.copy()
            if r["spindle"] is not None:
                from ..thermal import spindle_growth_mm
                # the shaft that grows lags the housing probe: first order over the plant time between
                # readings ([spindle] probe_lag_s; 0: the probe's temperature as it is)
                tau = self.cfg.spindle.probe_lag_s
                if self.shaft_C is None or tau <= 0.0 or self.shaft_t is None:
                    self.shaft_C = r["spindle"]
                else:
                    a = math.exp(-max(0.0, r["time_s"] - self.shaft_t) / tau)
                    self.shaft_C = a * self.shaft_C + (1.0 - a) * r["spindle"]
                self.shaft_t = r["time_s"]
                self.spindle_est = spindle_growth_mm(self.shaft_C, self.cfg)
                self.spindle_wall = r["wall"]
                self.spindle_stale = False
            self.last = r
            self.last_wall = r["wall"]
            if self.stale:
                log.warning("thermal probes back after a gap: offsets follow the estimate again")
            self.stale = False
            self._write_targets(time.monotonic())
        if self.plant is not None:
            self._measure_drift()

    def _write_targets(self, now: float) -> None:
        """Move the targets towards the clamped estimate by at most the rate limit times the wall time
        since the last call (called every tick, so they ramp), publish them (caller holds the lock).
        Stale probes: those targets stay where they were frozen."""
        tc = self.tc
        lim = tc.max_offset_mm
        dt = 0.0 if self.tgt_wall is None else max(0.0, now - self.tgt_wall)
        if self.tgt_wall is None:       # first targets: start from what the loop applies
            s = self.sh.s
            self.tgt = np.array([s[S.S_THERMAL_APP + i] for i in range(6)])
            self.sp_tgt = s[S.S_SPINDLE_APP]
        step = tc.max_offset_rate_mm_s * dt
        if not self.stale:
            want = np.clip(self.offsets_est, -lim, lim)
            self.tgt = self.tgt + np.clip(want - self.tgt, -step, step)
        if not self.spindle_stale and self.spindle_wall is not None:
            sp = min(lim, max(-lim, self.spindle_est))
            self.sp_tgt = self.sp_tgt + min(step, max(-step, sp - self.sp_tgt))
        self.tgt_wall = now
        s = self.sh.s
        if np.all(np.isfinite(self.tgt)) and math.isfinite(self.sp_tgt):
            for i in range(6):
                s[S.S_THERMAL_TGT + i] = float(self.tgt[i])
            s[S.S_SPINDLE_TGT] = float(self.sp_tgt)

    def _check_stale(self, now: float) -> None:
        lim = self.tc.stale_after_s
        with self.lock:
            s = self.sh.s
            if self.last_wall is not None and not self.stale and now - self.last_wall > lim:
                self.stale = True
                self.tgt = np.array([s[S.S_THERMAL_APP + i] for i in range(6)])
                for i in range(6):
                    s[S.S_THERMAL_TGT + i] = float(self.tgt[i])
                log.warning("thermal probes stale (no reading for %.1f s): strut offsets frozen", now - self.last_wall)
            if self.stale:
                self.tgt_wall = now       # resuming: the rate limit counts from here, no jump
            if self.spindle_wall is not None and not self.spindle_stale and now - self.spindle_wall > lim:
                self.spindle_stale = True
                self.sp_tgt = s[S.S_SPINDLE_APP]
                s[S.S_SPINDLE_TGT] = float(self.sp_tgt)
                log.warning("spindle probe stale: spindle growth frozen")
            if self.stale or self.spindle_stale:
                what = "strut/frame/air probes" if self.stale else "spindle probe"
                since = self.last_wall if self.stale else self.spindle_wall
                self.warning = (f"{what} stale: no reading for {now - since:.1f} s "
                                f"([thermal] stale_after_s = {lim:g}); offsets frozen")
            else:
                self.warning = None

    # ------------------------------------------------------------------ drift (simulated plant)
    def _measure_drift(self) -> None:
        """Tool-tip error the thermal growth leaves at the commanded pose, with and without the
        applied compensation (uses the simulated plant's true growth)."""
        hs = self.sh.read_status()
        s = hs[1]
        X = np.array(s[S.S_POSE_CMD:S.S_POSE_CMD + 6])
        if not np.all(np.isfinite(X)):
            return
        pose = np.r_[X[:3], np.degrees(X[3:])]
        R = matrix_from_euler(*X[3:])
        tip = np.asarray(self.cfg.tool.tip_platform_mm, dtype=float)
        axis = np.asarray(self.cfg.tool.axis_platform, dtype=float)
        g = self.plant.growth_mm()
        g_sp = self.plant.spindle_growth_mm()
        th = np.array(s[S.S_THERMAL_APP:S.S_THERMAL_APP + 6])
        sp = s[S.S_SPINDLE_APP]
        want = X[:3] + R @ tip
        out = {}
        for name, th_i, sp_i in (("uncompensated", np.zeros(6), 0.0), ("compensated", th, sp)):
            p = pose.copy()
            p[:3] -= sp_i * (R @ axis)
            L = self.hx.lengths(p) - th_i + g
            fk = self.hx.forward(L, pose)
            if not fk.ok:
                return
            Xa = np.r_[fk.pose[:3], np.radians(fk.pose[3:])]
            Ra = matrix_from_euler(*Xa[3:])
            d = (Xa[:3] + Ra @ (tip + g_sp * axis) - want) * 1e3
            out[name] = d.tolist()
            self.peak_um[name] = max(self.peak_um[name], abs(float(d[2])))
        self.drift = out

    # ------------------------------------------------------------------ status
    def status(self, s: list, h: list | None = None) -> dict:
        """The status map from a status-block copy ``s`` (and header ``h`` of the same read)."""
        now = time.monotonic()
        with self.lock:
            last = self.last
            obs = self.observer
            out = {
                "source": self.source,
                "state": ("off" if self.source == "none" else "waiting" if last is None
                          else "stale" if self.stale else "ok"),
                "warning": self.warning,
                "probe_segments": list(self.tc.probes),
                "probe_rate_hz": self.rate,
                "time_scale": self.scale,
                "strut_mean_C_est": (obs.T_est.mean(axis=1).tolist() if obs is not None and last is not None
                                     else [math.nan] * 6),
                "strut_offsets_est_mm": self.offsets_est.tolist(),
                "strut_offsets_target_mm": self.tgt.tolist(),
                "offsets_mm": s[S.S_THERMAL_APP:S.S_THERMAL_APP + 6],
                "spindle_growth_mm": s[S.S_SPINDLE_APP],
                "spindle_growth_est_mm": self.spindle_est,
                "spindle_shaft_C_est": self.shaft_C,
                "probes_C": None if last is None else {"struts": last["struts"].tolist(), "ambient": last["ambient"],
                                                       "frame": last["frame"], "spindle": last["spindle"]},
                "probes_age_s": None if self.last_wall is None else now - self.last_wall,
                "spindle_age_s": None if self.spindle_wall is None else now - self.spindle_wall,
                "time_s": None if last is None else last["time_s"],
                "readings": self.readings,
                "pending": len(self.pending) + (1 if self._busy else 0),
                "rejected": self.rejected,
                "loop_cycles": None if h is None else h[S.H_CYCLES],
                "last_error": self.last_error,
                "max_offset_mm": self.tc.max_offset_mm,
                "max_offset_rate_mm_s": self.tc.max_offset_rate_mm_s,
            }
            if self.plant is not None:
                out["sim"] = {**self.plant.truth(), "drift_um": self.drift, "peak_drift_z_um": dict(self.peak_um),
                              "strut_growth_at_reading_mm": None if last is None else last.get("truth_growth_mm")}
        return out


def thermal_supervisor(cfg, sh: S.Shared, state_fn=None) -> ThermalSupervisor:
    """Factory: the supervisor side of the thermal compensation."""
    return ThermalSupervisor(cfg, sh, state_fn)
