"""Programs for the daemon: G-code text -> interpreted blocks -> plan -> row source for the feeder.

``plan_program(cfg, hx, text, name, start_rad, period_s) -> ProgramPlan``: the whole program is
interpreted (:mod:`hexacnc.gcode`) from the tool tip of the pose the machine will be at when it
starts, planned (:mod:`hexacnc.planner`, every strut-length, joint-angle, velocity, acceleration and
jerk limit checked along the whole path) before anything moves.  Errors: ``GcodeError`` (line,
column), ``PlanError`` (line, limit).

:class:`ProgramSource` adapts the planner's ``PlanSampler`` (feed override, pause along the path,
jerk-limited stop, M0/M1) to the feeder's source interface.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import PlanError
from ..planner.window import tool_tip_pose_deg  # noqa: F401 (re-exported: the daemon's callers use it here)
from .ioprog import IoCursor, plan_with_io
from .shm import FLAG_END, ROW


@dataclass
class ProgramPlan:
    source: "ProgramSource"
    blocks: int
    duration_s: float
    end_rad: np.ndarray
    summary: dict


class ProgramSource:
    """Feeder source over a :class:`hexacnc.planner.sampler.PlanSampler`."""

    def __init__(self, plan, period_s: float, name: str, sampler=None, stream=None):
        """``plan`` (a whole plan), or ``sampler`` (a :class:`~hexacnc.planner.chain.ChainSampler`) over the
        windows of ``stream`` (a :class:`~hexacnc.daemon.planstream.StreamPlan`, closed with the source)."""
        self.plan = plan
        self.sampler = sampler if sampler is not None else plan.sampler(period_s)
        self.stream = stream
        self.name = name
        self.finished = False
        self.stopping = False
        self._last = None
        acts = getattr(plan, "io_actions", None)      # M62-M65 (hexacnc.daemon.ioprog)
        self.io = IoCursor(acts) if acts is not None and len(acts.index) else None

    # -- control --------------------------------------------------------------------------
    def pause(self) -> None:
        self.sampler.pause()

    def resume(self) -> None:
        self.sampler.resume()

    def stop(self) -> None:
        self.stopping = True
        self.sampler.stop()

    def set_feed_override(self, f: float) -> None:
        self.sampler.set_override(float(f))

    def set_optional_stop(self, on: bool) -> None:
        self.sampler.set_optional_stop(bool(on))

    @property
    def paused(self) -> bool:
        return self.sampler.state in ("pausing", "paused", "program_paused")

    def progress(self) -> tuple[int, float, float]:
        """(line, percent, time left s): the nominal time left at the feed override the operator set (not the
        rate of the moment, which a stop or a pause brings to 0: 'left 3:26:11' while stopping); 0 once
        stopping (the rest will not run); the nominal time while the override is 0."""
        pct, left = self.sampler.progress
        line = int(self.sampler.line)
        if self.stopping or self.sampler.state in ("stopping", "done"):
            return line, float(pct), 0.0
        f = float(self.sampler.user)
        return line, float(pct), float(left) / (f if f >= 0.01 else 1.0)

    @property
    def error(self):
        """The program's error that ended the motion early (streamed programs), else None."""
        return getattr(self.sampler, "error", None)

    def fail(self, error) -> None:
        """Stop at once (jerk-limited, on the path) for an error found ahead by the validation."""
        self.stopping = True
        self.sampler.fail(error)

    def close(self) -> None:
        """The job is over: its planning children end."""
        if self.stream is not None:
            self.stream.cancel()

    def stream_status(self) -> dict:
        """Status fields of a streamed program: its validation, windows waited for (rows at rest)."""
        if self.stream is None:
            return {}
        out = {"validation": dict(self.stream.validation),
               "starved_s": round(getattr(self.sampler, "starved_rows", 0) * self.sampler.period_s, 3)}
        if self.error is not None:
            out["error"] = {"line": getattr(self.error, "line", None), "message": str(self.error)}
        return out

    # -- rewind ----------------------------------------------------------------------------
    def snapshot(self) -> tuple:
        """State before the next row (see :meth:`Daemon._rewind`)."""
        return (self.sampler.snapshot(), self.finished, self.stopping, self._last,
                self.io.pos if self.io is not None else 0)

    def restore(self, snap: tuple) -> None:
        s, self.finished, self.stopping, self._last, io_pos = snap
        self.sampler.restore(s)
        if self.io is not None:
            self.io.pos = io_pos

    # -- rows ------------------------------------------------------------------------------
    def next_rows(self, count: int) -> np.ndarray:
        if self.finished:
            return np.empty((0, ROW))
        out = np.empty((count, ROW))
        n = self.sampler.next_rows(out)
        rows = out[:n]
        if n and self.io is not None:
            self.io.mark(rows, self.sampler.last_idx)
        if n:
            self._last = rows[-1].copy()
        if self.sampler.done:
            self.finished = True
            if n and int(rows[-1, 7]) & FLAG_END:
                return rows
            end = (self._last if self._last is not None else out[0]).copy()
            end[7] = float(int(end[7]) | FLAG_END)
            return np.vstack([rows, end[None, :]])
        return rows


def plan_program(cfg, hx, text: str, name: str, start_rad, period_s: float) -> ProgramPlan:
    from ..gcode import program_from_config
    from ..planner import plan_program as planner_plan
    start = tool_tip_pose_deg(cfg, start_rad)
    prog = program_from_config(text, name, cfg, start_pose=start)
    plan = plan_with_io(prog.blocks, cfg, planner_plan, hexapod=hx, period_s=period_s, start_pose=start)
    p0 = np.asarray(plan.start_pose_platform, dtype=float)
    if float(np.max(np.abs(p0 - np.asarray(start_rad, dtype=float)))) > 1e-6:
        raise PlanError(f"program {name!r} does not start where the machine is "
                        f"(planned start {np.round(p0, 6).tolist()}, machine {np.round(start_rad, 6).tolist()})",
                        limit="start")
    src = ProgramSource(plan, period_s, name)
    return ProgramPlan(source=src, blocks=len(prog.blocks), duration_s=float(plan.duration_s),
                       end_rad=np.asarray(plan.end_pose_platform, dtype=float), summary=plan.summary())


def program_source(sp, name: str, start_rad, period_s: float):
    """Wait until the streamed program ``sp`` (a :class:`~hexacnc.daemon.planstream.StreamPlan`) may move
    (``wait_ready``); returns
    (ProgramSource, info: blocks, duration_s, duration_exact, validated, end_rad or None).  ``duration_s``
    is the planned duration for a program of one window, else an estimate (``duration_exact`` false): the
    windows planned so far and the rest extrapolated from them by a fit of planned to nominal seconds and
    blocks (:meth:`~hexacnc.daemon.planstream.StreamPlan.unplanned_s`; by lines before the validation has
    counted the program)."""
    from ..planner.chain import ChainSampler
    try:
        first = sp.wait_ready()
        p0 = np.asarray(first.plan.start_pose_platform, dtype=float)
        if float(np.max(np.abs(p0 - np.asarray(start_rad, dtype=float)))) > 1e-6:
            raise PlanError(f"program {name!r} does not start where the machine is (planned start "
                            f"{np.round(p0, 6).tolist()}, machine {np.round(start_rad, 6).tolist()})", limit="start")
        chain = ChainSampler(sp, period_s)
    except BaseException:
        sp.cancel()
        raise
    src = ProgramSource(None, period_s, name, sampler=chain, stream=sp)
    val = dict(sp.validation)
    single = first.last
    info = {"blocks": int(first.blocks if single else val.get("blocks", 0)),
            "duration_s": float(first.plan.duration_s if single else sp.planned_s + sp.unplanned_s()),
            "duration_exact": bool(single), "validated": val.get("state") == "valid",
            "end_rad": np.asarray(first.plan.end_pose_platform, dtype=float) if single else sp.end_rad}
    return src, info
