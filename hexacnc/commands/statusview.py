"""Compact operator view of a status reply: at most 24 lines of at most 80 characters
(``hexacnc status --watch``; ``hexacnc status`` prints it above the details)."""
from __future__ import annotations

import math
from typing import Any

from .send import fmt_duration, progress_of

WIDTH, HEIGHT = 80, 24


def fixed(v: float, d: int = 3, w: int = 0) -> str:
    """A finite number with d decimals in at least w characters, never '-0.000' (a rounding of a tiny
    negative value)."""
    return f"{(v if round(v, d) != 0 else 0.0):{w}.{d}f}"


def _n(v: Any, w: int = 9, d: int = 3) -> str:
    """v in w characters with d decimals ('-' if not a finite number)."""
    if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)):
        return f"{'-':>{w}}"
    return fixed(v, d, w)


def _row(label: str, v: Any) -> str:
    """A pose row under the x y z, a b c header (10 and 9 wide): every number after a space, however wide
    (a machine z of -1150.004 ran into the y before it)."""
    if not isinstance(v, (list, tuple)) or len(v) < 6:
        return f"{label:<8} -"
    return f"{label:<8}" + "".join(" " + _n(x, 9, 3) for x in v[:3]) + "".join(" " + _n(x, 8, 3) for x in v[3:6])


def format_compact(st: dict) -> str:
    """The operator's view (see module doc)."""
    pr = progress_of(st)
    ov = st.get("overrides") or {}
    tool = st.get("tool") or {}
    wo = st.get("work_offset") or {}
    feed = st.get("feed") or {}
    tip = st.get("tool_tip") or {}
    enabled = "on" if st.get("drives_enabled") else "OFF"
    out = [f"hexacnc  {st.get('state', '?').upper():<9} drives {enabled:<3}  "
           f"ref {'yes' if st.get('referenced', True) else 'NO':<3}  ctl {str(st.get('controller') or '-')[:34]}"]
    why = st.get("why_idle")
    if why:
        out.append(f"why      {why}")
    out.append(f"{'':8}{'x':>10}{'y':>10}{'z':>10}{'a':>9}{'b':>9}{'c':>9}")
    out.append(_row("machine", tip.get("machine") or st.get("pose_cmd")))
    out.append(_row(f"work{wo.get('name', '')[1:]:>4}", tip.get("work")))
    out.append(_row("platform", st.get("pose_cmd")))
    m1 = "" if "optional_stop" not in ov else f"   M1 {'stops' if ov['optional_stop'] else 'skipped'}"
    out.append(f"tool     T{tool.get('number', 0)} length {_n(tool.get('length_mm'), 1, 3)} mm   "
               f"offset {wo.get('name', '-')}{m1}")
    fp = feed.get("programmed_mm_min")
    out.append(f"feed     prog {_n(fp, 1, 0) if fp is not None else '-'} mm/min  actual "
               f"{_n((feed.get('actual_mm_s') or 0.0) * 60.0, 1, 0)} mm/min  override "
               f"{_n(100 * ov.get('feed', 1.0), 1, 0)} %  rapid {_n(100 * ov.get('rapid', 1.0), 1, 0)} %")
    if pr:
        pct = pr.get("percent")
        out.append(f"program  {str(pr.get('name') or '-')[:30]}  line {pr.get('line', st.get('line'))}  "
                   f"{_n(pct, 1, 1)} %  elapsed {fmt_duration(st.get('elapsed_s'))}  "
                   f"left {fmt_duration(st.get('remaining_s'))}")
    if st.get("block"):
        out.append(f"block    {st['block'].strip()}")
    if st.get("modal"):
        out.append(f"modal    {st['modal']}")
    if st.get("message"):
        out.append(f"MSG      {st['message']}")
    jog = st.get("jog")
    if isinstance(jog, dict):
        out.append(f"jog      {jog.get('axis')} {jog.get('frame')} {'continuous' if jog.get('continuous') else 'step'}"
                   f" {'stopping' if jog.get('stopping') else ''}")
    f = st.get("fault")
    if isinstance(f, dict):
        out.append(f"FAULT    {f.get('code', '')}: {f.get('message', '')}")
    return "\n".join(line[:WIDTH] for line in out[:HEIGHT])
