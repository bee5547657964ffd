"""Program I/O (M62-M68, M66) for the daemon: checked against ``[io]``, placed on the plan's rows.

Before anything moves, :func:`check_io` refuses a program that uses

* any I/O while ``[io]`` maps nothing ("refused, not silently ignored"),
* a digital output P with no ``[io] digital_out_<P>``,
* M66 (wait on an input) and M67/M68 (analog outputs): not supported yet (``unsupported``),

naming the line, the M code and the channel.  :func:`plan_with_io` replaces each M62-M65 block by a
marker event the planner places like a coolant change (no stop), plans, then turns the markers'
table indices into the rows' triggers (:class:`IoActions`):

* M64/M65 (immediate): where the program reaches them: the end of the preceding motion (the planner
  stops the path at such an event, as at M7-M9), or after a dwell / pause / spindle or tool change
  that comes before them in the program;
* M62/M63 (synchronised): the first row after that stop (and any hold before the next motion): the
  row where the next motion starts.

:class:`IoCursor` (in :class:`~hexacnc.daemon.program.ProgramSource`) packs the changes into the
flags of the first row produced at or after each trigger (:mod:`.dioloop` takes them from there in
the hot loop); it is part of the source's snapshot, so a rewind re-produces them exactly once.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ..errors import GcodeError
from ..gcode import blocks as B
from ..setpoint import FLAG_DWELL
from .dioloop import SLOTS, encode, pack_row

_HOLDS = (B.DWELL, B.PAUSE, B.OPTIONAL_PAUSE, B.SPINDLE, B.TOOL_CHANGE)


_IO_WORD = re.compile(r"m\s*0*6[2-8](?![\d.])", re.IGNORECASE)


_IO_DIGITS = re.compile(r"6[2-8]")
#: the pattern of :func:`has_io_words` for :func:`.progtext.scan` (tried where its digits are)
IO_WORDS = (lambda s: _IO_DIGITS.search(s) is not None, _IO_WORD)


def has_io_words(text) -> bool:
    """Does the program text (str or pieces) contain an M62-M68 word (it is then planned whole, its outputs
    placed on the rows: :func:`plan_with_io`)?  A word inside a comment counts too (a harmless
    whole-program plan)."""
    from .progtext import scan
    return bool(scan({"io": IO_WORDS}, text))


def _mcode(ex: dict) -> str:
    if ex.get("op") == "digital_out":
        return {(True, True): "M62", (True, False): "M63", (False, True): "M64",
                (False, False): "M65"}[(bool(ex["synchronized"]), bool(ex["value"]))]
    if ex.get("op") == "analog_out":
        return "M67" if ex.get("synchronized") else "M68"
    return "M66"


def check_io(cfg, blocks, waits: bool = False) -> None:
    """Refuse (``GcodeError`` with the line) I/O the machine description does not map; M66 only
    where the caller synchronises on it (``waits``: :mod:`.probeprog`) and on a mapped digital input."""
    io = cfg.io
    for b in blocks:
        if b.kind != B.IO:
            continue
        ex = b.extra or {}
        m, n = _mcode(ex), int(ex.get("index", -1))
        if ex.get("op") == "wait_input":
            if ex.get("input") != "digital":
                raise GcodeError(f"{m} E{n}: analog inputs are not supported (no [io] mapping for them)",
                                 line=int(b.line), code="unsupported")
            if not waits:
                raise GcodeError(f"{m} P{n} (wait on an input) outside a synchronised program run",
                                 line=int(b.line), code="unsupported")
            if n not in io.digital_in:
                raise GcodeError(f"{m} P{n}: digital input {n} is not mapped ([io] digital_in_{n} is missing)",
                                 line=int(b.line), code="io")
            continue
        if ex.get("op") == "analog_out":
            raise GcodeError(f"{m} E{n}: analog outputs are not supported (no [io] mapping for them)",
                             line=int(b.line), code="unsupported")
        if io.empty:
            raise GcodeError(f"{m} P{n}: the machine description maps no I/O ([io] is empty or absent)",
                             line=int(b.line), code="io")
        if n not in io.digital_out:
            raise GcodeError(f"{m} P{n}: digital output {n} is not mapped ([io] digital_out_{n} is missing)",
                             line=int(b.line), code="io")


@dataclass(frozen=True)
class IoActions:
    """Output changes of a plan: ``index`` (n,) table indices, ascending; ``code`` (n,) packed changes."""
    index: np.ndarray
    code: np.ndarray


def _markers(cfg, blocks) -> tuple[list, list]:
    """Blocks with M62-M65 replaced by coolant marker events; per marker ``(code, synchronised,
    a hold comes first)``."""
    out, info = [], []
    kinds = [b.kind for b in blocks]
    last_motion = -1
    for k, b in enumerate(blocks):
        if b.kind in B.MOTION_KINDS:
            last_motion = k
        if b.kind != B.IO:
            out.append(b)
            continue
        ex = b.extra
        drive, bit = cfg.io.digital_out[int(ex["index"])]
        if ex["synchronized"]:
            nxt = next((j for j in range(k + 1, len(kinds)) if kinds[j] in B.MOTION_KINDS), len(kinds))
            span = kinds[last_motion + 1:nxt]
        else:
            span = kinds[last_motion + 1:k]
        info.append((encode(drive, bit, bool(ex["value"])), bool(ex["synchronized"]),
                     any(x in _HOLDS for x in span)))
        out.append(B.Block(B.COOLANT, b.line, coolant=("io", len(info) - 1)))
    return out, info


def _after_hold(flag_tab, j: int, window: int) -> int:
    """The first index after a hold (FLAG_DWELL run) that starts within ``window`` of ``j``."""
    n = len(flag_tab)
    d = next((i for i in range(j, min(n, j + window + 1)) if flag_tab[i] & FLAG_DWELL), None)
    if d is None:
        return j
    while d < n and flag_tab[d] & FLAG_DWELL:
        d += 1
    return min(d, n - 1)


def plan_with_io(blocks, cfg, planner_plan, **kw):
    """``planner_plan(blocks, cfg, **kw)`` with the program's M62-M65 placed on the plan's rows
    (``plan.io_actions``: :class:`IoActions` or None without I/O); :func:`check_io` first."""
    blocks = list(blocks)
    check_io(cfg, blocks)
    if not any(b.kind == B.IO for b in blocks):
        plan = planner_plan(blocks, cfg, **kw)
        plan.io_actions = None
        return plan
    marked, info = _markers(cfg, blocks)
    plan = planner_plan(marked, cfg, **kw)
    window = int(round(plan.filter_s / plan.dt)) + 3
    ft = np.asarray(plan.flag_tab)
    at: dict[int, int] = {}      # marker -> table index (the planner may list it twice: hold and position)
    for t, _line, kind, value in plan.events:
        if kind == B.COOLANT and isinstance(value, tuple) and value[:1] == ("io",):
            j = min(len(ft) - 1, int(round(t / plan.dt)))
            at[value[1]] = max(j, at.get(value[1], j))
    idx, codes = [], []
    for n, (code, sync, hold) in enumerate(info):
        j = at[n]
        idx.append(_after_hold(ft, j, window) if sync or hold else j)
        codes.append(code)
    order = np.argsort(np.asarray(idx, dtype=np.int64), kind="stable")
    plan.io_actions = IoActions(np.asarray(idx, dtype=np.int64)[order], np.asarray(codes, dtype=np.int64)[order])
    return plan


class IoCursor:
    """Packs a plan's output changes into the rows a :class:`PlanSampler` produces (see the module)."""

    def __init__(self, actions: IoActions):
        self.a = actions
        self.pos = 0

    def mark(self, rows: np.ndarray, table_idx: np.ndarray) -> None:
        """``rows`` (n, ROW) just produced, ``table_idx`` (n,) their plan table indices."""
        a, n = self.a, len(rows)
        if self.pos >= len(a.index) or n == 0:
            return
        i = int(np.searchsorted(table_idx[:n], a.index[self.pos], side="left"))
        while i < n and self.pos < len(a.index):
            if a.index[self.pos] > table_idx[i]:
                i = int(np.searchsorted(table_idx[:n], a.index[self.pos], side="left"))
                continue
            take = []
            while self.pos < len(a.index) and a.index[self.pos] <= table_idx[i] and len(take) < SLOTS:
                take.append(int(a.code[self.pos]))
                self.pos += 1
            rows[i, 7] = float(pack_row(int(rows[i, 7]), take))
            i += 1
