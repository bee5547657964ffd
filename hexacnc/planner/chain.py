"""Runtime sampler over a sequence of planned windows (:mod:`hexacnc.planner.window`): one setpoint row per
cycle, the same interface as :class:`~hexacnc.planner.sampler.PlanSampler` (override, pause, stop,
snapshot/restore, progress).

Every window starts and ends at rest, so the handover from one window's sampler to the next carries the
rate state (override, rate and its derivative, pause or stop request) and never a jump.  A window not
planned yet when the previous one ends (the planner fell behind) is waited for at rest: rows hold the
pose (``FLAG_DWELL``; counted in ``starved_rows``).  A window feed that ends with an error ends the
motion at rest where the last good window ended (``error``); :meth:`fail` stops at once (jerk-limited,
on the path) for an error found ahead by the validation.

The window feed (``feed``) is any object with ``window(i) -> Window | None`` (None: not planned yet),
``peek(i)`` (the same, never waiting or planning), ``finished`` (no window beyond those delivered),
``error`` and ``release(i)`` (windows before i are no
longer needed); :class:`IterFeed` plans from an iterator of windows in the caller's thread.
"""
from __future__ import annotations

import numpy as np

from ..setpoint import COL_FLAGS, COL_LINE, FLAG_DWELL, FLAG_END, ROW

#: nominal seconds of finished windows kept for a rewind (the daemon takes back at most ~0.3 s of rows)
KEEP_S = 2.0


class IterFeed:
    """Windows from an iterator (e.g. :func:`~hexacnc.planner.window.plan_windows`), planned on demand."""

    def __init__(self, windows, total_lines: int = 0):
        self._it = iter(windows)
        self._have: dict = {}
        self._n = 0
        self.finished = False
        self.error = None
        self.total_lines = int(total_lines)

    def window(self, i: int):
        while i >= self._n and not self.finished:
            try:
                w = next(self._it)
            except StopIteration:
                self.finished = True
                break
            except Exception as exc:            # a bad window: the motion ends before it
                self.error = exc
                self.finished = True
                break
            self._have[self._n] = w
            self._n += 1
            if w.last:
                self.finished = True
        return self._have.get(i)

    def peek(self, i: int):
        """Window i if planned already (never plans)."""
        return self._have.get(i)

    def release(self, i: int) -> None:
        for k in [k for k in self._have if k < i]:
            del self._have[k]

    def close(self) -> None:
        close = getattr(self._it, "close", None)
        if close is not None:
            close()


class ChainSampler:
    """Setpoint rows over the windows of a feed (see the module docstring)."""

    def __init__(self, feed, period_s: float, optional_stop: bool = False):
        self.feed = feed
        self.period_s = float(period_s)
        self.optional_stop = bool(optional_stop)
        self.error = None
        self.starved_rows = 0
        self.rows_written = 0
        self._i = 0
        self._user = 1.0
        self._rapid = 1.0
        self._intent = "run"          # run, pause, stop: what the operator asked last
        self._done = False
        self._last = None             # the last row written (the pose held while waiting)
        self._dur = {}                # window -> nominal duration (s), while kept
        self._s = None
        self._win = None
        w = feed.window(0)
        if w is None and feed.finished:
            self.error = feed.error
            self._done = True
        elif w is not None:
            self._enter(w, None)

    # -- windows -------------------------------------------------------------------------
    def _enter(self, w, prev) -> None:
        s = w.plan.sampler(self.period_s, optional_stop=self.optional_stop)
        s.set_override(self._user)
        s.set_rapid_override(self._rapid)
        if prev is not None:        # both at rest here: the rate carries over
            s.f, s.fd = prev.f, prev.fd
        if self._intent == "pause":
            s.pause()
        self._win, self._s, self._i = w, s, w.index
        self._dur[w.index] = w.plan.duration_s
        # windows more than KEEP_S of nominal time before this one are released (a rewind never goes there)
        acc = 0.0
        for k in sorted((k for k in self._dur if k < w.index), reverse=True):
            acc += self._dur[k]
            if acc >= KEEP_S:
                self.feed.release(k)
                for j in [j for j in self._dur if j < k]:
                    del self._dur[j]
                break

    def _advance(self) -> bool:
        """After a window ended on its own: enter the next one. False while it is not planned yet."""
        if self._win.last or self._intent == "stop":
            self._done = True
            return False
        w = self.feed.window(self._i + 1)
        if w is None:
            if self.feed.finished:
                self.error = self.feed.error
                self._done = True
            return False
        self._enter(w, self._s)
        return True

    # -- commands --------------------------------------------------------------------------
    def set_optional_stop(self, on: bool) -> None:
        """The optional-stop switch, for the window running and the next ones."""
        self.optional_stop = bool(on)
        if self._s is not None:
            self._s.set_optional_stop(on)

    def set_override(self, f: float) -> None:
        self._user = float(f)
        if self._s is not None:
            self._s.set_override(f)
            self._user = self._s.user

    def set_rapid_override(self, r: float) -> None:
        self._rapid = float(r)
        if self._s is not None:
            self._s.set_rapid_override(r)
            self._rapid = self._s.rapid

    def pause(self) -> None:
        self._intent = "pause"
        if self._s is not None:
            self._s.pause()

    def resume(self) -> None:
        self._intent = "run"
        if self._s is not None:
            self._s.resume()

    def stop(self) -> None:
        self._intent = "stop"
        if self._s is not None:
            self._s.stop()
        if self._s is None or self._s.done:
            self._done = True

    def fail(self, error) -> None:
        """An error found ahead (validation): stop now, on the path, and report it."""
        if self.error is None:
            self.error = error
        self.stop()

    # -- state -------------------------------------------------------------------------------
    @property
    def done(self) -> bool:
        return self._done

    @property
    def state(self) -> str:
        if self._done:
            return "done"
        if self._s is None or self._s.done:
            return "paused" if self._intent == "pause" else "running"
        return self._s.state

    @property
    def override(self) -> float:
        return self._s.f if self._s is not None else 0.0

    @property
    def user(self) -> float:
        return self._user

    @property
    def line(self) -> int:
        return self._s.line if self._s is not None else 0

    @property
    def progress(self) -> tuple[float, float]:
        """(percent done by program line, time left s: the windows planned so far, and the feed's estimate
        of the rest, ``unplanned_s()``, where it has one)."""
        finished = self._done and self.error is None and self._intent != "stop"    # a stopped program is not
        if self._s is None:
            return (100.0 if finished else 0.0), 0.0
        _pct, left = self._s.progress
        k = self._i + 1
        w = self.feed.peek(k)
        while w is not None:
            left += w.plan.duration_s
            k += 1
            w = self.feed.peek(k)
        if finished:
            return 100.0, 0.0
        rest = getattr(self.feed, "unplanned_s", None)
        if rest is not None:
            left += rest()
        total = max(1, int(getattr(self.feed, "total_lines", 0) or 0))
        return min(100.0, 100.0 * self.line / total), left

    def snapshot(self) -> tuple:
        s = self._s
        return (self._i, self._win, s, s.snapshot() if s is not None else None, self._user, self._rapid,
                self._intent, self._done, self._last, self.rows_written, self.error)

    def restore(self, snap: tuple) -> None:
        (self._i, self._win, self._s, ss, self._user, self._rapid, self._intent, self._done, self._last,
         self.rows_written, self.error) = snap
        if self._s is not None:
            self._s.restore(ss)

    # -- rows -----------------------------------------------------------------------------------
    def next_rows(self, out: np.ndarray) -> int:
        nmax = out.shape[0]
        cnt = 0
        while cnt < nmax and not self._done:
            s = self._s
            if s is None:
                break
            if s.done:
                if self._advance():
                    continue
                if self._done:
                    break
                # the next window is not planned yet: wait at rest (the previous one ended at rest)
                n = nmax - cnt
                out[cnt:cnt + n] = self._last
                out[cnt:cnt + n, COL_FLAGS] = FLAG_DWELL
                self.starved_rows += n
                cnt += n
                break
            n = s.next_rows(out[cnt:])
            if n:
                if not (self._win.last or self._intent == "stop" and s.done):
                    out[cnt:cnt + n, COL_FLAGS] = np.asarray(out[cnt:cnt + n, COL_FLAGS], dtype=np.int64) & ~FLAG_END
                self._last = out[cnt + n - 1].copy()
                cnt += n
            if s.done and self._intent == "stop":
                self._done = True
            elif not n and not s.done:
                break
        self.rows_written += cnt
        return cnt


__all__ = ["ChainSampler", "IterFeed", "ROW", "COL_LINE"]
