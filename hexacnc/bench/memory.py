"""Planning memory for ``hexacnc bench plan`` (``memory``): peak RSS of planning a long CAM program made by
repeating the body of 3D_Chips.ngc (bench placement, feeds as programmed), each size in its own process,
window by window as the daemon plans (:func:`hexacnc.planner.window.plan_windows`, blocks streamed by the
interpreter), and the per-line slope extrapolated to the 1e6-line target (issue 19: <= 500 MB whatever the
length).  ``hexacnc bench stream`` measures a 1e6-line program directly."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

#: repeats of the 3D_Chips body measured (4712 lines each)
REPEATS = (1, 4)
TARGET_LINES = 1_000_000
TARGET_RSS_MB = 500.0

_CHILD = r"""
import dataclasses, json, re, resource, sys, time
from pathlib import Path
from hexacnc.bench.memory import repeated_program
from hexacnc.bench.placement import _place
from hexacnc.bench.toppra_peer import lift_workspace
from hexacnc.config import load_config
from hexacnc.gcode.textstream import iter_text_blocks
from hexacnc.gcode.factory import machine_defaults
from hexacnc.planner.window import plan_windows
text, n = repeated_program(Path(sys.argv[1]), 1)
cfg = lift_workspace(load_config(sys.argv[3] or None))
_prog, wo = _place(text, "once.ngc", cfg)
cfg = cfg.replace(planner=dataclasses.replace(cfg.planner, work_offset_mm=tuple(wo)))
del _prog
text, n = repeated_program(Path(sys.argv[1]), int(sys.argv[2]))
t0 = time.process_time()
dur, nb, nw = 0.0, 0, 0
for w in plan_windows(iter_text_blocks(text, "repeated.ngc", **machine_defaults(cfg)), cfg):
    dur, nb, nw = dur + w.plan.duration_s, nb + w.blocks, nw + 1
cpu = time.process_time() - t0
print(json.dumps({"lines": n, "blocks": nb, "windows": nw, "duration_s": dur, "planning_cpu_s": cpu,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}))
"""


def repeated_program(src: Path, repeats: int) -> tuple[str, int]:
    """The header (first 23 lines) and ``repeats`` copies of the rest without M2/M30/%: (text, lines).

    3D_Chips.ngc's body starts with the feed move that sets G1 and the cutting feed (line 24) and ends with
    a G0 retract: every copy starts with that line, so it is cut in G1 at its feed as the original is (a
    copy that started one line later ran in the G0 the previous copy left, all rapids: no CAM smoothing)."""
    lines = src.read_text(encoding="utf-8", errors="replace").split("\n")
    head = lines[:23]
    body = [ln for ln in lines[23:] if not re.search(r"M0*(2|30)\b", ln) and ln.strip() != "%"]
    out = head + body * int(repeats) + ["M2", ""]
    return "\n".join(out), len(out) - 1


def bench_memory(corpus: Path, config: str | None, repeats=REPEATS) -> dict:
    src = corpus / "3D_Chips.ngc"
    if not src.is_file():
        return {"skipped": f"no file {src}"}
    rows = []
    for r in repeats:
        p = subprocess.run([sys.executable, "-c", _CHILD, str(src), str(r), config or ""], capture_output=True,
                           text=True, timeout=3600)
        if p.returncode != 0:
            rows.append({"repeats": r, "failed": p.stderr.strip().splitlines()[-1:] or ["?"]})
            continue
        row = json.loads(p.stdout.strip().splitlines()[-1])
        row["repeats"] = r
        row["real_time_ratio_cpu"] = round(row["duration_s"] / max(row["planning_cpu_s"], 1e-9), 1)
        rows.append(row)
    ok = [r for r in rows if "peak_rss_mb" in r]
    out = {"program": "3D_Chips.ngc body repeated (bench placement, programmed feeds)", "sizes": rows,
           "target_lines": TARGET_LINES, "target_peak_rss_mb": TARGET_RSS_MB}
    if len(ok) >= 2:
        a, b = ok[0], ok[-1]
        slope = (b["peak_rss_mb"] - a["peak_rss_mb"]) / max(b["lines"] - a["lines"], 1)
        est = a["peak_rss_mb"] + slope * (TARGET_LINES - a["lines"])
        out.update({"rss_mb_per_1000_lines": round(1000 * slope, 2), "extrapolated_rss_mb_at_target": round(est),
                    "within_target": bool(est <= TARGET_RSS_MB),
                    "note": "windowed planning as in the daemon (the program text is held, ~30 bytes per line; "
                            "blocks, grid and table per window)"})
    return out
