"""How long the unplanned rest of a streamed program takes, learnt from the windows planned so far.

A program's nominal seconds (each block at its programmed feed, :mod:`.blocktime`) explain its planned time
where the machine can follow the feeds; where it cannot (3D_Chips.ngc's F4.5e6, capped at the rapid feed:
24 s nominal, 89 s planned) the time is set per block by the struts' dynamics.  Each planned window adds, per
program line, the line's nominal seconds ``n``, its blocks ``m`` and its planned seconds ``t`` (its rows,
counted) to six sums; the model ``t = alpha n + beta m`` (``alpha``, ``beta`` >= 0) is their least-squares
fit, and the rest of the program is ``alpha (N - N_planned) + beta (M - M_planned)`` with the validation's
whole-program totals ``N``, ``M``.

On a CAM raster at a feed the struts cannot follow (``hexacnc.bench.camgen`` at F2.4e6, windows of 60
blocks) the estimate after the first window (which holds the rapid approach from home) is 6 % over the
planned time, where the older mix of a nominal-seconds ratio and a blocks ratio was 37 % over; from the
second window on within 6.4 % (was 19 %).  At feeds the struts follow ``alpha`` is ~1 and ``beta`` small.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the sums a window carries: sum n^2, n m, m^2, n t, m t, t^2 over its lines
N_SUMS = 6


def line_sums(lines, seconds, line_tab: np.ndarray, dt: float) -> tuple[float, ...]:
    """The six sums (:data:`N_SUMS`) of a planned window: ``lines`` and ``seconds`` are its blocks' program
    lines and nominal seconds (equal length); ``line_tab`` (N,) the program line of each row of its plan,
    ``dt`` the row period (s).  Rows of a line without a block in the window do not count."""
    per: dict[int, list] = {}
    for ln, s in zip(lines, seconds):
        e = per.setdefault(int(ln), [0.0, 0])
        e[0] += float(s)
        e[1] += 1
    rows = _row_counts(np.asarray(line_tab))
    out = [0.0] * N_SUMS
    for ln, (n, m) in per.items():
        t = rows.get(ln, 0) * dt
        for k, v in enumerate((n * n, n * m, m * m, n * t, m * t, t * t)):
            out[k] += v
    return tuple(out)


def _row_counts(line_tab: np.ndarray) -> dict:
    """{line: rows}: a bincount over the window's line span (7x faster than np.unique on 2 M rows), np.unique
    where the span is much wider than the table (a subroutine far from its call)."""
    if line_tab.size == 0:
        return {}
    lo, hi = int(line_tab.min()), int(line_tab.max())
    if hi - lo > 4 * line_tab.size:
        return dict(zip(*(a.tolist() for a in np.unique(line_tab, return_counts=True))))
    c = np.bincount(line_tab - lo)
    nz = np.nonzero(c)[0]
    return dict(zip((nz + lo).tolist(), c[nz].tolist()))


def add_sums(a: tuple, b: tuple) -> tuple:
    """Element-wise sum of two six-tuples of sums (an empty tuple counts as zeros)."""
    if not a:
        return tuple(b)
    if not b:
        return tuple(a)
    return tuple(x + y for x, y in zip(a, b))


def fit(sums: tuple) -> tuple[float, float] | None:
    """(alpha s/s, beta s/block) of ``t = alpha n + beta m`` by least squares with both >= 0 (the better
    one-term fit where the two-term one has a negative term or is singular); None without data."""
    if len(sums) != N_SUMS:
        return None
    snn, snm, smm, snt, smt, stt = sums
    det = snn * smm - snm * snm
    if det > 1e-12 * snn * smm:
        a = (snt * smm - smt * snm) / det
        b = (smt * snn - snt * snm) / det
        if a >= 0.0 and b >= 0.0:
            return a, b
    best = None
    for sxx, sxt, pair in ((snn, snt, lambda c: (c, 0.0)), (smm, smt, lambda c: (0.0, c))):
        if sxx > 0.0:
            c = max(0.0, sxt / sxx)
            res = stt - 2.0 * c * sxt + c * c * sxx
            if best is None or res < best[0]:
                best = (res, pair(c))
    return None if best is None else best[1]


@dataclass
class Planned:
    """What the windows planned so far add up to."""
    seconds: float = 0.0        #: planned seconds
    nominal_s: float = 0.0      #: their blocks' nominal seconds
    blocks: int = 0
    last_line: int = 0          #: the last program line they reach
    sums: tuple = ()            #: :func:`line_sums`, added up

    def add(self, window) -> None:
        """Add a :class:`~hexacnc.planner.window.Window`."""
        self.seconds += float(window.plan.duration_s)
        self.nominal_s += float(window.nominal_s)
        self.blocks += int(window.blocks)
        self.last_line = max(self.last_line, int(window.last_line))
        self.sums = add_sums(self.sums, window.time_sums)


@dataclass(frozen=True)
class Counted:
    """The validator's count of the program so far (all of it once ``whole``)."""
    line: int
    nominal_s: float
    blocks: int
    whole: bool


def unplanned_s(planned: Planned, total_lines: int, counted: Counted | None) -> float:
    """Estimated seconds of the program's part not planned yet: the fit of the windows planned so far applied
    to the validator's totals (``counted.whole``), or to its counts so far scaled to the program's lines where
    it is ahead of the planner; else the planned seconds per program line.  0 before anything is planned."""
    if planned.seconds <= 0.0 or planned.blocks <= 0:
        return 0.0
    done = max(1, planned.last_line)
    if counted is not None and counted.whole:
        blocks_rest = max(0, counted.blocks - planned.blocks)
        rest = rest_s(planned.sums, counted.nominal_s - planned.nominal_s, blocks_rest)
        return planned.seconds * blocks_rest / planned.blocks if rest is None else rest
    if counted is not None and counted.line > done:
        rest = rest_from_counted(planned.sums, planned.nominal_s, planned.blocks, counted.line, counted.nominal_s,
                                 counted.blocks, total_lines)
        if rest is not None:
            return rest
    return planned.seconds * max(0, total_lines - done) / done


def rest_from_counted(sums: tuple, planned_nominal_s: float, planned_blocks: int, counted_line: int,
                      counted_nominal_s: float, counted_blocks: int, total_lines: int) -> float | None:
    """Before the validation has counted the whole program: its counts up to ``counted_line`` (nominal seconds,
    blocks) scaled to the program's ``total_lines``, less what is planned, through :func:`rest_s`.  None where
    there is no count or no fit."""
    if counted_line <= 0 or counted_blocks <= 0:
        return None
    k = float(total_lines) / counted_line
    return rest_s(sums, counted_nominal_s * k - planned_nominal_s, int(round(counted_blocks * k)) - planned_blocks)


def rest_s(sums: tuple, nominal_rest_s: float, blocks_rest: int) -> float | None:
    """Estimated seconds of the unplanned rest (its nominal seconds and blocks, clipped at 0); None where
    the sums hold no fit."""
    ab = fit(sums)
    if ab is None:
        return None
    return ab[0] * max(0.0, float(nominal_rest_s)) + ab[1] * max(0, int(blocks_rest))
