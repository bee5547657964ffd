"""Runtime sampler of a :class:`~hexacnc.planner.plan.Plan`: one platform setpoint row per cycle period.

The plan is a table ``s(tau)`` (path position against nominal time).  The
sampler advances ``tau`` at rate ``f`` (feed override, pause, stop) and emits
the platform pose at ``s(tau)`` - always on the programmed path.  ``f`` is
moved by Ruckig (1 DOF, velocity interface: position ``tau``, velocity ``f``,
acceleration ``f'``, jerk ``f''``) with limits recomputed every row from the
plan's look-ahead headroom so that, with nominal strut velocity ``v``,
acceleration ``a`` and jerk ``j`` at ``tau``,

    velocity  f v                              <= vmax
    accel.    f^2 a + f' v                     <= amax
    jerk      f^3 j + 3 f f' a + f'' v         <= jmax

(the plan keeps ``a``, ``j`` <= 0.95 of the limits, so there is always room).
Pause and stop are jerk-limited decelerations of ``f`` to 0: the platform
comes to rest on the path; resume ramps ``f`` back up.  M0 (and M1 with
``optional_stop``) pause inside a standstill hold of the plan.

Rows: float64 ``[x, y, z, a, b, c, line, flags]`` - platform pose in mm and
radians, source line, flag bits (see :mod:`hexacnc.planner.plan`).
"""
from __future__ import annotations

import math

import numpy as np
from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig, RuckigError, Trajectory

from ..setpoint import COL_FLAGS, COL_LINE, FLAG_END, FLAG_PAUSED, FLAG_RAPID, FLAG_STOPPING

#: samples per governor block; blocks a rate transition's limits cover at first (the window then grows until it
#: covers every block the transition runs through); look-ahead of the override cap (seconds)
GOV_BLOCK = 20
TRANSITION_BLOCKS = 4
CAP_LOOKAHEAD_S = 4.0
#: override range accepted by set_override (the plan's headroom may cap it further)
MAX_OVERRIDE = 2.0
#: look-ahead (s) of the rapid-feed cap on the override: no limit of the machine's, the ramp down to it (~30 ms
#: at A_MAX, J_MAX) may pass the rapid feed briefly where the struts' headroom makes the ramp slower
SPEED_CAP_LOOKAHEAD_S = 0.25
#: caps on the rate's derivatives (1/s, 1/s^2): 0 -> 1 in no less than ~40 ms
A_MAX = 50.0
J_MAX = 5000.0

RUN, PAUSING, PAUSED, PROGRAM_PAUSED, STOPPING, DONE = "running", "pausing", "paused", "program_paused", \
    "stopping", "done"


def governor_tables(uv, ua, uj, va, ajr, vjr, dt: float, speed_share=None) -> dict:
    """Block maxima of the nominal utilisations (each block with the one before it).  A rate transition takes
    the maxima over the blocks it runs through (:meth:`PlanSampler._transition_limits`), and the override cap
    the maxima over CAP_LOOKAHEAD_S.  ``speed_share`` (N,): the path speed of each row over the rapid feed;
    the override is capped at its inverse (maxima over SPEED_CAP_LOOKAHEAD_S), so that no override runs a
    move faster than the rapid feed, as LinuxCNC's maximum velocity caps every move."""
    N = uv.shape[0]
    nb = (N + GOV_BLOCK - 1) // GOV_BLOCK
    pad = nb * GOV_BLOCK - N
    out = {}
    for name, arr in (("uv", uv), ("ua", ua), ("uj", uj), ("va", va), ("ajr", ajr), ("vjr", vjr)):
        a = np.concatenate([arr, np.full(pad, arr[-1] if N else 0.0)]).reshape(nb, GOV_BLOCK).max(axis=1)
        w = a.copy()
        w[1:] = np.maximum(w[1:], a[:-1])           # one block behind
        out[name] = w
    # override above 1 only where the nominal leaves room, looking CAP_LOOKAHEAD_S ahead so that a
    # slow (headroom-limited) ramp back down completes in time; never below 1 (the plan itself is valid)
    Wc = max(1, int(math.ceil(CAP_LOOKAHEAD_S / (GOV_BLOCK * dt))))
    mx = {}
    for name in ("uv", "ua", "uj"):
        mx[name] = _ahead_max(out[name], Wc)
    with np.errstate(divide="ignore"):
        cap = np.minimum(0.99 / np.maximum(mx["uv"], 1e-12), np.sqrt(0.85 / np.maximum(mx["ua"], 1e-12)))
        cap = np.minimum(cap, np.cbrt(0.85 / np.maximum(mx["uj"], 1e-12)))
        if speed_share is not None and N:
            sh = np.concatenate([speed_share, np.full(pad, speed_share[-1])]).reshape(nb, GOV_BLOCK).max(axis=1)
            sh[1:] = np.maximum(sh[1:], sh[:-1])
            Ws = max(1, int(math.ceil(SPEED_CAP_LOOKAHEAD_S / (GOV_BLOCK * dt))))
            cap = np.minimum(cap, 1.0 / np.maximum(_ahead_max(sh, Ws), 1e-12))
    out["cap"] = np.clip(cap, 1.0, MAX_OVERRIDE)
    return out


def _ahead_max(a: np.ndarray, W: int) -> np.ndarray:
    """``out[b] = max(a[b .. b + W])`` (clipped at the end), by doubling."""
    w = a.copy()
    k = 1
    while k <= W:
        step = min(k, W + 1 - k)
        w[:-step] = np.maximum(w[:-step], w[step:])
        k += step
    return w


def _rest_and_rapid_rows(s_tab: np.ndarray, flags: np.ndarray) -> tuple:
    """Per table row: at rest (rows i and i + 1 equal: a stop's rows, where the path's speed and acceleration
    vanish, so that a change of the rate there changes neither), rapid (a rest counts as the motion after it),
    and the last row of its run of equal rapid-ness: numpy arrays, read a row at a time outside the steady
    stretches (10 bytes a row; Python lists took ~30 MB per million rows, a 900 s dwell is 1.8 million)."""
    n = s_tab.shape[0]
    flat = np.zeros(n, dtype=bool)
    if n >= 2:
        flat[:-1] = s_tab[1:] == s_tab[:-1]
    idx = np.where(flat, n - 1, np.arange(n))
    nxt = np.minimum.accumulate(idx[::-1])[::-1]          # the first row at or after i that moves
    rapid = (flags[nxt] & FLAG_RAPID) != 0 if n else np.zeros(0, dtype=bool)
    change = np.nonzero(rapid[1:] != rapid[:-1])[0]      # run ends
    ends = np.concatenate([change, [n - 1]]) if n else np.zeros(0, dtype=np.int64)
    run_end = ends[np.searchsorted(ends, np.arange(n))] if n else ends
    return flat, rapid, run_end.astype(np.int64)


class PlanSampler:
    """Setpoint rows from a plan, with feed override, pause/resume and stop.

    ``next_rows(out)`` fills ``out`` ((n, 8) float64) and returns the number of
    rows written (0 once the program has ended or been stopped).  While paused
    it keeps writing the standstill pose (flag FLAG_PAUSED).
    """

    def __init__(self, plan, period_s: float, optional_stop: bool = False):
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ValueError(f"period_s must be positive, got {period_s!r}")
        self.plan = plan
        self.period_s = float(period_s)
        self.optional_stop = bool(optional_stop)
        self.s_tab = plan.s_tab
        self.n = plan.s_tab.shape[0]
        self.step = self.period_s / plan.dt          # table samples per row at f = 1
        self.k = 0.0                                 # plan time in table samples
        self.f = 1.0
        self.fd = 0.0
        self.user = 1.0
        self.rapid = 1.0                             # rapid override: rate factor on governor blocks of rapids
        self._flat, self._rapid_row, self._rapid_end = _rest_and_rapid_rows(plan.s_tab, np.asarray(plan.flag_tab))
        self.state = RUN
        self.done = self.n == 0
        g = plan.gov
        self._g = g
        self._nb = g["cap"].shape[0]
        self._cap = g["cap"].tolist()
        self._lim = None
        self._lim_tgt = None
        self._lim_age = 0
        self._pauses = sorted(plan.pause_idx)
        self._next_pause = 0
        self._otg = Ruckig(1, self.period_s)        # never the third (cloud) argument
        self._inp = InputParameter(1)
        self._inp.control_interface = ControlInterface.Velocity
        self._out = OutputParameter(1)
        self._otg_offline = Ruckig(1)               # duration estimates (never the cloud argument)
        self._traj = Trajectory(1)
        self.rows_written = 0

    # -- commands --------------------------------------------------------------------
    def set_optional_stop(self, on: bool) -> None:
        """The optional-stop switch: M1 pauses (as M0) when on; read when the motion reaches an M1."""
        self.optional_stop = bool(on)

    def set_override(self, f: float) -> None:
        """Feed override (0 .. 2; above 1 only where the plan has headroom); jerk-limited transition."""
        f = float(f)
        if not math.isfinite(f):
            raise ValueError(f"override must be finite, got {f!r}")
        self.user = min(MAX_OVERRIDE, max(0.0, f))

    def set_rapid_override(self, r: float) -> None:
        """Rapid override (0 .. 1): scales the rate on rapids (G0) only; jerk-limited transitions."""
        r = float(r)
        if not math.isfinite(r):
            raise ValueError(f"rapid override must be finite, got {r!r}")
        self.rapid = min(1.0, max(0.0, r))

    def pause(self) -> None:
        """Jerk-limited deceleration to standstill on the path."""
        if self.state == RUN:
            self.state = PAUSING

    def resume(self) -> None:
        """Restart after pause() or an M0/M1 program pause."""
        if self.state in (PAUSING, PAUSED, PROGRAM_PAUSED):
            self.state = RUN

    def stop(self) -> None:
        """Jerk-limited stop on the path; the program then ends (done)."""
        if self.state in (PAUSED, PROGRAM_PAUSED):
            self.state = DONE
            self.done = True
            self.f = self.fd = 0.0
        elif self.state != DONE:
            self.state = STOPPING

    # -- rewind (the daemon takes back rows it queued but the drives have not run) ---------
    def snapshot(self) -> tuple:
        """The sampler's whole state before the next row (immutable; for :meth:`restore`)."""
        return (self.k, self.f, self.fd, self.user, self.state, self.done, self._lim, self._lim_tgt,
                self._lim_age, self._next_pause, self.rows_written)

    def restore(self, snap: tuple) -> None:
        """Go back to a :meth:`snapshot`: the next rows continue from there, as if nothing followed."""
        (self.k, self.f, self.fd, self.user, self.state, self.done, self._lim, self._lim_tgt,
         self._lim_age, self._next_pause, self.rows_written) = snap

    # -- status ------------------------------------------------------------------------
    @property
    def line(self) -> int:
        i = min(self.n - 1, max(0, int(round(self.k))))
        return int(self.plan.line_tab[i]) if self.n else 0

    @property
    def progress(self) -> tuple[float, float]:
        """(percent done, nominal time left in seconds at override 1)."""
        if self.n <= 1:
            return 100.0, 0.0
        frac = min(1.0, self.k / (self.n - 1))
        return 100.0 * frac, (self.n - 1 - min(self.k, self.n - 1)) * self.plan.dt

    @property
    def override(self) -> float:
        """The rate currently applied (after ramps and the headroom cap)."""
        return self.f

    # -- rows ----------------------------------------------------------------------------
    def _limits_window(self, b0: int, b1: int, f: float, tgt: float) -> tuple[float, float]:
        """Ruckig limits for the rate over governor blocks b0..b1 (margin 0.97 of every strut limit).

        With ``fh = max(f, target)`` and the block maxima: ``A = (0.97 - fh^2 ua) / va`` (capped so
        the cross term ``3 fh A a/J`` takes at most 30 % of the jerk headroom) and
        ``J = (0.97 - fh^3 uj - 3 fh A ajr) / vjr``.
        """
        g = self._g
        sl = slice(max(0, b0), min(self._nb, b1 + 1))
        ua, uj, va = float(g["ua"][sl].max()), float(g["uj"][sl].max()), float(g["va"][sl].max())
        ajr, vj = float(g["ajr"][sl].max()), float(g["vjr"][sl].max())
        fh = f if f > tgt else tgt
        hj = max(0.01, 0.97 - fh * fh * fh * uj)
        ha = max(0.01, 0.97 - fh * fh * ua)
        A = ha / va if va > 1e-12 else A_MAX
        if fh > 0 and ajr > 1e-12:
            A = min(A, 0.3 * hj / (3.0 * fh * ajr))
        A = min(max(A, 1e-4), A_MAX)
        J = (hj - 3.0 * fh * A * ajr) / vj if vj > 1e-12 else J_MAX
        J = min(max(J, 1e-3), J_MAX)
        return A, J

    def _transition_limits(self, b: int, tgt: float) -> tuple[float, float]:
        """Constant limits for a whole transition: the window grows until it covers the transition (the table
        time a rate ramp runs through is at most ``max(f, tgt)`` times its duration); if it has not settled after
        6 rounds, the limits of every block from here to the end."""
        nbk = TRANSITION_BLOCKS
        for _ in range(6):
            A, J = self._limits_window(b - 1, b + nbk, self.f, tgt)
            dur = self._duration(tgt, A, J)
            need = int((max(self.f, tgt) * dur / self.plan.dt) / GOV_BLOCK) + 2
            if need <= nbk:
                return A, J
            nbk = need
        return self._limits_window(b - 1, self._nb, self.f, tgt)

    def _rate_input(self, position: float, tgt: float, A: float, J: float) -> InputParameter:
        """Ruckig input for moving the rate from its current state (f, f') to ``tgt`` at rest."""
        inp = self._inp
        inp.current_position = [position]
        inp.current_velocity = [self.f]
        inp.current_acceleration = [self.fd]
        inp.target_velocity = [tgt]
        inp.target_acceleration = [0.0]
        inp.max_velocity = [MAX_OVERRIDE + 1.0]
        inp.max_acceleration = [A]
        inp.max_jerk = [J]
        return inp

    def _duration(self, tgt: float, A: float, J: float) -> float:
        inp = self._rate_input(0.0, tgt, A, J)
        try:
            res = self._otg_offline.calculate(inp, self._traj)
        except RuckigError:
            return 10.0
        return float(self._traj.duration) if res in (Result.Working, Result.Finished) else 10.0

    def _target(self, b: int, i: int) -> float:
        """The rate aimed at in governor block b at table row i."""
        if self.state in (PAUSING, STOPPING, PAUSED, PROGRAM_PAUSED, DONE):
            return 0.0
        if self.rapid != 1.0 and self._rapid_row[i]:
            return min(self.user * self.rapid, self._cap[b])
        return min(self.user, self._cap[b])

    def _steady_rows(self, room: int, nxt: int, b: int, i: int) -> int:
        """Rows at the steady rate from here (at most ``room``): to the table row ``nxt`` (a pause or the end),
        the end of governor block b, and with a rapid override to the next change between rapid and feed rows
        (row i is the current one)."""
        adv = max(self.f * self.step, 1e-9)
        if self.f > 0:
            room = min(room, max(1, int((nxt - self.k) / (self.f * self.step))))
        room = min(room, max(1, int(((b + 1) * GOV_BLOCK - self.k) / adv) + 1))
        if self.rapid != 1.0:
            room = min(room, max(1, int((self._rapid_end[i] + 1 - self.k) / adv) + 1))
        return room

    def next_rows(self, out: np.ndarray) -> int:
        if self.done:
            return 0
        nmax = out.shape[0]
        ks = np.empty(nmax)
        extra = np.zeros(nmax, dtype=np.int64)
        cnt = 0
        last = self.n - 1
        inp, otg, o = self._inp, self._otg, self._out
        while cnt < nmax:
            i = min(last, int(self.k))
            b = min(len(self._cap) - 1, i // GOV_BLOCK)
            tgt = self._target(b, i)
            if self.state == RUN and self.f != tgt and self._flat[i]:
                self._rate_at_rest(tgt, i)
                continue
            if self.f == tgt and self.fd == 0.0 and self.state == RUN:
                # steady: vectorised advance up to the next pause, the end or a cap change
                nxt = self._pauses[self._next_pause][0] if self._next_pause < len(self._pauses) else last
                room = self._steady_rows(nmax - cnt, nxt, b, i)
                kk = self.k + self.f * self.step * np.arange(1, room + 1)
                if kk[-1] >= nxt:
                    room = int(np.searchsorted(kk, nxt, side="left")) + 1
                    kk = kk[:room]
                    kk[-1] = min(kk[-1], nxt)
                ks[cnt:cnt + room] = kk
                cnt += room
                self.k = float(kk[-1])
            elif self.state in (PAUSED, PROGRAM_PAUSED):
                ks[cnt] = self.k
                extra[cnt] = FLAG_PAUSED
                cnt += 1
                continue
            else:
                if self._lim is None or tgt != self._lim_tgt:
                    self._lim = self._transition_limits(b, tgt)
                    self._lim_tgt = tgt
                    self._lim_age = 0
                else:
                    self._lim_age += 1
                    if tgt < self.f and self._lim_age >= 40:
                        # slowing down frees headroom (f^2 a, f^3 j shrink): raise the limits, never lower
                        self._lim_age = 0
                        A2, J2 = self._transition_limits(b, tgt)
                        if A2 >= self._lim[0] and J2 >= self._lim[1]:
                            self._lim = (A2, J2)
                A, J = self._lim
                self._rate_input(self.k * self.plan.dt, tgt, A, J)
                try:
                    res = otg.update(inp, o)
                except RuckigError:
                    res = None
                if res not in (Result.Working, Result.Finished):
                    # fall back to holding the rate (never a jump)
                    nk = self.k + self.f * self.step
                    nf, nfd = self.f, 0.0
                else:
                    nk = max(self.k, o.new_position[0] / self.plan.dt)
                    nf, nfd = max(0.0, o.new_velocity[0]), o.new_acceleration[0]
                if abs(nf - tgt) < 1e-9 and abs(nfd) < 1e-7:
                    nf, nfd = tgt, 0.0
                    self._lim = None
                self.k, self.f, self.fd = nk, nf, nfd
                ks[cnt] = self.k
                if self.state == STOPPING:
                    extra[cnt] = FLAG_STOPPING
                cnt += 1
                if self.f == 0.0 and self.fd == 0.0:
                    if self.state == PAUSING:
                        self.state = PAUSED
                    elif self.state == STOPPING:
                        self.state = DONE
                        self.done = True
                        break
            # program pause / end
            if self._next_pause < len(self._pauses) and self.k >= self._pauses[self._next_pause][0]:
                p, optional, _ln = self._pauses[self._next_pause]
                self._next_pause += 1
                if not optional or self.optional_stop:
                    self.k = float(p)
                    ks[cnt - 1] = self.k
                    self.f = self.fd = 0.0
                    if self.state == RUN or self.state == PAUSING:
                        self.state = PROGRAM_PAUSED
                    elif self.state == STOPPING:
                        self.state = DONE
                        self.done = True
                        break
            if self.k >= last:
                self.k = float(last)
                ks[cnt - 1] = self.k
                extra[cnt - 1] |= FLAG_END
                self.state = DONE
                self.done = True
                break
        self._fill(out, ks[:cnt], extra[:cnt])
        self.rows_written += cnt
        return cnt

    def _rate_at_rest(self, tgt: float, i: int) -> None:
        """At rest (table rows i and i + 1 equal) the rate changes at once: a rapid override ends with the rapid's
        stop, not a transition into the feed move after it.  The phase moves onto the next table row (anywhere
        between the two is the same rest): the interpolation at a fractional phase reads a jerk step of the table
        up to 4 % higher."""
        self.f, self.fd, self._lim = tgt, 0.0, None
        if self.k < i + 1 and self.k != i:
            self.k = float(i + 1)

    def _fill(self, out: np.ndarray, k: np.ndarray, extra: np.ndarray) -> None:
        n = k.shape[0]
        if n == 0:
            return
        s = self._interp(k)
        X = self.plan.platform_at(s)
        idx = np.clip(np.rint(k).astype(np.int64), 0, self.n - 1)
        self.last_idx = idx          #: table index of each row of the last batch (hexacnc.daemon.ioprog)
        out[:n, :6] = X
        out[:n, COL_LINE] = self.plan.line_tab[idx]
        out[:n, COL_FLAGS] = (self.plan.flag_tab[idx] & ~FLAG_END) | extra

    def _interp(self, k: np.ndarray) -> np.ndarray:
        """Catmull-Rom interpolation of the s table at fractional indices, clamped between neighbours."""
        S = self.s_tab
        last = self.n - 1
        i = np.clip(np.floor(k).astype(np.int64), 0, last)
        t = k - i
        i0 = np.clip(i - 1, 0, last)
        i2 = np.clip(i + 1, 0, last)
        i3 = np.clip(i + 2, 0, last)
        p0, p1, p2, p3 = S[i0], S[i], S[i2], S[i3]
        v = 0.5 * (2 * p1 + (p2 - p0) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t * t
                   + (3 * p1 - p0 - 3 * p2 + p3) * t * t * t)
        exact = t == 0.0
        v = np.where(exact, p1, np.clip(v, np.minimum(p1, p2), np.maximum(p1, p2)))
        return v
