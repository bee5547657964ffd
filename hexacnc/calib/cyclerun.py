"""``hexacnc calib run`` / ``verify``: a measurement plan executed on the running daemon.

Per pose: a rapid to an *approach pose* from which every strut reaches the pose extending (each
strut ``approach_mm`` shorter: ``X_pre = X - J^-1 (approach_mm * 1)``), a slow straight feed into
the pose (so the backlash of every drive is taken up in the same direction), ``settle_s`` at
rest, then one instrument reading through the daemon's ``measure`` op, which pairs it with the
drive readings.  Readings are checked: *missing* (no reading), *late* (paired more than
``max_gap_s`` away from drive readings, or taken before the machine came to rest), *outlier*
(the measured tool tip more than ``outlier_mm`` from where the controller's own model puts it, and
not confirmed by the next reading).  An uncalibrated machine may really stand that far off (a
machine at twice the synthetic tolerances: up to 3 mm), an instrument's gross error does not
repeat: a far reading that the next reading of the same pose confirms (within ``confirm_mm`` /
``confirm_deg``) is kept, flagged ``confirmed``, unless it is more than ``gross_mm`` off (no
calibration removes that: a wrong configuration).  A flagged reading is measured again (up to
``retries``); if it stays bad, the row is written with its drive readings, no measured coordinate
and the reason in ``flag``.  Rows are appended and flushed as they are
taken: an interrupted run resumes after the last written row (``resume``).

Poses the machine cannot reach (pose or approach pose outside any strut or joint limit) are
refused before anything moves.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DataError, ProtocolError
from ..kinematics import Hexapod
from ..pose import matrix_from_euler
from .measurements import atomic_write_text

COLUMNS = ("q1", "q2", "q3", "q4", "q5", "q6", "x", "y", "z", "a", "b", "c", "t_s", "flag")
POSE = ("x", "y", "z", "a", "b", "c")


@dataclass
class RunOptions:
    instrument: str = "tracker"
    approach_mm: float = 0.3          #: every strut approaches the pose extending by this much
    settle_s: float = 0.2
    feed_mm_min: float = 600.0        #: the final approach feed
    retries: int = 2
    max_gap_s: float = 0.05
    outlier_mm: float = 2.0
    outlier_deg: float = 0.5
    confirm_mm: float = 0.05          #: a far reading confirmed by the next one within this is kept
    confirm_deg: float = 0.01
    gross_mm: float = 10.0            #: never kept beyond this from the model
    progress: bool = True
    wait_s: float = 5.0
    probe_cycle: str = "touch"        #: probe: "touch" (5 G38.2 touches per sphere) or "result" (simulated result)
    probe_log: str | None = None      #: probe log (JSON lines), every contact
    reset_faults: int = 0             #: faults reset (and the pose re-measured) per run, at most
    faults_reset: int = 0


@dataclass
class PoseResult:
    index: int
    q_mm: list
    values: dict
    target: str
    t_s: float
    flag: str = ""
    tip_cmd_mm: list = field(default_factory=list)


def load_plan(path) -> np.ndarray:
    """Platform poses (N,6) mm/deg from a plan CSV (``calib plan --out``: x,y,z,a,b,c[,q1..q6])."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise DataError(f"{p}: cannot read the plan: {exc.strerror or exc}") from exc
    rows = list(csv.reader(io.StringIO(text)))
    if not rows:
        raise DataError(f"{p}: empty plan; expected a header with x,y,z,a,b,c")
    head = [h.strip() for h in rows[0]]
    miss = [c for c in POSE if c not in head]
    if miss:
        raise DataError(f"{p}: plan header lacks {', '.join(miss)} (columns of hexacnc calib plan --out)")
    idx = [head.index(c) for c in POSE]
    out = []
    for ln, r in enumerate(rows[1:], start=2):
        if not r or all(not c.strip() for c in r):
            continue
        if len(r) != len(head):
            raise DataError(f"{p}: line {ln}: {len(r)} fields, the header has {len(head)}")
        try:
            v = [float(r[i]) for i in idx]
        except ValueError:
            raise DataError(f"{p}: line {ln}: a pose value is not a number") from None
        if not all(math.isfinite(x) for x in v):
            raise DataError(f"{p}: line {ln}: a pose value is not finite")
        out.append(v)
    if not out:
        raise DataError(f"{p}: no pose rows")
    return np.asarray(out, dtype=float)


def tip_of(cfg, X_deg) -> np.ndarray:
    X = np.asarray(X_deg, dtype=float)
    R = matrix_from_euler(*np.radians(X[3:6]))
    return np.r_[X[:3] + R @ np.asarray(cfg.tool.tip_platform_mm, dtype=float), X[3:6]]


def platform_of_tip(cfg, T_deg) -> np.ndarray:
    T = np.asarray(T_deg, dtype=float)
    R = matrix_from_euler(*np.radians(T[3:6]))
    return np.r_[T[:3] - R @ np.asarray(cfg.tool.tip_platform_mm, dtype=float), T[3:6]]


def approach_pose(hx: Hexapod, X_deg, approach_mm: float) -> np.ndarray:
    """Platform pose (mm/deg) from which every strut reaches ``X_deg`` extending by ~approach_mm."""
    X = np.asarray(X_deg, dtype=float)
    J = hx.jacobian(X)                       # dL = J dX, angles in rad
    dX = np.linalg.solve(J, -approach_mm * np.ones(6))
    return np.r_[X[:3] + dX[:3], X[3:] + np.degrees(dX[3:])]


def probe_reach_offsets_mm() -> np.ndarray:
    """Tool-tip offsets (mm) the probing cycle of calib run travels around a sphere's centre."""
    from ..sim.probesignal import SPHERE_RADIUS_MM, STYLUS_RADIUS_MM
    from .probing import cycle_tip_offsets_mm
    return cycle_tip_offsets_mm(SPHERE_RADIUS_MM + STYLUS_RADIUS_MM)


def _shifted(cfg, X_deg: np.ndarray, offsets_mm: np.ndarray) -> np.ndarray:
    """Platform poses with the tool tip of ``X_deg`` moved by each offset (orientation kept)."""
    T = tip_of(cfg, X_deg)
    return np.array([platform_of_tip(cfg, np.r_[T[:3] + d, T[3:]]) for d in offsets_mm])


def retarget_probe(cfg, poses_deg: np.ndarray, spheres_mm: np.ndarray) -> np.ndarray:
    """Each pose moved so that its tool tip sits at an artefact sphere (orientation kept): the nearest
    one whose probing cycle stays within the limits and the ``[workspace]`` box (tilted poses put the
    platform up to |tip| sin(angle) beside the sphere, the touches 18.5 mm around it); the nearest
    if none does (then refused by :func:`check_reachable`)."""
    offs = probe_reach_offsets_mm()
    out = []
    for X in poses_deg:
        t = tip_of(cfg, X)
        order = np.argsort(np.linalg.norm(spheres_mm - t[None, :3], axis=1))
        cands = [platform_of_tip(cfg, np.r_[spheres_mm[k], X[3:]]) for k in order]
        pick = cands[0]
        for C in cands:
            if not unreachable(cfg, np.vstack([C[None], _shifted(cfg, C, offs)])).any():
                pick = C
                break
        out.append(pick)
    return np.asarray(out)


def outside_box(cfg, poses_deg: np.ndarray) -> np.ndarray:
    """(N,) True where a platform pose (mm/deg) is outside the ``[workspace]`` box (the planner's soft limits)."""
    from ..planner.softlimits import outside
    under, over = outside(cfg, poses_deg)
    return np.any(under | over, axis=1)


#: calib plan keeps its poses this far (mm) inside the [workspace] box: the moves between poses are straight
#: lines of the tool tip with the orientation interpolated, along which the platform bulges out by up to
#: |tip| * angle^2 / 8 (250 mm tip, 0.6 rad: 11 mm) - the planner refuses any sample outside the box
BOX_MARGIN_MM = 15.0


def near_box_edge(cfg, poses_deg: np.ndarray, margin_mm: float = BOX_MARGIN_MM) -> np.ndarray:
    """(N,) True where a platform pose's x, y or z is within ``margin_mm`` of the ``[workspace]`` box."""
    P = np.atleast_2d(np.asarray(poses_deg, dtype=float))
    lo = np.asarray(cfg.workspace_min, dtype=float)[:3] + margin_mm
    hi = np.asarray(cfg.workspace_max, dtype=float)[:3] - margin_mm
    return np.any((P[:, :3] < lo[None]) | (P[:, :3] > hi[None]), axis=1)


def unreachable(cfg, poses_deg: np.ndarray, approach_mm: float = 0.3) -> np.ndarray:
    """(N,) True where a pose or its approach pose is outside the strut/joint limits or the workspace box."""
    hx = Hexapod(cfg)
    P = np.atleast_2d(np.asarray(poses_deg, dtype=float))
    pre = np.array([approach_pose(hx, X, approach_mm) for X in P])
    return hx.batch_violations(P) | hx.batch_violations(pre) | outside_box(cfg, P) | outside_box(cfg, pre)


def check_reachable(cfg, poses_deg: np.ndarray, approach_mm: float, source: str = "plan",
                    tip_offsets_mm: np.ndarray | None = None) -> None:
    """Refuse (DataError, every bad row named) a plan with a pose or approach pose outside the limits;
    ``tip_offsets_mm``: the tool tip also travels this far around each pose (a probing cycle)."""
    bad = unreachable(cfg, poses_deg, approach_mm)
    if tip_offsets_mm is not None:
        bad = bad | np.array([unreachable(cfg, _shifted(cfg, X, tip_offsets_mm), approach_mm).any()
                              for X in np.atleast_2d(poses_deg)])
    if bad.any():
        rows = np.where(bad)[0]
        raise DataError(f"{source}: {len(rows)} pose(s) the machine cannot reach within its strut and joint limits "
                        f"and the [workspace] box (pose or its approach pose) "
                        f"(rows {', '.join(str(int(r) + 1) for r in rows[:20])}{' ...' if len(rows) > 20 else ''}); "
                        f"nothing moved")


#: the rapid between poses is cut into straight platform steps of at most this rotation (deg): a tool-tip
#: straight move with the orientation interpolated swings the platform out by |tip| * angle^2 / 8
#: (250 mm tip, 0.6 rad: 11 mm, out of the [workspace] box near its edge); per 2 deg step: 0.04 mm
ROTATION_STEP_DEG = 2.0


def transit_tips(cfg, start_deg, X_deg) -> list:
    """Tool-tip poses between platform poses ``start_deg`` (None: none) and ``X_deg`` (both excluded),
    on the straight platform line, at most ``ROTATION_STEP_DEG`` apart in orientation."""
    if start_deg is None:
        return []
    S, X = np.asarray(start_deg, dtype=float), np.asarray(X_deg, dtype=float)
    n = int(math.ceil(float(np.max(np.abs(X[3:] - S[3:]))) / ROTATION_STEP_DEG))
    return [tip_of(cfg, S + (X - S) * (k / n)) for k in range(1, n)]


def move_program(cfg, hx: Hexapod, X_deg, opts: RunOptions, start_deg=None) -> str:
    """Rapid to the approach pose (from ``start_deg``, the platform pose now, in steps along the straight
    platform line), then the slow feed into the pose."""
    pre_X = approach_pose(hx, X_deg, opts.approach_mm)
    pre = tip_of(cfg, pre_X)
    tip = tip_of(cfg, X_deg)

    def words(T):
        return " ".join(f"{a}{v:.6f}" for a, v in zip("XYZABC", T))
    rapids = transit_tips(cfg, start_deg, pre_X) + [pre]
    return ("G21 G90 G94\n" + "".join(f"G53 G0 {words(T)}\n" for T in rapids)
            + f"G53 G1 {words(tip)} F{opts.feed_mm_min:.3f}\nM2\n")


def _progress(k: int, n: int, flag: str, opts: RunOptions) -> None:
    if not opts.progress:
        return
    w = 30
    f = int(w * k / max(n, 1))
    sys.stderr.write(f"\r[{'#' * f}{'.' * (w - f)}] {k}/{n} {flag[:40]:40s}")
    if k == n:
        sys.stderr.write("\n")
    sys.stderr.flush()


def _deviation(cfg, hx: Hexapod, r: dict):
    """(mm, deg) the reading is off the model's pose at its drive readings, or None (no pose)."""
    vals = r.get("values") or {}
    fk = hx.forward_readings(np.asarray(r["q_mm"], dtype=float))
    if not fk.ok:
        return None
    model = fk.pose if r.get("target") == "platform" else tip_of(cfg, fk.pose)
    dev = max([abs(vals[k] - model[i]) for i, k in enumerate(("x", "y", "z")) if k in vals] + [0.0])
    dev_deg = max([abs(vals[k] - model[3 + i]) for i, k in enumerate(("a", "b", "c")) if k in vals] + [0.0])
    return dev, dev_deg


def _check_reading(cfg, hx: Hexapod, r: dict, t_rest: float, opts: RunOptions) -> str:
    """'' if the reading is usable, else why not (missing / late / outlier)."""
    vals = r.get("values") or {}
    if not vals:
        return "missing: no reading"
    if float(r.get("pair_gap_s", 0.0)) > opts.max_gap_s or float(r.get("t_s", 0.0)) < t_rest:
        return f"late: reading at {r.get('t_s')} paired {r.get('pair_gap_s')} s from drive readings"
    d = _deviation(cfg, hx, r)
    if d is None:
        return "outlier: the drive readings give no pose of the model"
    dev, dev_deg = d
    if dev > opts.outlier_mm or dev_deg > opts.outlier_deg:
        return f"outlier: {dev:.3f} mm / {dev_deg:.4f} deg from the model's pose"
    return ""


def _confirms(cfg, hx: Hexapod, r: dict, prev: dict | None, opts: RunOptions) -> bool:
    """A far reading ``r`` that agrees with the previous far reading ``prev`` of the same pose (the
    machine is there, not an instrument's gross error), not beyond ``gross_mm``."""
    if prev is None:
        return False
    a, b = r.get("values") or {}, prev.get("values") or {}
    if not a or set(a) != set(b):
        return False
    if max(abs(a[k] - b[k]) for k in a if k in "xyz") > opts.confirm_mm:
        return False
    if max([abs(a[k] - b[k]) for k in a if k in "abc"] + [0.0]) > opts.confirm_deg:
        return False
    d = _deviation(cfg, hx, r)
    return d is not None and d[0] <= opts.gross_mm


def measure_probe_pose(client, cfg, hx: Hexapod, X_deg, index: int, opts: RunOptions) -> PoseResult:
    """Probing cycle on the artefact sphere at the pose's tool tip, then the machine at the centre it saw."""
    from ..sim.probesignal import SPHERE_RADIUS_MM, STYLUS_RADIUS_MM
    from .probing import probe_sphere
    c_nom = tip_of(cfg, X_deg)
    abc = np.asarray(X_deg[3:], dtype=float)
    now = client.call("status").get("pose_cmd")
    res = probe_sphere(client, c_nom[:3], abc, SPHERE_RADIUS_MM + STYLUS_RADIUS_MM, log_path=opts.probe_log,
                       lead_in=lambda T: transit_tips(cfg, now, platform_of_tip(cfg, T)))
    Xc = platform_of_tip(cfg, np.r_[res["centre_mm"], abc])
    _move_and_settle(client, cfg, hx, Xc, index, opts)
    st = client.call("status")
    q = (np.asarray(st["struts_act_mm"]) - np.asarray(cfg.strut_offset_mm)).tolist()
    flag = "" if res["residual_um"] < 5.0 else f"probe sphere fit residual {res['residual_um']:.1f} um"
    return PoseResult(index, q, {k: float(v) for k, v in zip("xyz", c_nom[:3])}, "tool", time.time(), flag,
                      np.r_[res["centre_mm"], abc].tolist())


def _reset(client) -> None:
    """Reset a fault; a reset the drives refuse (still settling after the stall) is tried again."""
    for attempt in range(3):
        try:
            client.call("reset", reply_timeout_s=60.0)
            break
        except ProtocolError as exc:
            if not _refused(exc) or attempt == 2:
                raise
            time.sleep(1.0)
    client.call("wait", timeout_s=60.0)


def _refused(exc: BaseException) -> bool:
    """A daemon's error reply (it carries a code), not a lost connection."""
    return isinstance(exc, ProtocolError) and getattr(exc, "code", None) is not None


#: error codes of a daemon that cannot take the move *now* (a fault, the stop after it still running)
TRANSIENT = ("fault", "busy")


def _transient_state(client) -> str:
    """After a refusal: wait out a stop in progress; the state then ("fault", "idle", ...)."""
    st = client.call("status").get("state")
    if st not in ("fault", "idle"):
        try:
            st = client.call("wait", timeout_s=60.0).get("state")
        except ProtocolError as exc:
            if not _refused(exc):
                raise
            st = client.call("status").get("state")
    return st


def _arrived(client, X_deg, tol_mm: float = 1e-3, tol_deg: float = 1e-4) -> str | None:
    """None when the commanded platform pose is ``X_deg``, else why not: a program that a fault ended
    may be reported idle (seen under load: pose 15 measured 52 mm short, where the machine stopped)."""
    pc = client.call("status").get("pose_cmd")
    if pc is None:
        return None
    d = np.abs(np.asarray(pc, dtype=float) - np.asarray(X_deg, dtype=float))
    if float(np.max(d[:3])) <= tol_mm and float(np.max(d[3:])) <= tol_deg:
        return None
    return f"the move ended {float(np.max(d[:3])):.3f} mm / {float(np.max(d[3:])):.4f} deg short of the pose"


def _move_and_settle(client, cfg, hx: Hexapod, X_deg, index: int, opts: RunOptions) -> None:
    while True:
        try:
            start = client.call("status").get("pose_cmd")
            client.call("program", text=move_program(cfg, hx, X_deg, opts, start), name=f"calib-pose-{index + 1}",
                        reply_timeout_s=120.0)
            st = client.call("wait", timeout_s=120.0)
        except ProtocolError as exc:
            if not _refused(exc):
                raise
            st = {"state": "refused", "fault": {"message": str(exc)}, "code": exc.code}
        if st.get("state") == "idle":
            at = _arrived(client, X_deg)
            if at is None:
                break
            st = {"state": "short", "fault": {"message": at}}   # a program ended by a fault read as idle
        why = (st.get("fault") or {}).get("message", "")
        if st.get("state") == "refused" and st.get("code") not in TRANSIENT \
                and client.call("status").get("state") != "fault":
            raise DataError(f"pose {index + 1}: the daemon refused the move: {why}; "
                            f"the rows taken so far are kept")
        if st.get("state") in ("fault", "refused", "short") and opts.faults_reset < opts.reset_faults:
            opts.faults_reset += 1
            sys.stderr.write(f"\npose {index + 1}: {why}: reset ({opts.faults_reset}/{opts.reset_faults}), "
                             f"measuring the pose again\n")
            if _transient_state(client) == "fault":
                _reset(client)
            continue
        raise DataError(f"pose {index + 1}: the machine did not come to rest ({st.get('state')}: {why}); "
                        f"the rows taken so far are kept: run again to resume")
    time.sleep(opts.settle_s)


def measure_pose(client, cfg, hx: Hexapod, X_deg, index: int, opts: RunOptions) -> PoseResult:
    """Move to one pose (approach, settle) and take a checked reading."""
    if opts.instrument == "probe" and opts.probe_cycle == "touch":
        while True:
            try:
                return measure_probe_pose(client, cfg, hx, X_deg, index, opts)
            except (DataError, ProtocolError) as exc:
                if isinstance(exc, ProtocolError) and not _refused(exc):
                    raise
                busy = getattr(exc, "code", None) == "busy"          # the stop after a fault still running
                st = _transient_state(client)
                if st != "fault" and not (busy and st == "idle") or opts.faults_reset >= opts.reset_faults:
                    raise
                opts.faults_reset += 1
                sys.stderr.write(f"\npose {index + 1}: {exc}: reset, probing the sphere again\n")
                if st == "fault":
                    _reset(client)
    _move_and_settle(client, cfg, hx, X_deg, index, opts)
    t_rest = time.time() - 0.05
    why = []
    r: dict = {}
    far = None                        #: the last reading far from the model (confirmed by the next?)
    for attempt in range(opts.retries + 1):
        try:
            r = client.call("measure", instrument=opts.instrument, wait_s=opts.wait_s, after_t_s=t_rest,
                            reply_timeout_s=opts.wait_s + 30.0)
        except ProtocolError as exc:
            if not _refused(exc):
                raise
            r = {"values": {}, "q_mm": None}
            why.append(f"missing: {exc}")
            continue
        bad = _check_reading(cfg, hx, r, t_rest, opts)
        if bad.startswith("outlier: ") and _confirms(cfg, hx, r, far, opts):
            bad, why = "", [f"confirmed: {bad[len('outlier: '):]}, two readings agree"]
        if not bad:
            flag = why[0] if why and why[0].startswith("confirmed") else \
                ("remeasured: " + "; ".join(why)) if why else ""
            return PoseResult(index, list(r["q_mm"]), dict(r["values"]), r.get("target", "platform"),
                              float(r["t_s"]), flag, tip_of(cfg, X_deg).tolist())
        why.append(bad)
        far = r if bad.startswith("outlier: ") and "no pose" not in bad else None
    st = client.call("status")
    q = r.get("q_mm") or (np.asarray(st["struts_act_mm"]) - np.asarray(cfg.strut_offset_mm)).tolist()
    return PoseResult(index, list(q), {}, r.get("target", "platform"), time.time(),
                      "excluded: " + "; ".join(why), tip_of(cfg, X_deg).tolist())


def _row(res: PoseResult) -> str:
    cells = [repr(float(v)) for v in res.q_mm]
    cells += [repr(float(res.values[k])) if k in res.values else "" for k in POSE]
    cells += [f"{res.t_s:.6f}", res.flag.replace(",", ";").replace("\n", " ")]
    return ",".join(cells) + "\n"


def rows_done(path: Path) -> int:
    """Data rows already in a measurement file written by calib run (0 if absent); refuses others."""
    if not path.exists():
        return 0
    lines = path.read_text(encoding="utf-8").splitlines()
    if not lines:
        return 0
    if lines[0].strip() != ",".join(COLUMNS):
        raise DataError(f"{path}: exists and is not a calib run file (header {lines[0][:60]!r}); "
                        f"choose another --out or remove it")
    return sum(1 for ln in lines[1:] if ln.strip())


def sidecar_path(path) -> Path:
    return Path(str(path) + ".json")


def run_plan(client, cfg, poses_deg: np.ndarray, out, opts: RunOptions, meta: dict | None = None) -> list[PoseResult]:
    """Measure every pose not yet in ``out`` (appending rows as they are taken)."""
    out = Path(out)
    hx = Hexapod(cfg)
    done = rows_done(out)
    if done > len(poses_deg):
        raise DataError(f"{out}: has {done} rows, the plan only {len(poses_deg)} poses")
    if done == 0:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(",".join(COLUMNS) + "\n", encoding="utf-8")
    results = []
    with open(out, "a", encoding="utf-8") as f:
        for k in range(done, len(poses_deg)):
            res = measure_pose(client, cfg, hx, poses_deg[k], k, opts)
            f.write(_row(res))
            f.flush()
            os.fsync(f.fileno())
            results.append(res)
            _progress(k + 1, len(poses_deg), res.flag, opts)
            if k == done and meta is not None:
                m = dict(meta, target=res.target)
                atomic_write_text(sidecar_path(out), json.dumps(m, indent=2) + "\n")
    return results
