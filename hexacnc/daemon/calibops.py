"""Socket ops of the calibration cycle: ``measure``, ``measurement``, ``reload``.

* ``measurement`` {instrument, t_s, values: {x..c subset}, target?}: a reading of a real (or any)
  instrument with its time stamp (Unix time, s).  The daemon pairs it with the drive readings it
  sampled at that time (:class:`ReadingHistory`, 100 Hz, last 60 s) and keeps it (last 256) for
  ``measure``.  Refused: unknown coordinate, non-finite value, a time stamp outside the history
  (``late``) or in the future.
* ``measure`` {instrument, wait_s?, after_t_s?}: one reading paired with drive readings.  With a
  true machine (``hexacnc run --truth``) a simulated instrument (tracker, probe, indicator) reads
  the true pose at the current readings; for another name, or without a truth, the first ``measurement`` of that instrument time-stamped after
  ``after_t_s`` (default: now) is returned, waiting up to ``wait_s`` (default 5, max 60) -
  missing: error ``refused`` with "no reading".
* ``reload`` {config}: load a machine description while idle: validated first (the loader's
  error is the reply), refused while anything moves, then a controlled stop, drives disabled,
  the hot loop and drives restarted with the new description, drives enabled.

Registered on :class:`hexacnc.daemon.server.SocketServer` by :func:`register`.
"""
from __future__ import annotations

import bisect
import logging
import math
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from ..errors import HexacncError
from . import protocol as P
from . import shm as S

log = logging.getLogger("hexacnc.calibops")

HISTORY_S = 60.0
SAMPLE_S = 0.01
DIRECTION_DEADBAND_MM = 0.0005
MAX_KEPT = 256
MAX_WAIT_S = 60.0
COORDS = ("x", "y", "z", "a", "b", "c")

OPS = {
    "measure": {"instrument": ((str,), True), "wait_s": ((int, float), False), "after_t_s": ((int, float), False)},
    "measurement": {"instrument": ((str,), True), "t_s": ((int, float), True), "values": ((dict,), True),
                    "target": ((str,), False)},
    "reload": {"config": ((str,), True)},
}


def last_direction(d_prev: np.ndarray, c0, T0, v0, c1, T1, deadband_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Each strut's last direction of motion (+1 extending) from two looks at its command ``c`` and
    its cumulative commanded travel ``T`` (the hot loop adds every cycle's step, so nothing between
    the looks is lost), ``v0`` the commanded velocity at the first look.  Travel beyond the net move
    is a reversal in between: the first leg continues ``v0`` (else the last direction), the last leg
    goes back.  Returns ``(direction, decided)``: ``decided`` where the looks moved it past the dead
    band (the caller keeps its first look for the others, so slow moves add up)."""
    net = np.asarray(c1, dtype=float) - np.asarray(c0, dtype=float)
    dT = np.asarray(T1, dtype=float) - np.asarray(T0, dtype=float)
    out = np.array(d_prev, dtype=float)
    decided = np.zeros(len(out), dtype=bool)
    for i in range(len(out)):
        if dT[i] - abs(net[i]) > deadband_mm:             # went one way, then back
            f = float(np.sign(v0[i])) if abs(v0[i]) > 1e-9 else out[i]
            last_leg = 0.5 * (dT[i] - f * net[i])
            out[i] = -f if last_leg > deadband_mm else f
            decided[i] = True
        elif abs(net[i]) > deadband_mm:
            out[i] = float(np.sign(net[i]))
            decided[i] = True
    return out, decided


class ReadingHistory(threading.Thread):
    """Samples the drive readings (mm) every 10 ms; each strut's last direction of motion (from the
    hot loop's commands and cumulative commanded travel, :func:`last_direction`: a look missed
    under load, a reversal between two looks included, does not flip the simulated backlash)."""

    def __init__(self, daemon: Any):
        super().__init__(name="hexacnc-readings", daemon=True)
        self.daemon_ = daemon
        self.off = np.asarray(daemon.cfg.strut_offset_mm, dtype=float)
        n = int(HISTORY_S / SAMPLE_S)
        self.t: deque = deque(maxlen=n)
        self.q: deque = deque(maxlen=n)
        self.direction = np.ones(6)
        self._ref: tuple | None = None                 #: command, travel, velocity at the last decision
        self.lock = threading.Lock()
        self.stop_event = threading.Event()
        self.kept: deque = deque(maxlen=MAX_KEPT)      #: paired external measurements
        self.cv = threading.Condition(self.lock)

    def current(self) -> tuple[float, np.ndarray]:
        h, s = self.daemon_.sh.read_status()
        return time.time(), np.asarray(s[S.S_STRUT_ACT:S.S_STRUT_ACT + 6], dtype=float) - self.off

    def run(self) -> None:
        while not self.stop_event.wait(SAMPLE_S):
            if self.daemon_.sh is None or self.daemon_.closed:
                break
            h, s = self.daemon_.sh.read_status()
            t = time.time()
            q = np.asarray(s[S.S_STRUT_ACT:S.S_STRUT_ACT + 6], dtype=float) - self.off
            look = (np.asarray(s[S.S_STRUT_CMD:S.S_STRUT_CMD + 6], dtype=float),
                    np.asarray(s[S.S_TRAVEL:S.S_TRAVEL + 6], dtype=float),
                    np.asarray(s[S.S_STRUT_VEL:S.S_STRUT_VEL + 6], dtype=float))
            with self.lock:
                if self._ref is None:
                    self._ref = look
                c0, T0, v0 = self._ref
                self.direction, moved = last_direction(self.direction, c0, T0, v0, look[0], look[1],
                                                       DIRECTION_DEADBAND_MM)
                self._ref = tuple(np.where(moved, a, b) for a, b in zip(look, self._ref))
                self.t.append(t)
                self.q.append(q)

    def at(self, t_s: float) -> tuple[np.ndarray, float]:
        """Readings at time ``t_s`` (linear between samples) and the gap to the nearest sample."""
        with self.lock:
            if not self.t:
                raise ValueError("no drive readings sampled yet")
            ts = list(self.t)
            if t_s < ts[0] - SAMPLE_S:
                raise ValueError(f"late: time stamp {t_s:.3f} is {ts[-1] - t_s:.1f} s old, beyond the "
                                 f"{HISTORY_S:g} s of drive readings kept")
            if t_s > time.time() + 0.5:
                raise ValueError(f"time stamp {t_s:.3f} is in the future")
            k = bisect.bisect_left(ts, t_s)
            if k <= 0:
                return np.array(self.q[0]), abs(ts[0] - t_s)
            if k >= len(ts):
                return np.array(self.q[-1]), abs(t_s - ts[-1])
            w = (t_s - ts[k - 1]) / max(ts[k] - ts[k - 1], 1e-9)
            q = (1 - w) * np.asarray(self.q[k - 1]) + w * np.asarray(self.q[k])
            return q, min(t_s - ts[k - 1], ts[k] - t_s)


def attach(daemon: Any, truth=None, seed: int = 0) -> None:
    """Give a daemon its reading history (and, in simulation, the true machine for the instruments)."""
    hist = ReadingHistory(daemon)
    hist.start()
    daemon.calib_history = hist
    daemon.calib_truth = truth
    daemon.calib_instruments = {}
    daemon.calib_seed = seed
    daemon.calib_probe_signal = None
    if truth is not None:        # the touch probe's input (op probe): the true tool tip against the artefact
        from ..sim.probesignal import ProbeSignal, artefact_spheres_mm
        daemon.calib_probe_signal = ProbeSignal(truth, None, artefact_spheres_mm(seed))


def _check_values(values: dict) -> dict:
    if len(values) > 6:
        raise ValueError("values: at most x, y, z, a, b, c")
    out = {}
    for k, v in values.items():
        if k not in COORDS:
            raise ValueError(f"values: unknown coordinate {k!r}; known: {', '.join(COORDS)}")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise ValueError(f"values: {k} = {v!r} is not a finite number")
        out[k] = float(v)
    if not out:
        raise ValueError("values: no coordinate")
    return out


def _simulated(daemon: Any, name: str) -> dict:
    from ..sim.instruments import make_instrument
    inst = daemon.calib_instruments.get(name)
    if inst is None:
        inst = daemon.calib_instruments[name] = make_instrument(name, daemon.calib_seed)
    hist = daemon.calib_history
    t, q = hist.current()
    X = daemon.calib_truth.platform_pose_rad(q, hist.direction.copy())
    r = inst.read(X, np.asarray(daemon.cfg.tool.tip_platform_mm, dtype=float))
    return {"instrument": name, "target": r.target, "values": r.values, "sigma": r.sigma, "t_s": t,
            "q_mm": q.tolist(), "pair_gap_s": 0.0, "simulated": True}


def _external(daemon: Any, name: str, after: float, wait_s: float) -> dict | None:
    hist = daemon.calib_history
    t_end = time.monotonic() + wait_s
    with hist.cv:
        while True:
            for m in hist.kept:
                if m["instrument"] == name and m["t_s"] > after:
                    return dict(m)
            left = t_end - time.monotonic()
            if left <= 0:
                return None
            hist.cv.wait(min(left, 0.05))


def register(server_cls: Any) -> None:
    """Add the ops to the protocol table and their handlers to the server class."""
    P.OPS.update(OPS)
    from . import calibprobe
    calibprobe.register(server_cls)

    def _op_measure(self, conn, req) -> None:
        d = self.daemon
        name = req.fields["instrument"]
        if getattr(d, "calib_history", None) is None:
            self._send(conn, P.error_reply(req.id, P.REFUSED, "this daemon keeps no drive readings for measurements"))
            return
        from ..sim.instruments import INSTRUMENTS
        if getattr(d, "calib_truth", None) is not None and name in INSTRUMENTS:
            try:
                self._send(conn, P.ok_reply(req.id, **P.plain(_simulated(d, name))))
            except ValueError as exc:
                self._send(conn, P.error_reply(req.id, P.BAD_VALUE, f"instrument: {exc}"))
            return
        wait_s = min(MAX_WAIT_S, max(0.0, float(req.fields.get("wait_s", 5.0))))
        after = float(req.fields.get("after_t_s", time.time()))

        def job() -> None:
            m = _external(d, name, after, wait_s)
            out = P.ok_reply(req.id, **P.plain(m)) if m is not None else P.error_reply(
                req.id, P.REFUSED, f"no reading of instrument {name!r} within {wait_s:g} s (missing)")
            self._results.put((conn, out, "measure"))
            self._wake()
        self._wait_pool.submit(job)

    def _op_measurement(self, conn, req) -> None:
        d = self.daemon
        hist = getattr(d, "calib_history", None)
        if hist is None:
            self._send(conn, P.error_reply(req.id, P.REFUSED, "this daemon keeps no drive readings for measurements"))
            return
        try:
            vals = _check_values(req.fields["values"])
            t_s = float(req.fields["t_s"])
            q, gap = hist.at(t_s)
        except ValueError as exc:
            self._send(conn, P.error_reply(req.id, P.BAD_VALUE, str(exc)))
            return
        target = req.fields.get("target", "platform")
        if target not in ("platform", "tool"):
            self._send(conn, P.error_reply(req.id, P.BAD_VALUE, f"target {target!r}: expected platform or tool"))
            return
        m = {"instrument": req.fields["instrument"][:64], "target": target, "values": vals, "sigma": {},
             "t_s": t_s, "q_mm": q.tolist(), "pair_gap_s": gap, "simulated": False}
        with hist.cv:
            hist.kept.append(m)
            hist.cv.notify_all()
        self._send(conn, P.ok_reply(req.id, **P.plain(m)))

    def _op_reload(self, conn, req) -> None:
        from ..config import load_config
        from ..errors import ConfigError
        if not self._take_control(conn, req):
            return
        try:
            cfg = load_config(req.fields["config"])
        except ConfigError as exc:
            self._send(conn, P.error_reply(req.id, P.BAD_VALUE, f"reload refused: {exc}"))
            return
        st = self.daemon.status().get("state")
        if st != "idle":
            self._send(conn, P.error_reply(req.id, P.INVALID_STATE, f"reload refused: the machine is {st}; "
                                                                    f"reload only when idle"))
            return
        server = self

        def call() -> dict:
            return reload_daemon(server, cfg)
        self._submit_motion(conn, req, call, lambda r: P.ok_reply(req.id, **P.plain(r)))

    server_cls._op_measure = _op_measure
    server_cls._op_measurement = _op_measurement
    server_cls._op_reload = _op_reload


def reload_daemon(server: Any, cfg: Any) -> dict:
    """Controlled stop of the running daemon, then the same daemon with ``cfg`` (old one on failure)."""
    from .core import Daemon
    old = server.daemon
    t0 = getattr(old, "calib_truth", None)
    from pathlib import Path
    if t0 is not None and not cfg.simulation_truth and Path(t0.path).is_file():
        cfg = cfg.replace(simulation_truth=str(Path(t0.path).resolve()))   # the drives' probe input keeps it
    if old.status().get("state") != "idle":
        raise HexacncError("reload refused: the machine started moving")
    kw = {"io_mode": old.io_mode, "realtime": old.realtime, "log_level": old.log_level}
    truth, seed = getattr(old, "calib_truth", None), getattr(old, "calib_seed", 0)
    hist = getattr(old, "calib_history", None)
    server.calib_reloading = True
    try:
        if hist is not None:
            hist.stop_event.set()
        old.close()
        try:
            new = Daemon(cfg, **kw)
        except Exception as exc:
            log.error("reload of %s failed (%s); restarting with the previous description", cfg.path, exc)
            back = Daemon(old.cfg, **kw)
            attach(back, truth, seed)
            _serve_daemon(server, back, old.cfg)
            raise
        attach(new, truth, seed)
        _serve_daemon(server, new, cfg)
    finally:
        server.calib_reloading = False
    log.info("reloaded machine description %s (%s)", cfg.path, cfg.name)
    return {"config": cfg.path, "machine": cfg.name}


def _serve_daemon(server: Any, daemon: Any, cfg: Any) -> None:
    """Make ``daemon`` the one the server (and its operator functions) drive."""
    from .ops_operator import attach_operator
    server.daemon = daemon
    server.cfg = cfg
    if getattr(server, "operator", None) is not None:
        server.operator = attach_operator(daemon, cfg)
